"""What every scenario run shares (scenario.py): its log reading, its refusal of bad options."""
from ibvs_bringup.runner import COMPOSED_NAME, container_name
from ibvs_harness.scenario import supervisor_log, supervisor_transitions


def test_the_supervisor_log_is_its_container_s_when_it_has_none_of_its_own(tmp_path):
    logs = tmp_path / 'run' / 'logs'
    logs.mkdir(parents=True)
    (logs / f'{container_name("control")}.log').write_text('')       # --layout grouped
    assert supervisor_log(str(tmp_path / 'run')).endswith(f'logs/{container_name("control")}.log')
    (logs / f'{COMPOSED_NAME}.log').write_text('')                      # --layout composed
    assert supervisor_log(str(tmp_path / 'run')).endswith(f'logs/{COMPOSED_NAME}.log')
    (logs / 'mode_supervisor.log').write_text('')                       # --layout processes
    assert supervisor_log(str(tmp_path / 'run')).endswith('logs/mode_supervisor.log')


def test_supervisor_transitions_are_read_from_its_log(tmp_path):
    log = tmp_path / 'mode_supervisor.log'
    log.write_text(
        '[INFO] [1.0] [mode_supervisor]: mode supervisor ready in IDLE: SupervisorConfig()\n'
        '[INFO] [2.0] [mode_supervisor]: mode IDLE -> WINDOW at t = 1.000 s: start requested\n'
        '[ERROR] [3.0] [mode_supervisor]: a refused message\n'
        '[INFO] [4.0] [mode_supervisor]: mode WINDOW -> FAILSAFE at t = 5.620 s: '
        'window stale for more than 0.5 s in WINDOW\n')
    assert supervisor_transitions(str(log)) == [
        'mode IDLE -> WINDOW at t = 1.000 s: start requested',
        'mode WINDOW -> FAILSAFE at t = 5.620 s: window stale for more than 0.5 s in WINDOW']
    assert supervisor_transitions(str(tmp_path / 'missing.log')) == []


def test_runner_and_run_scenario_refuse_a_missing_parameter_file(tmp_path, capsys):
    """Exit 2 with the reason, no traceback and nothing started (launch_ros only warns)."""
    from ibvs_bringup import runner as runner_cli
    from ibvs_harness import run_scenario
    missing = str(tmp_path / 'typo.yaml')
    assert runner_cli.main(['onboard', '--params-file', missing]) == 2
    assert run_scenario.main(['--params-file', missing, '--results-root', str(tmp_path),
                              '--run-name', 'x']) == 2
    err = capsys.readouterr().err
    assert err.count(f"parameter file '{missing}' cannot be read") == 2
    assert 'Traceback' not in err and not (tmp_path / 'x').exists()


def test_a_failed_run_says_why_on_its_closing_line(tmp_path, capsys):
    """The closing console line of a failed run ends with its cause, and a failsafe's with
    the supervisor's own reason; a success says nothing more; progress lines name modes."""
    from ibvs_common.core.modes import mode_name
    from ibvs_harness.scenario import failure_explanation, finish, RunOptions
    transitions = ['mode IDLE -> WINDOW at t = 1.000 s: auto-start at 1 s, window detected',
                   'mode WINDOW -> FAILSAFE at t = 1.560 s: window stale for more than 0.5 s '
                   'in WINDOW']
    failsafe = {'success': False, 'window': {'crossed': False, 'min_clearance_m': None},
                'landing': {'landed': False}, 'modes': [{'mode': 0}, {'mode': 1}, {'mode': 5}],
                'run': {'transitions': transitions}}
    assert failure_explanation(failsafe) == \
        'failsafe in window (window stale for more than 0.5 s in WINDOW)'
    assert failure_explanation({'success': False, 'run': {'error': 'a node died'}}) == \
        'error: a node died'
    landing = {'success': False, 'window': {'crossed': True, 'min_clearance_m': 0.1},
               'landing': {'landed': True, 'error_m': 0.2, 'touchdown_speed_mps': 0.2},
               'modes': [{'mode': 4}], 'run': {}}
    assert failure_explanation(landing) == 'landing error'
    assert failure_explanation({'success': True}) is None
    opts = RunOptions(run_name='x', results_root=str(tmp_path), plots=False)
    assert finish(opts, failsafe, None) == 1
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.endswith('; failed: failsafe in window (window stale for more than 0.5 s in '
                         'WINDOW)')
    assert [mode_name(m) for m in (0, 4, 5, None, 9)] == ['IDLE', 'SHUTDOWN', 'FAILSAFE', '?',
                                                          '9']
