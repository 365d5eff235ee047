"""What the fault tests on real firmware in lockstep check of a run (PX4 and ArduPilot alike)."""
from __future__ import annotations

import json
from pathlib import Path


def killed_bridge_run(results_root: Path, run_name: str, autopilot: str) -> dict:
    """Fly the mission with the bridge killed 0.5 s into WINDOW; return its summary.json.

    Checked here: the run fails, never crosses, the supervisor fails safe on the IMU (which
    the bridge published), the firmware's own failsafe lands and disarms the vehicle, and the
    lockstep waits for the dead bridge at most twice (then it is silent: no 50 frames x the
    time-out).
    """
    from ibvs_harness.run_scenario import main
    main(['--autopilot', autopilot, '--run-name', run_name, '--kill-node', 'mavlink_bridge',
          '--kill-at-s', '1.5', '--follow-failsafe', '--results-root', str(results_root),
          '--no-bag', '--no-plots'])
    summary = json.loads((results_root / run_name / 'summary.json').read_text())
    run, timing = summary['run'], summary['timing']
    assert not summary['success'] and summary['window']['crossed'] is False
    assert run['stop_reason'] == 'failsafe, then the autopilot landed and disarmed', run
    assert run['transitions'][-1].startswith('mode WINDOW -> FAILSAFE')
    assert 'IMU stale' in run['transitions'][-1]
    # (how long the lockstep waited for the dead bridge depends on whether the firmware was
    # already flying its setpoints when it died: killed before the OFFBOARD switch showed,
    # none is awaited; the silence itself is a unit test of LockstepGate)
    assert timing['lockstep_timeouts'] <= 2 * 2
    assert summary['landing']['touchdown_speed_mps'] < 1.0
    return summary
