"""The pure parts of the px4-sih mode (ibvs_sim.core.px4_plant, graph, harness options).

Expected values are computed here by hand from the documents (vehicle.yaml's numbers, PX4's
parameter definitions, the length of a degree on PX4's 6371 km sphere), not by the code.
"""
import math
import os
from types import SimpleNamespace

import numpy as np
import pytest

from ibvs_bringup import graph
from ibvs_harness.px4_sih import px4_boot_parameters
from ibvs_harness.run_scenario import parse_args
from ibvs_common.core.config import load_vehicle
from ibvs_sim.core.px4_plant import (ContactWatch, find_px4_sitl, FrameClock, geodetic_to_ned,
                                     hil_state_sample, NedToI, PositionFilter, px4_home,
                                     Px4PlantError, sih_parameters)
from ibvs_sim.core.events import EventType
from ibvs_sim.core.world import load_world

HOME = (47.397742, 8.545594, 489.4)
M_PER_DEG = 6371000.0 * math.pi / 180.0      # 111194.93 m per degree of arc


def hil(q=(1.0, 0.0, 0.0, 0.0), lat=HOME[0], lon=HOME[1], alt=HOME[2], v=(0, 0, 0),
        rates=(0.0, 0.0, 0.0), t_us=1_000_000):
    """A HIL_STATE_QUATERNION's fields (degE7, mm, cm/s) like pymavlink's message."""
    return SimpleNamespace(time_usec=t_us, attitude_quaternion=list(q),
                           rollspeed=rates[0], pitchspeed=rates[1], yawspeed=rates[2],
                           lat=int(round(lat * 1e7)), lon=int(round(lon * 1e7)),
                           alt=int(round(alt * 1e3)), vx=v[0], vy=v[1], vz=v[2])


def test_sih_parameters_are_the_pelicans():
    p = sih_parameters(load_vehicle())
    # vehicle.yaml: mass 1.676 kg, inertia diag(0.01676, 0.01676, 0.03352), 8.2204 N per rotor
    assert p['SIH_MASS'] == pytest.approx(1.676)
    inertia = (p['SIH_IXX'], p['SIH_IYY'], p['SIH_IZZ'])
    assert inertia == pytest.approx((0.01676, 0.01676, 0.03352))
    assert p['SIH_T_MAX'] == pytest.approx(8.2204)
    assert 4 * p['SIH_T_MAX'] == pytest.approx(2 * 1.676 * 9.80665, rel=1e-3)   # 2 m g
    assert p['SIH_Q_MAX'] == pytest.approx(0.016 * 8.2204)
    assert p['SIH_L_ROLL'] == p['SIH_L_PITCH'] == pytest.approx(0.2 / math.sqrt(2.0))
    assert p['SIH_T_TAU'] == pytest.approx(0.025)
    assert p['SIH_KDV'] == pytest.approx(0.207)
    assert p['MPC_THR_HOVER'] == pytest.approx(16.4359 / 32.8816, abs=2e-4)   # ~ 0.5


def test_boot_parameters_add_home_takeoff_height_and_refuse_a_bad_height():
    boot = px4_boot_parameters({'SIH_MASS': 1.676}, 1.72, HOME, 0.5)
    assert boot['SIH_MASS'] == 1.676 and boot['MIS_TAKEOFF_ALT'] == 1.72
    assert (boot['SIH_LOC_LAT0'], boot['SIH_LOC_LON0'], boot['SIH_LOC_H0']) == HOME
    assert boot['COM_OF_LOSS_T'] == 0.5
    with pytest.raises(ValueError):
        px4_boot_parameters({}, 0.0)


def test_geodetic_to_ned_one_degree_lengths():
    assert geodetic_to_ned(*HOME, HOME) == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    north = geodetic_to_ned(HOME[0] + 1e-5, HOME[1], HOME[2], HOME)
    assert north == pytest.approx([1e-5 * M_PER_DEG, 0.0, 0.0], abs=1e-4)
    east = geodetic_to_ned(HOME[0], HOME[1] + 1e-5, HOME[2] - 1.5, HOME)
    assert east == pytest.approx([0.0, 1e-5 * M_PER_DEG * math.cos(math.radians(HOME[0])),
                                  1.5], abs=1e-4)


def test_px4_home_is_the_float32_parameter():
    lat, lon, alt = px4_home(*HOME)
    # 47.397742 as an IEEE float32 is 47.39774322509765625 (24-bit mantissa, step 2^-18 deg)
    assert lat == 47.39774322509765625 and abs(lat - HOME[0]) < 2 ** -18
    north = geodetic_to_ned(lat, lon, alt, HOME)
    assert north[0] == pytest.approx((lat - HOME[0]) * M_PER_DEG)
    assert 0.12 < north[0] < 0.15                  # PX4 at rest: 0.133 m north of the double


