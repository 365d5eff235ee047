"""The campaign runner's ROS-free core (issue 14 item 3): statistics, causes, draws, resume."""
import json
import math
import os

import numpy as np
import pytest

from ibvs_harness import campaign
from ibvs_harness.campaign import CampaignConfig, draw_run, LawSpec, run_campaign, run_specs
from ibvs_harness.campaign_stats import aggregate, failure_cause, format_table, wilson_interval

BOX = {'x': (-2.6, -1.8), 'y': (-0.3, 0.3), 'z': (-1.9, -1.35)}   # docs/spec.md section 2


@pytest.mark.parametrize('k, n, lo, hi', [
    # Newcombe (1998), Statistics in Medicine 17:857-872, Table I, method 3 (Wilson score)
    (81, 263, 0.2553, 0.3662), (15, 148, 0.0624, 0.1605), (0, 20, 0.0, 0.1611),
    (1, 29, 0.0061, 0.1718)])
def test_wilson_interval_matches_newcombe(k, n, lo, hi):
    got = wilson_interval(k, n)
    assert got == pytest.approx((lo, hi), abs=5e-5)


def test_wilson_interval_edges():
    # all successes: upper 1, lower n / (n + z^2) (closed form), 50 / 53.84 = 0.9286
    assert wilson_interval(50, 50) == pytest.approx((50 / (50 + 1.959964 ** 2), 1.0))
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def _summary(success=True, crossed=True, clearance=0.15, landed=True, error=0.01,
             td_speed=0.3, duration=14.0, last_mode=4, law='closed', level=0.2, speed=0.4,
             xi0=(-2.0, 0.1, -1.8), direction=0.0):
    return {'success': success,
            'window': {'crossed': crossed, 'min_clearance_m': clearance,
                       'crossing_offset_m': [0.0, 0.0] if crossed else None,
                       'crossing_speed_mps': speed if crossed else None},
            'landing': {'landed': landed, 'error_m': error if landed else None,
                        'touchdown_speed_mps': td_speed if landed else None},
            'modes': [{'mode': m, 't_start_s': float(m)}
                      for m in ((0, 1, 5) if last_mode == 5 else range(last_mode + 1))],
            'duration_s': duration,
            'run': {'law': law, 'wind_level_mps2': level, 'wall_time_s': 1.0,
                    'initial_position_I': list(xi0), 'wind_direction_rad': direction}}


def test_failure_causes():
    assert failure_cause(_summary()) is None
    f = dict(success=False)
    assert failure_cause(_summary(**f, clearance=-0.01, landed=False)) == \
        'collision after crossing'
    assert failure_cause(_summary(**f, crossed=False, clearance=0.0, landed=False)) == \
        'collision before crossing'
    assert failure_cause(_summary(**f, crossed=False, landed=False, last_mode=5)) == \
        'failsafe in window'
    stalled = _summary(**f, crossed=False, landed=False)
    stalled['modes'] = [{'mode': m, 't_start_s': t}
                        for m, t in ((0, 0.0), (1, 0.0), (2, 5.5), (5, 15.5))]
    assert failure_cause(stalled) == 'failsafe in crossing'
    assert failure_cause(_summary(**f, crossed=False, landed=True)) == 'floor before window'
    assert failure_cause(_summary(**f, crossed=False, landed=False, last_mode=1)) == \
        'stalled before window'
    assert failure_cause(_summary(**f, landed=False, last_mode=3)) == 'no touchdown'
    assert failure_cause(_summary(**f, error=0.11)) == 'landing error'
    assert failure_cause(_summary(**f, td_speed=0.6)) == 'touchdown speed'
    assert failure_cause(_summary(**f, duration=61.0)) == 'duration'


