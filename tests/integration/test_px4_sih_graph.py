"""The whole graph against the real PX4 (v1.16 SITL, SIH as the plant): ``--autopilot px4-sih``.

Runs ``run_scenario --autopilot px4-sih`` briefly (``FLIGHT_S`` after ibvs/start) as a user
would, against ``../shared/px4-sitl`` (SKIPPED when absent: a user's clone does not have it),
with the shipped onboard params.yaml, on the system clock, in real time. What is asserted holds
on this 2-core machine under load (docs/px4_sih.md has the measured figures of whole flights):

- PX4 took off itself (the harness as the pilot's GCS arms it) and was brought to the
  scenario's start ({I}, from PX4's ground truth through the NED -> {I} map);
- the cameras were rendered from PX4's ground truth (frames published, ground truth at the
  rate asked with SET_MESSAGE_INTERVAL) and the window was detected in them (preflight);
- the graph engaged: the supervisor left IDLE for WINDOW, the bridge reached ``engaged``
  (OFFBOARD on an armed vehicle it did not arm), and forces answered images (latency);
- the vehicle approached the window: x grew towards the wall, no collision within FLIGHT_S.

Not asserted: a failsafe or the whole flight's success (it does not succeed in real time on
this machine, docs/px4_sih.md).

Opt-in (``IBVS_PX4_SIH_TEST=1``), not part of ``make test``: in the first fresh-clone CI runs
with it, PX4 SIH (at nice -5, real time) and px4_sim's rendering beside the lockstep
whole-graph tests on the other worker loaded 2 cores so far that the pad-killed repeat ended
in "no pad after 10 s of blind crossing" (its restarted pad detector logged nothing; alone the
run is bit-identical to the reference) and, at load 13, the reference run timed out; and
PX4's own hold missed the start by 1 m in height in one of two CI runs.
Run it alone: ``IBVS_PX4_SIH_TEST=1 .venv/bin/python -m pytest -s
tests/integration/test_px4_sih_graph.py``.
"""
import json
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from ibvs_harness.px4_scenario import in_box, START_SPEED_TOL_MPS, START_TOLERANCE_M
from ibvs_sim.core.px4_plant import find_px4_sitl
from ibvs_sim.core.world import load_world

REPO = Path(__file__).resolve().parents[2]
FLIGHT_S = 4.0                 # s (system clock) of flight after ibvs/start (the window is
#                                reached after 5 s at the earliest: docs/px4_sih.md)
RUN_TIMEOUT_S = 400            # s (wall), the whole run_scenario process
MIN_APPROACH_M = 0.1           # x gained towards the wall within FLIGHT_S
OPT_IN = 'IBVS_PX4_SIH_TEST'   # =1: run (alone); else skipped (see the module doc)

# one SITL at a time, on one pytest-xdist worker (as the bridge's SITL tests)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group('sitl')]


@pytest.fixture(scope='module')
def px4_run(tmp_path_factory):
    """Run the px4-sih scenario once; return (exit code, summary, output, node logs)."""
    if os.environ.get(OPT_IN) != '1':
        pytest.skip(f'px4-sih whole-graph test is opt-in: set {OPT_IN}=1 and run it alone '
                    '(real-time PX4 + rendering starves the lockstep tests run beside it)')
    try:
        find_px4_sitl(cwd=str(REPO))
    except FileNotFoundError as exc:
        pytest.skip(f'PX4 SITL absent, px4-sih test skipped: {exc}')
    root = tmp_path_factory.mktemp('px4sih')
    cmd = [sys.executable, '-m', 'ibvs_harness.run_scenario', '--autopilot', 'px4-sih',
           '--run-name', 'brief', '--results-root', str(root), '--no-bag', '--no-plots',
           '--px4-flight-s', str(FLIGHT_S), '--timeout', str(RUN_TIMEOUT_S - 60)]
    proc = subprocess.run(cmd, cwd=str(REPO), env=dict(os.environ), capture_output=True,
                          text=True, timeout=RUN_TIMEOUT_S)
    path = root / 'brief' / 'summary.json'
    assert path.exists(), proc.stdout[-3000:] + proc.stderr[-3000:]
    log_files = sorted((path.parent / 'logs').glob('*.log'))
    logs = ''.join(f.read_text(errors='replace') for f in log_files)
    return proc.returncode, json.loads(path.read_text()), proc.stdout + proc.stderr, logs


def test_px4_flies_the_graph_towards_the_window(px4_run):
    code, summary, out, logs = px4_run
    run = summary['run']
    assert code != 2 and not run.get('error'), out[-4000:]
    assert run['autopilot'] == 'px4-sih'
    assert run['px4_parameters']['SIH_MASS'] == pytest.approx(1.676)
    # PX4 took off itself and the harness brought its ground truth to the start, at rest,
    # within the harness's own tolerances (0.2 m until 66b7bff, 0.5 m since: this test kept
    # 0.25 m and failed at 0.29 m on 2026-11-27)
    world = load_world()
    start = np.array(run['start_pose_I'])
    assert np.linalg.norm(start - world.initial_position_I) < START_TOLERANCE_M, start
    assert in_box(start, world.random_box), start                  # SPEC's random-start box
    # judged < START_SPEED_TOL_MPS on the same sample, stored rounded to 1 mm/s (0.09996 m/s
    # is stored as 0.1: this test failed on it, 2026-11-28)
    assert run['start_speed_mps'] <= START_SPEED_TOL_MPS, run['start_speed_mps']
    # PX4's own estimator on the relayed motion capture (params.yaml px4_sim mocap_rate_hz)
    assert run['px4_estimator'] == 'mocap' and run['px4_parameters']['EKF2_GPS_CTRL'] == 0
    # the cameras were rendered from PX4's ground truth, at the rate asked
    timing = summary['timing']
    assert timing['pacing'] == 'px4_sih'
    assert timing['frames_published'] > 0
    assert timing['ground_truth_rate_hz'] > 40.0, timing          # asked 100, default 25
    assert timing['mocap_sent'] > 0, timing
    # the graph answered the images and engaged PX4's OFFBOARD itself, on an armed vehicle
    assert timing['frames_answered'] > 0 and timing['latency_median_ms'] > 0.0
    modes = [m['mode'] for m in summary['modes']]
    assert modes and modes[0] == 1, modes                         # WINDOW
    # the bridge's own log: summary['bridge'] samples /diagnostics at 1 Hz and missed an
    # engagement of 1.3 s on 2026-11-27 (a starved run: forces too old, held, FAILSAFE)
    states = [row.get('engage_state') for row in summary['bridge']]
    assert 'engage: set_mode -> engaged' in logs, (states, logs[-3000:])
    assert 'ibvs/start: start accepted' in out       # the supervisor's answer (7ecf05d)
    # and flew towards the window (x along its normal), into no wall
    assert run['max_x_I'] - start[0] > MIN_APPROACH_M, (start, run['max_x_I'], modes)
    assert not any(e.get('type') == 'collision' for e in run['events']), run['events']