def test_ned_to_I_takes_off_below_the_start():
    world = load_world()
    start = (-2.0, 0.1, -1.82)                  # world.yaml initial_condition
    f = NedToI.from_start(start, world.floor_z, 0.1)
    assert f.to_I([0.0, 0.0, 0.0]) == pytest.approx([-2.0, 0.1, -0.1])  # home, at rest
    assert f.takeoff_altitude(start) == pytest.approx(1.72)
    assert f.to_I([0.0, 0.0, -1.72]) == pytest.approx(start)
    assert f.to_I([1.5, -0.1, 0.0]) == pytest.approx([-0.5, 0.0, -0.1])  # 1.5 m north
    assert f.to_ned(f.to_I([0.3, -0.2, -1.0])) == pytest.approx([0.3, -0.2, -1.0])
    with pytest.raises(Px4PlantError):
        NedToI.from_start((math.nan, 0.0, 0.0), 0.0, 0.1)


def test_hil_state_to_I():
    f = NedToI.from_start((-2.0, 0.1, -1.82), 0.0, 0.1)
    c = math.cos(math.pi / 4)
    m = hil(q=(c, 0.0, 0.0, c), lat=HOME[0] + 1e-5, alt=HOME[2] + 1.72, v=(50, -20, 10),
            rates=(0.1, -0.2, 0.3), t_us=2_500_000)
    s = hil_state_sample(m, HOME, f)
    assert s.t_boot_s == pytest.approx(2.5)
    # 1e-5 deg north (1.112 m) from the take-off point, 1.72 m up
    assert s.xi_I == pytest.approx([-2.0 + 1e-5 * M_PER_DEG, 0.1, -1.82], abs=1e-3)
    assert s.v_I == pytest.approx([0.5, -0.2, 0.1])
    assert s.Omega_B == pytest.approx([0.1, -0.2, 0.3])
    # yaw +90 deg (NED, z down): the body's nose (x_B) points east = y_I
    assert s.R_IB @ np.array([1.0, 0.0, 0.0]) == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    ahead = s.extrapolated(0.1)
    assert ahead.xi_I - s.xi_I == pytest.approx([0.05, -0.02, 0.01])
    assert s.state().xi_I == pytest.approx(s.xi_I)
    with pytest.raises(Px4PlantError):
        hil_state_sample(hil(q=(0.5, 0.0, 0.0, 0.0)), HOME, f)
    with pytest.raises(Px4PlantError):
        hil_state_sample(hil(q=(math.nan, 0.0, 0.0, 1.0)), HOME, f)


def test_position_filter_beats_the_quantisation():
    q = 0.0111                                  # m, 1e-7 deg of latitude
    flt = PositionFilter(0.2)
    raw_err, flt_err = [], []
    for k in range(400):                        # 4 s at 100 Hz, 0.3 m/s north
        t = 0.01 * k
        true = np.array([0.3 * t, 0.0, -1.0])
        fix = np.round(true / q) * q
        p = flt.update(t, fix, [0.3, 0.0, 0.0])
        if t > 1.0:
            raw_err.append(abs(fix[0] - true[0]))
            flt_err.append(abs(p[0] - true[0]))
    assert np.sqrt(np.mean(np.square(flt_err))) < 0.5 * np.sqrt(np.mean(np.square(raw_err)))
    assert max(flt_err) < q
    jump = flt.update(4.01, [5.0, 0.0, -1.0], [0.3, 0.0, 0.0])
    assert jump == pytest.approx([5.0, 0.0, -1.0])          # a jump restarts at the fix
    # the altitude (mm resolution) is never filtered: a body SIH stopped on the ground is there
    landed = flt.update(4.02, [5.0, 0.0, -0.004], [0.0, 0.0, 0.0])
    assert landed[2] == -0.004 and landed[0] == pytest.approx(5.0)


def test_frame_clock_drops_whole_late_periods():
    c = FrameClock(50.0, start_ns=0)
    assert c.due(0) == 0
    assert c.due(19_000_000) is None
    assert c.due(20_500_000) == 20_000_000
    assert c.due(65_000_000) == 60_000_000 and c.dropped == 1   # 40 ms dropped
    assert c.due(80_000_000) == 80_000_000 and c.dropped == 1
    assert c.due_count == 5
    with pytest.raises(Px4PlantError):
        FrameClock(0.0, 0)