def test_aggregate_statistics_by_hand():
    runs = [_summary(clearance=c, error=e, td_speed=v, speed=sp)
            for c, e, v, sp in [(0.10, 0.01, 0.20, 0.3), (0.20, 0.02, 0.30, 0.4),
                                (0.30, 0.03, 0.40, 0.5)]]
    runs.append(_summary(success=False, error=0.20, td_speed=0.25, speed=0.6))  # landing error
    runs.append(_summary(success=False, crossed=False, landed=False, last_mode=1))  # stalled
    runs.append(_summary(law='other', level=0.0))
    runs.append(_summary(law='other', level=0.0, last_mode=5))  # SPEC met, then FAILSAFE
    rows = aggregate(runs)
    assert [(r['law'], r['wind_level_mps2'], r['runs']) for r in rows] == \
        [('closed', 0.2, 5), ('other', 0.0, 2)]
    assert [r['success_not_shutdown'] for r in rows] == [0, 1]
    assert rows[1]['successes'] == 2 and rows[1]['failure_causes'] == {}
    r = rows[0]
    assert r['successes'] == 3 and r['success_rate'] == pytest.approx(0.6)
    assert r['success_ci95'] == pytest.approx(wilson_interval(3, 5))
    assert r['clearance_min_m'] == pytest.approx(0.10)          # successes only
    assert r['clearance_median_m'] == pytest.approx(0.20)
    assert r['crossing_speed_median_mps'] == pytest.approx(0.45)  # 4 crossed: (0.4 + 0.5) / 2
    assert r['crossing_speed_min_mps'] == pytest.approx(0.3)
    # 4 landed: errors 0.01 0.02 0.03 0.20; median 0.025; p95 (linear) 0.03 + 0.85 x 0.17
    assert r['landing_error_median_m'] == pytest.approx(0.025)
    assert r['landing_error_p95_m'] == pytest.approx(0.1745)
    # touchdown speeds 0.20 0.25 0.30 0.40: p95 = 0.30 + 0.85 x 0.10
    assert r['touchdown_speed_p95_mps'] == pytest.approx(0.385)
    assert r['failure_causes'] == {'landing error': 1, 'stalled before window': 1}
    table = format_table(rows)
    assert '| closed | 0.2 | 3 / 5 | 60.0 % [23.1, 88.2] |' in table
    assert table.splitlines()[-1].endswith('| - | 1 |')       # no failures, 1 not SHUTDOWN


def test_law_spec_parse():
    assert LawSpec.parse('intended') == LawSpec('intended', (('crossing_law', 'intended'),))
    assert LawSpec.parse('paper') == LawSpec('paper', (('disturbance_law', 'paper'),))
    law = LawSpec.parse('stiff:crossing_law=closed, crossing.kf=3.5')
    assert law == LawSpec('stiff', (('crossing_law', 'closed'), ('crossing.kf', 3.5)))
    for bad in ('robust', 'a b:x=1', 'x:kf', ''):
        with pytest.raises(ValueError):
            LawSpec.parse(bad)


def test_the_cores_start_from_the_node_defaults_and_take_the_files_blocks():
    """core_configs reads a parameter file as the nodes do: code defaults, /**, the section."""
    from ibvs_control.core.control_laws import DisturbanceLaw
    from ibvs_harness.core_configs import controller_config, supervisor_config
    assert controller_config({}).disturbance_law == DisturbanceLaw.OBSERVER_INTEGRAL
    data = {'force_controller': {'ros__parameters': {'disturbance_law': 'paper'}},
            'mode_supervisor': {'ros__parameters': {'imu_timeout_s': 0.3}},
            '/**': {'ros__parameters': {'window_layout_file': '', 'no_node_reads': 1}}}
    assert controller_config(data).disturbance_law == DisturbanceLaw.PAPER
    assert supervisor_config(data).imu_timeout_s == 0.3
    assert supervisor_config({}).imu_timeout_s == 0.2
    with pytest.raises(ValueError, match='imu_timeout_s'):          # as the node: a type error
        supervisor_config({'mode_supervisor': {'ros__parameters': {'imu_timeout_s': 'x'}}})


