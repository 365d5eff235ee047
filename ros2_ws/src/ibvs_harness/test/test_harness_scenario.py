"""What every scenario run shares (scenario.py): its log reading, its refusal of bad options."""
from ibvs_bringup.runner import COMPOSED_NAME
from ibvs_harness.scenario import supervisor_log, supervisor_transitions


def test_the_supervisor_log_is_the_composed_process_s_when_it_has_none_of_its_own(tmp_path):
    assert supervisor_log(str(tmp_path / 'run')).endswith(f'logs/{COMPOSED_NAME}.log')
    (tmp_path / 'run' / 'logs').mkdir(parents=True)
    (tmp_path / 'run' / 'logs' / 'mode_supervisor.log').write_text('')
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