def test_contacts_after_take_off_only():
    world = load_world()
    w = ContactWatch(world, 0.33, 0.2, airborne_m=0.3)
    assert w.check(0.0, [-2.0, 0.1, -0.1], [0, 0, 0]) is None        # resting on the floor
    assert w.check(1.0, [-2.0, 0.1, -1.8], [0, 0, 0]) is None        # airborne
    assert w.check(2.0, [0.0, 0.0, -0.12], [0, 0, 0.4]) is None
    td = w.check(2.1, [0.0, 0.0, -0.1], [0, 0, 0.0])
    assert td.type is EventType.TOUCHDOWN and td.speed_mps == pytest.approx(0.4)
    assert w.check(2.2, [0.0, 0.0, -0.1], [0, 0, 0.0]) is None       # once
    w2 = ContactWatch(world, 0.33, 0.2)
    w2.check(0.0, [-2.0, 0.0, -1.5], [0, 0, 0])
    hit = w2.check(0.1, [-0.6, 1.5, -1.5], [1.0, 0, 0])               # the wall beside it
    assert hit.type is EventType.COLLISION and hit.surface == 'wall'


def test_px4_sitl_absent_names_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.delenv('IBVS_PX4_SITL_DIR', raising=False)
    here = str(tmp_path / 'repo' / 'ros2_ws' / 'src' / 'x.py')
    with pytest.raises(FileNotFoundError, match='shared/px4-sitl'):
        find_px4_sitl(cwd=str(tmp_path / 'repo'), here=here)
    sitl = tmp_path / 'shared' / 'px4-sitl'
    sitl.mkdir(parents=True)
    (sitl / 'px4-sih').write_text('#!/bin/sh\n')
    assert find_px4_sitl(cwd=str(tmp_path / 'repo'), here=here) == os.path.normpath(sitl)


def test_px4_sih_graph_talks_to_px4_directly():
    specs = graph.px4_sih_graph(graph.GraphOptions(use_sim_time=False), 6)
    by_name = {s.name: s for s in specs}
    assert specs[0].name == 'px4_sim' and specs[0].executable == 'px4_sim'
    assert by_name['px4_sim'].overrides()['state_url'] == 'udpin:127.0.0.1:19416'
    bridge = by_name['mavlink_bridge'].overrides()
    assert bridge['url'] == 'udpin:127.0.0.1:14546'
    assert not bridge.get('arm_on_start', False)               # the bridge never arms here
    assert not any(s.overrides().get('use_sim_time') for s in specs)
    assert 'auto_start_at_s' not in by_name['mode_supervisor'].overrides()
    with pytest.raises(ValueError):
        graph.px4_sih_graph(graph.GraphOptions(use_sim_time=True), 6)
    with pytest.raises(ValueError):
        graph.px4_urls(10)


def test_autopilot_option_default_is_the_sim():
    assert parse_args([]).autopilot == 'sim'
    opts = parse_args(['--autopilot', 'px4-sih', '--px4-instance', '7'])
    assert (opts.autopilot, opts.px4_instance) == ('px4-sih', 7)
    opts = parse_args(['--autopilot', 'ardupilot', '--px4-instance', '2'])
    assert (opts.autopilot, opts.px4_instance) == ('ardupilot', 2)
    with pytest.raises(SystemExit):
        parse_args(['--autopilot', 'betaflight'])


def test_px4_sih_run_without_px4_fails_clearly(tmp_path, monkeypatch, capsys):
    from ibvs_harness import px4_scenario
    from ibvs_harness.scenario import prepare_out_dir

    def absent():
        raise FileNotFoundError('PX4 SITL not found (looked for px4-sih in /nowhere)')
    monkeypatch.setattr(px4_scenario, 'find_px4_sitl', absent)
    opts = parse_args(['--autopilot', 'px4-sih', '--results-root', str(tmp_path),
                       '--run-name', 'nopx4'])
    prepare_out_dir(opts)
    assert px4_scenario.run_px4_sih(opts) == 2
    assert 'PX4 SITL not found' in capsys.readouterr().err
    import json
    summary = json.loads((tmp_path / 'nopx4' / 'summary.json').read_text())
    assert summary['success'] is False and 'PX4 SITL not found' in summary['run']['error']