def test_law_overrides_are_checked_against_the_controllers_parameters(tmp_path):
    """Any force_controller parameter, set in the file or not; of its type and range."""
    from ibvs_harness.core_configs import controller_config
    ctrl = controller_config({}, (('observer.tau_s', 0.3), ('crossing.kf', 3)))
    assert (ctrl.observer.tau_s, ctrl.crossing.kf) == (0.3, 3.0)
    for bad, match in ((('no_such', 1.0), 'no such force_controller parameter'),
                       (('window.kp', 'x'), 'window.kp'),
                       (('landing.lateral_scale_min', 1.5), 'outside')):
        with pytest.raises(ValueError, match=match):
            controller_config({}, (bad,))
    cfg = CampaignConfig(name='c', runs=1, levels_mps2=(0.0,), results_root=str(tmp_path),
                         laws=(LawSpec.parse('stiff:crossing.kf=3'),))
    spec = run_specs(cfg, BOX)[0]
    params = campaign.image_run_params(cfg, spec, campaign.run_wind(cfg, spec, 1.676))
    kf = params['force_controller']['ros__parameters']['crossing.kf']
    assert kf == 3.0 and isinstance(kf, float)          # a double, as the node declares it
    bad = CampaignConfig(name='b', runs=1, laws=(LawSpec.parse('x:no_such=1'),))
    with pytest.raises(ValueError, match='no such force_controller parameter'):
        campaign.image_run_params(bad, run_specs(bad, BOX)[0], campaign.run_wind(cfg, spec, 1.0))


def test_draws_are_deterministic_in_the_box_and_shared_by_levels_and_laws():
    a, b = draw_run(14, 7, BOX), draw_run(14, 7, BOX)
    assert a == b and a != draw_run(14, 8, BOX) and a != draw_run(15, 7, BOX)
    xi, psi, _ = a
    assert all(BOX[k][0] <= v <= BOX[k][1] for k, v in zip('xyz', xi))
    assert 0.0 <= psi < 2 * math.pi
    cfg = CampaignConfig(name='t', runs=3, levels_mps2=(0.0, 0.5),
                         laws=(LawSpec.parse('closed'), LawSpec.parse('intended')))
    specs = run_specs(cfg, BOX)
    assert len(specs) == 12
    by_index = {}
    for s in specs:
        by_index.setdefault(s.index, set()).add(
            (s.initial_position_I, s.direction_rad, s.gust_seed))
    assert all(len(v) == 1 for v in by_index.values())
    assert specs[0].run_dir('out') == os.path.join('out', 'runs', 'closed', '0', '0')


def test_campaign_resumes_and_refuses_other_settings(tmp_path):
    """Two feature-level runs (about 1.2 s), then a resume that flies nothing."""
    cfg = CampaignConfig(name='tiny', runs=2, levels_mps2=(0.2,), laws=(LawSpec('params'),),
                         results_root=str(tmp_path))
    messages = []
    first = run_campaign(cfg, workers=1, progress=messages.append)
    assert len(first) == 2 and messages[0].endswith('0 done, 2 to fly on 1 worker(s)')
    path = os.path.join(cfg.out_dir, 'runs', 'params', '0.2', '1', 'summary.json')
    with open(path) as f:
        stored = json.load(f)
    assert stored['run']['wind']['steady_force_I'][2] == pytest.approx(0.3 * 0.2 * 1.676)
    assert stored['run']['failure_cause'] == failure_cause(stored)
    assert stored['run']['transitions'][0] == \
        '-> WINDOW at t = 0.00 s: start requested, window detected'
    messages.clear()
    again = run_campaign(cfg, workers=1, progress=messages.append)
    assert messages == ['campaign tiny: 2 runs, 2 done, 0 to fly on 1 worker(s)']
    assert again == first
    rows = campaign.write_outputs(cfg, again, plots=False)
    assert rows[0]['runs'] == 2
    assert os.path.exists(os.path.join(cfg.out_dir, 'table.md'))
    with pytest.raises(ValueError, match='other settings'):
        run_campaign(CampaignConfig(name='tiny', runs=2, levels_mps2=(0.2,), gust_level=0.5,
                                    laws=(LawSpec('params'),), results_root=str(tmp_path)),
                     workers=1, progress=None)


def test_campaign_stops_after_its_wall_clock_budget(tmp_path):
    cfg = CampaignConfig(name='budget', runs=3, levels_mps2=(0.0,), results_root=str(tmp_path))
    messages = []
    out = run_campaign(cfg, workers=1, progress=messages.append, max_wall_s=0.0)
    assert len(out) == 1 and out[0]['run']['index'] == 0
    assert messages[-1].startswith('  stopped after 0 s of wall clock: 1 / 3 flown')


