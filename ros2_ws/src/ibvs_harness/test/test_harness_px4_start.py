"""The PX4 SIH harness's start rule: near the start, and inside SPEC's box of random starts."""
import numpy as np

from ibvs_harness.px4_scenario import at_start, in_box, START_TOLERANCE_M
from ibvs_sim.core.world import load_world

BOX = load_world().random_box          # x [-2.6, -1.8], y [-0.3, 0.3], z [-1.9, -1.35]
START = np.array([-2.0, 0.1, -1.82])   # world.yaml's start, inside the box


def test_the_box_is_world_yaml_s_and_holds_the_reference_start():
    assert BOX['y'] == (-0.3, 0.3) and in_box(START, BOX)
    assert not in_box(START + [0.0, 0.4, 0.0], BOX)


def test_a_pose_near_the_start_but_outside_the_box_does_not_start():
    # s30px4b: y = +0.50, 0.4 m from the start (inside the 0.5 m tolerance), outside the box
    pose = np.array([-1.94, 0.50, -1.83])
    assert np.linalg.norm(pose - START) < START_TOLERANCE_M
    assert not at_start(pose, START, 0.0, BOX)
    assert at_start(np.array([-1.94, 0.25, -1.83]), START, 0.0, BOX)


def test_distance_and_heading_still_count_inside_the_box():
    assert not at_start(np.array([-2.55, 0.1, -1.4]), START, 0.0, BOX)   # in the box, 0.7 m
    assert not at_start(START, START, 0.06, BOX)                          # heading 0.06 rad
    assert at_start(START, START, -0.04, BOX)


def test_a_start_chosen_outside_the_box_is_judged_by_distance_alone():
    start = np.array([-2.0, 0.6, -1.82])          # a user's --initial-position
    assert at_start(start + [0.0, 0.1, 0.0], start, 0.0, BOX)


def test_the_preflight_limit_counts_from_the_end_of_the_firmwares_pre_roll(monkeypatch):
    """A lockstep firmware's pre-roll (boot, take-off, hold) comes before frame 0; the wait
    for it returns at the first truth message, and a pre-roll that never ends stops the run
    after PREROLL_WAIT_S of wall time (a PX4 campaign start was lost: its 137 s pre-roll
    outlasted the preflight's own 120 s)."""
    from types import SimpleNamespace

    import pytest

    from ibvs_harness import run_scenario

    monitor = SimpleNamespace(first_truth_wall=None)
    spins = []

    def spin(dt):
        spins.append(dt)
        if len(spins) == 5:
            monitor.first_truth_wall = 1.0

    run_scenario.wait_for_preroll(monitor, spin)
    assert len(spins) == 5
    monitor.first_truth_wall = None
    monkeypatch.setattr(run_scenario, 'PREROLL_WAIT_S', -1.0)     # the limit has passed
    with pytest.raises(run_scenario._Stop, match='did not hold at the start'):
        run_scenario.wait_for_preroll(monitor, lambda dt: None)
    assert 'px4' in run_scenario.LOCKSTEP_FIRMWARES
    assert 'ardupilot' in run_scenario.LOCKSTEP_FIRMWARES


def test_a_kill_once_engaged_waits_for_the_bridges_engaged_report():
    """``--kill-once-engaged``: the bridge's latest /diagnostics decides (the firmware's
    offboard-loss failsafe applies only once it flies the setpoints); the option needs
    ``--kill-node``."""
    from collections import deque
    from types import SimpleNamespace

    from ibvs_harness import run_scenario

    monitor = SimpleNamespace(bridge_history=deque())
    assert not run_scenario.bridge_engaged(monitor)
    monitor.bridge_history.append({'t': 1.2, 'engage_state': 'set_mode'})
    assert not run_scenario.bridge_engaged(monitor)
    monitor.bridge_history.append({'t': 1.6, 'engage_state': 'engaged'})
    assert run_scenario.bridge_engaged(monitor)
    monitor.bridge_history.append({'t': 2.0, 'engage_state': 'held'})
    assert not run_scenario.bridge_engaged(monitor)
    opts = run_scenario.parse_args(['--kill-node', 'mavlink_bridge', '--kill-once-engaged'])
    assert opts.kill_once_engaged and opts.kill_node == 'mavlink_bridge'
    assert run_scenario.main(['--kill-once-engaged', '--no-plots']) != 0