def test_state_link_stamps_on_arrival_and_asks_the_sender_for_the_rate():
    import time
    from pymavlink import mavutil
    from ibvs_sim.core.px4_plant import StateLink
    link = StateLink('udpin:127.0.0.1:0', 100.0, request_period_s=0.0, threaded=True)
    sim = mavutil.mavlink_connection(f'udpout:127.0.0.1:{link.local_port}', source_system=6,
                                     source_component=1)
    try:
        sent = []
        for k in range(3):                                # 20 Hz, as SIH's default 25 Hz
            sent.append(time.time_ns())
            sim.mav.hil_state_quaternion_send(0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                              473977432, 85455942, 489400, 0, 0, 0, 0, 0,
                                              0, 0, 0)
            time.sleep(0.05)
        got = link.poll()
        assert len(got) == 3 and link.target == (6, 1)       # PX4's id learnt (1 + instance)
        for (msg, receipt_ns), t_sent in zip(got, sent):
            assert msg.get_type() == 'HIL_STATE_QUATERNION'
            assert 0 <= receipt_ns - t_sent < 40_000_000        # stamped on arrival
        ask = sim.recv_match(type='COMMAND_LONG', blocking=True, timeout=1.0)
        assert ask is not None and ask.command == 511          # SET_MESSAGE_INTERVAL
        assert (ask.target_system, ask.param1, ask.param2) == (6, 115, 10000)
        assert link.poll() == []
    finally:
        link.close()
        sim.close()


def test_renice_threads_sets_every_thread_of_a_sitl_process():
    """Linux keeps a nice value per thread: each task of /proc/PID/task gets it."""
    import subprocess
    import sys
    from ibvs_harness.px4_sih import renice_threads
    code = ('import threading, time\n'
            'for _ in range(3):\n'
            '    threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n'
            'print("up", flush=True)\n'
            'time.sleep(30)\n')
    child = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == 'up'
        tids = [int(t) for t in os.listdir(f'/proc/{child.pid}/task')]
        assert len(tids) == 4                              # main + 3 threads
        assert renice_threads(child.pid, 7) == '4 threads at nice 7'   # no privilege needed
        assert [os.getpriority(os.PRIO_PROCESS, t) for t in tids] == [7] * 4
    finally:
        child.kill()
        child.wait()
    assert renice_threads(child.pid, 7).startswith('not reniced')       # gone: reported


def test_mocap_pose_is_ned_about_home_with_zyx_euler_angles():
    from ibvs_sim.core.px4_plant import MocapRelay
    relay = MocapRelay(HOME, 50.0)
    # 30 deg yaw about NED z (down), then nothing else: q = (cos 15, 0, 0, sin 15)
    half = math.radians(15.0)
    p, (roll, pitch, yaw) = relay.pose(hil(q=(math.cos(half), 0.0, 0.0, math.sin(half)),
                                           lat=HOME[0] + 1e-5, alt=HOME[2] + 1.5))
    assert p == pytest.approx([1e-5 * M_PER_DEG, 0.0, -1.5], abs=1e-3)   # 1.11 m N, 1.5 m up
    assert (roll, pitch, yaw) == pytest.approx((0.0, 0.0, math.radians(30.0)), abs=1e-9)
    # a 10 deg roll about the body x axis alone
    half = math.radians(5.0)
    _, (roll, pitch, yaw) = relay.pose(hil(q=(math.cos(half), math.sin(half), 0.0, 0.0)))
    assert (roll, pitch, yaw) == pytest.approx((math.radians(10.0), 0.0, 0.0), abs=1e-9)


def test_mocap_relay_sends_at_its_rate_and_the_origin_early_only():
    from unittest import mock
    from ibvs_sim.core.px4_plant import MocapRelay
    relay = MocapRelay(HOME, 50.0, origin_for_s=2.0)
    mav = mock.Mock()
    for k in range(400):                               # 100 Hz samples for 4 s
        relay.on_sample(mav, hil(lat=HOME[0] + 1e-7 * k), 6, 10.0 + 0.01 * k)
    sent = mav.vision_position_estimate_send.call_args_list
    assert len(sent) == relay.sent == 200              # 50 Hz of 100
    usec, x, y, z, roll, pitch, yaw = sent[-1].args
    assert usec == 0 and x == pytest.approx(398e-7 * M_PER_DEG, abs=2e-3)   # the latest
    origins = mav.set_gps_global_origin_send.call_args_list
    assert len(origins) == 3                          # at 0, 1 and 2 s, then no more
    assert origins[0].args == (6, 473977420, 85455940, 489400)
    # a sample that is not a pose is not sent
    relay.on_sample(mav, hil(q=(math.nan, 0.0, 0.0, 1.0)), 6, 20.0)
    assert relay.sent == 200
    with pytest.raises(Px4PlantError):
        MocapRelay(HOME, 0.0)


def test_mocap_boot_parameters_turn_gps_and_magnetometer_off():
    boot = px4_boot_parameters({}, 1.72, HOME, mocap=True)
    assert (boot['EKF2_GPS_CTRL'], boot['EKF2_EV_CTRL'], boot['EKF2_HGT_REF'],
            boot['EKF2_MAG_TYPE']) == (0, 11, 3, 5)
    assert 'EKF2_EV_CTRL' not in px4_boot_parameters({}, 1.72, HOME)