def test_help_and_bad_arguments(capsys):
    with pytest.raises(SystemExit) as e:
        campaign.parse_args(['--help'])
    assert e.value.code == 0 and '--crossing-law' in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        campaign.parse_args(['--runs', '0'])
    assert e.value.code == 2


def test_estimate_error_reaches_the_feature_sim_and_the_image_level_params(tmp_path):
    """--estimate-error ROLL PITCH (deg): into the run's sim, its manifest and its summary."""
    cfg, *_ = campaign.parse_args(['--name', 'est', '--runs', '1', '--levels', '0',
                                   '--estimate-error', '1.7', '-1.0',
                                   '--results-root', str(tmp_path)])
    assert cfg.estimate_error_rad == pytest.approx((math.radians(1.7), math.radians(-1.0)))
    assert cfg.model('x')['estimate_error_rad'] == list(cfg.estimate_error_rad)
    assert 'estimate_error_rad' not in CampaignConfig(name='old').model('x')   # old ones resume
    (summary,) = run_campaign(cfg, workers=1, progress=None)
    assert summary['run']['estimate_error_rad'] == pytest.approx(list(cfg.estimate_error_rad))
    spec = run_specs(cfg, BOX)[0]
    params = campaign.image_run_params(cfg, spec, campaign.run_wind(cfg, spec, 1.676))
    assert params['sim']['ros__parameters']['attitude_estimate_offset_rad'] == \
        pytest.approx(list(cfg.estimate_error_rad))
    with pytest.raises(SystemExit) as e:
        campaign.parse_args(['--estimate-error', '12', '0'])
    assert e.value.code == 2


def test_estimate_noise_defaults_to_the_params_file_and_reaches_both_levels(tmp_path,
                                                                            monkeypatch):
    """The estimate's wandering error: the sim's, with params.yaml, unless --estimate-noise."""
    import yaml
    from ibvs_harness import feature_sim
    from ibvs_bringup.graph import default_params_file
    from ibvs_common.core.params import node_values
    from ibvs_sim.config import SimNodeConfig
    installed = default_params_file()
    with open(installed, encoding='utf-8') as f:
        sim = node_values(SimNodeConfig, yaml.safe_load(f), 'sim')   # defaults, /**, section
    expected = (sim['attitude_noise_std_rad'], sim['attitude_noise_tau_s'])
    assert expected[0] > 0.0                       # the default flies an estimate error
    flown = []
    real = feature_sim.run_feature_scenario

    def spy(*args, **kwargs):
        flown.append(args[5])                      # the FeatureSimConfig
        return real(*args, **kwargs)
    monkeypatch.setattr(feature_sim, 'run_feature_scenario', spy)
    args = ['--runs', '1', '--levels', '0', '--results-root', str(tmp_path)]
    cfg, *_ = campaign.parse_args(['--name', 'default', *args])
    assert cfg.estimate_noise is None and 'estimate_noise' not in cfg.model('x')
    (summary,) = run_campaign(cfg, workers=1, progress=None)
    assert (flown[-1].attitude_noise_std, flown[-1].attitude_noise_tau_s) == \
        pytest.approx(expected)
    assert summary['run']['estimate_noise'] == pytest.approx(list(expected))
    spec = run_specs(cfg, BOX)[0]
    params = campaign.image_run_params(cfg, spec, campaign.run_wind(cfg, spec, 1.676))
    assert node_values(SimNodeConfig, params, 'sim')['attitude_noise_std_rad'] == expected[0]

    cfg, *_ = campaign.parse_args(['--name', 'set', '--estimate-noise', '0.5', '3', *args])
    assert cfg.estimate_noise == pytest.approx((math.radians(0.5), 3.0))
    assert cfg.model('x')['estimate_noise'] == pytest.approx([math.radians(0.5), 3.0])
    (summary,) = run_campaign(cfg, workers=1, progress=None)
    assert (flown[-1].attitude_noise_std, flown[-1].attitude_noise_tau_s) == \
        pytest.approx((math.radians(0.5), 3.0))
    params = campaign.image_run_params(cfg, spec, campaign.run_wind(cfg, spec, 1.676))
    sim = params['sim']['ros__parameters']
    assert (sim['attitude_noise_std_rad'], sim['attitude_noise_tau_s']) == \
        pytest.approx((math.radians(0.5), 3.0))
    for bad in (['6', '2'], ['0.5', '-1'], ['nan', '2']):
        with pytest.raises(SystemExit) as e:
            campaign.parse_args(['--estimate-noise', *bad])
        assert e.value.code == 2


STAND_IN = """
import json, os, sys
import yaml
args = sys.argv[1:]
root = args[args.index('--results-root') + 1]
with open(args[args.index('--params-file') + 1]) as f:
    params = yaml.safe_load(f)
os.makedirs(os.path.join(root, 'flight'), exist_ok=True)
with open(os.path.join(root, 'calls.json'), 'w') as f:
    json.dump({'args': args, 'domain': os.environ['ROS_DOMAIN_ID']}, f)
with open(os.path.join(root, 'flight', 'summary.json'), 'w') as f:
    json.dump(json.loads(os.environ['STAND_IN_SUMMARY']), f)
sys.exit(1)
"""


def test_image_level_runs_call_run_scenario_in_their_own_domain(tmp_path, monkeypatch):
    """The whole-graph path with a stand-in for run_scenario (no graph is started).

    The pool's workers are spawned (a fork beside DDS threads can deadlock), so the stand-in
    is a module on PYTHONPATH that the campaign runs as ``python -m``, as it runs run_scenario.
    """
    import subprocess
    import yaml
    (tmp_path / 'stand_in_scenario.py').write_text(STAND_IN)
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(
        [str(tmp_path)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    monkeypatch.setenv('STAND_IN_SUMMARY', json.dumps(
        _summary(success=False, crossed=False, landed=False, last_mode=5)))
    cfg = CampaignConfig(name='img', runs=2, levels_mps2=(0.5,), image_level=True,
                         laws=(LawSpec.parse('stiff:crossing.kf=3.0'),), domain_base=40,
                         results_root=str(tmp_path), scenario_module='stand_in_scenario')
    out = run_campaign(cfg, workers=2, progress=None)
    assert len(out) == 2 and {s['run']['ros_domain_id'] for s in out} <= {'40', '41'}
    assert all(s['run']['failure_cause'] == 'failsafe in window' for s in out)
    assert all(s['run']['image_level'] and not s['run']['feature_level'] for s in out)
    # the calls themselves ran in the pool's workers: read back what each wrote
    run0 = os.path.join(cfg.out_dir, 'runs', 'stiff', '0.5', '0')
    s0 = json.load(open(os.path.join(run0, 'summary.json')))
    assert json.load(open(os.path.join(run0, 'calls.json')))['domain'] in {'40', '41'}
    params = yaml.safe_load(open(os.path.join(run0, 'params.yaml')))
    wind = s0['run']['wind']
    assert params['force_controller']['ros__parameters']['crossing.kf'] == 3.0
    sim = params['sim']['ros__parameters']
    assert sim['wind_gust_amplitude_N'] == pytest.approx(0.3 * 0.5 * 1.676)
    assert sim['seed'] == wind['seed'] == s0['run']['gust_seed']
    assert wind['steady_force_I'][2] == pytest.approx(0.3 * 0.5 * 1.676)
    calls = []

    def fake_run(cmd, stdout, stderr, env, timeout):
        args = cmd[cmd.index('stand_in_scenario') + 1:]
        calls.append((args, None, env['ROS_DOMAIN_ID']))
        root = args[args.index('--results-root') + 1]
        os.makedirs(os.path.join(root, 'flight'), exist_ok=True)
        with open(os.path.join(root, 'flight', 'summary.json'), 'w') as f:
            json.dump(json.loads(os.environ['STAND_IN_SUMMARY']), f)
        return subprocess.CompletedProcess(cmd, 1)

    monkeypatch.setattr(subprocess, 'run', fake_run)
    # in-process (one worker would fork too: check the command on a direct call)
    spec = run_specs(cfg, BOX)[0]
    monkeypatch.setenv('ROS_DOMAIN_ID', '77')
    calls.clear()
    campaign.fly_image_run(cfg, spec)
    args, _, domain = calls[0]
    assert domain == '77'
    assert [float(x) for x in args[args.index('--wind') + 1:][:3]] == \
        pytest.approx(wind['steady_force_I'])
    assert [float(x) for x in args[args.index('--initial-position') + 1:][:3]] == \
        pytest.approx(s0['run']['initial_position_I'])
    assert '--no-bag' in args
    with pytest.raises(ValueError, match='one gust sine'):
        campaign.image_run_params(
            CampaignConfig(name='k', image_level=True, gust_components=3), spec,
            campaign.run_wind(CampaignConfig(name='k', gust_components=3), spec, 1.676))


def test_a_realistic_sensors_run_draws_its_errors_and_flies_the_truth_it_drew(tmp_path):
    """--sensors realistic: each run its own mounts, lever arms, latency, recorded and flown."""
    cfg, *_ = campaign.parse_args(['--name', 'sensors', '--runs', '2', '--levels', '0',
                                   '--sensors', 'realistic', '--camera-rate', '25',
                                   '--results-root', str(tmp_path)])
    assert cfg.sensors == 'realistic' and cfg.camera_rate_hz == 25.0
    specs = campaign.run_specs(cfg, campaign.load_setup(None, ()).world.random_box)
    errors = [campaign.run_sensor_errors(cfg, s) for s in specs]
    assert errors[0] != errors[1] and errors[0] == campaign.run_sensor_errors(cfg, specs[0])
    for e in errors:
        assert 0.015 <= e.latency_s <= 0.040 and e.camera_rate_hz == 25.0
        for cam in e.cameras.values():
            assert max(abs(a) for a in cam.mount_rpy_rad) <= np.radians(1.0)
            assert max(abs(a - b) for a, b in zip(cam.t_BC_true, cam.t_BC_calibrated)) <= 0.005
    summary = campaign.fly_run(cfg, specs[0])
    drawn = summary['run']['sensor_errors']
    assert drawn['latency_s'] == errors[0].latency_s and drawn['camera_rate_hz'] == 25.0
    assert campaign.feature_camera_dt(25.0) == 0.04 and campaign.feature_camera_dt(30.0) == 0.032


def test_a_sensor_profile_field_is_replaced_by_sensor_set_and_a_bad_one_refused(capsys):
    cfg, *_ = campaign.parse_args(['--name', 'sweep', '--sensors', 'realistic',
                                   '--sensor-set', 'mount_error_rad=0.05',
                                   '--sensor-set', 'latency_s=0.06,0.06'])
    assert cfg.sensor_overrides == (('mount_error_rad', 0.05), ('latency_s', (0.06, 0.06)))
    specs = campaign.run_specs(cfg, campaign.load_setup(None, ()).world.random_box)
    e = campaign.run_sensor_errors(cfg, specs[0])
    assert e.latency_s == 0.06 and max(abs(a) for a in e.cameras['down'].mount_rpy_rad) <= 0.05
    with pytest.raises(SystemExit) as exit_:
        campaign.parse_args(['--name', 'x', '--sensor-set', 'no_such_field=1'])
    assert exit_.value.code == 2 and 'no_such_field' in capsys.readouterr().err


def test_an_image_level_realistic_run_gives_the_sim_the_truth_and_the_graph_the_calibration(
        tmp_path, capsys):
    """Image level: the drawn latency on the camera options, two vehicle files that differ
    exactly by the drawn errors, the camera rate in both; ideal sensors add no option."""
    import yaml
    from ibvs_common.core.config import load_vehicle
    from ibvs_common.core.frames import rot_from_euler_zyx
    cfg, *_ = campaign.parse_args(['--name', 'img', '--image-level', '--sensors', 'realistic',
                                   '--camera-rate', '30', '--results-root', str(tmp_path)])
    spec = campaign.run_specs(cfg, BOX)[0]
    errors = campaign.run_sensor_errors(cfg, spec)
    opts = campaign.image_sensor_options(str(tmp_path), errors)
    assert float(opts[opts.index('--camera-latency') + 1]) == pytest.approx(
        1e3 * errors.latency_s)
    assert float(opts[opts.index('--camera-jitter') + 1]) == pytest.approx(3.0)
    assert '--camera-rate' not in opts          # the files carry it
    true = yaml.safe_load(open(opts[opts.index('--true-vehicle') + 1]))
    onboard = yaml.safe_load(open(opts[opts.index('--onboard-vehicle') + 1]))
    nominal = load_vehicle().raw
    for cam, e in errors.cameras.items():
        t, c, n = true['cameras'][cam], onboard['cameras'][cam], nominal['cameras'][cam]
        assert t['rate_hz'] == c['rate_hz'] == 30.0
        # the truth's mount is the calibration's turned by the drawn error, in the optical frame
        R_err = np.asarray(c['R_BC']).T @ np.asarray(t['R_BC'])
        assert np.allclose(R_err, rot_from_euler_zyx(*e.mount_rpy_rad), atol=1e-12)
        assert c['R_BC'] == n['R_BC'] and c['K'] == n['K']
        assert t['K'][0] == pytest.approx(n['K'][0] * e.focal_scale)
        assert t['K'][5] == pytest.approx(n['K'][5] + e.principal_point_px[1])
        assert t['t_BC'] == list(e.t_BC_true) and c['t_BC'] == list(e.t_BC_calibrated)
        assert t['time_offset_s'] == e.time_offset_s
    ideal, *_ = campaign.parse_args(['--name', 'i', '--image-level', '--camera-rate', '30'])
    assert campaign.image_sensor_options(str(tmp_path), campaign.run_sensor_errors(
        ideal, spec)) == ['--camera-rate', '30.0']
    with pytest.raises(SystemExit):
        campaign.parse_args(['--name', 'i', '--image-level', '--command-delay', '20'])
    assert 'feature level' in capsys.readouterr().err


def test_firmware_campaign_options_give_each_worker_its_own_instance(monkeypatch):
    """--autopilot px4|ardupilot: image level only, at most one worker per instance, worker w
    flies instance base + w (parallel runs never race for a free one); it is in the model, so
    a campaign stored with another autopilot does not resume into it."""
    cfg, workers, _, _, _ = campaign.parse_args(['--image-level', '--autopilot', 'ardupilot',
                                                 '--workers', '2'])
    assert cfg.autopilot == 'ardupilot' and workers == 2
    monkeypatch.setenv(campaign.WORKER_ENV, '1')
    assert campaign.firmware_options(cfg) == ['--autopilot', 'ardupilot', '--px4-instance', '2']
    px4 = campaign.parse_args(['--image-level', '--autopilot', 'px4'])[0]
    assert campaign.firmware_options(px4) == ['--autopilot', 'px4', '--px4-instance', '6']
    sim = campaign.parse_args(['--image-level'])[0]
    assert campaign.firmware_options(sim) == []
    assert 'autopilot' not in sim.model('') and cfg.model('')['autopilot'] == 'ardupilot'
    for bad in (['--autopilot', 'px4'],
                ['--image-level', '--autopilot', 'ardupilot', '--workers', '5']):
        with pytest.raises(SystemExit):
            campaign.parse_args(bad)


def test_accel_noise_reaches_the_feature_sim_and_is_refused_at_image_level(tmp_path,
                                                                           monkeypatch):
    """--accel-noise X Y Z (m/s^2 per sample, body FRD): in the manifest and the sim's config."""
    from ibvs_harness import feature_sim
    cfg, *_ = campaign.parse_args(['--name', 'acc', '--runs', '1', '--levels', '0',
                                   '--accel-noise', '0.28', '0.95', '0.80',
                                   '--results-root', str(tmp_path)])
    assert cfg.model('x')['accel_noise_std'] == [0.28, 0.95, 0.80]
    assert 'accel_noise_std' not in CampaignConfig(name='old').model('x')   # old ones resume
    seen = []
    flown = feature_sim.run_feature_scenario

    def spy(*args, **kwargs):
        seen.append(args[5].accel_noise_std_B)
        return flown(*args, **kwargs)

    monkeypatch.setattr(feature_sim, 'run_feature_scenario', spy)
    run_campaign(cfg, workers=1, progress=None)
    assert seen == [(0.28, 0.95, 0.80)]
    for bad in (['--accel-noise', '-1', '0', '0'],
                ['--accel-noise', '0.3', '0.3', '0.3', '--image-level']):
        with pytest.raises(SystemExit) as e:
            campaign.parse_args(bad)
        assert e.value.code == 2
