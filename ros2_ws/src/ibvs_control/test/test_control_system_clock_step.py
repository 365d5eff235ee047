"""A real step back of the system clock under the mode supervisor (opt-in, root, run alone).

The node tests of test_control_nodes.py step the node clock through ``/clock`` (sim time);
rcl sees such a jump and re-arms its timers. Onboard the ROS clock is system time, which rcl
does not watch, so this test steps CLOCK_REALTIME itself: the supervisor flies WINDOW on
inputs stamped with the system time, the clock goes back by ``STEP_S``, the inputs go on
(stamped with the stepped clock) and the supervisor must be in FAILSAFE within
``DETECT_WITHIN_S`` of wall time. It also counts how often a 20 Hz timer on the ROS clock
fired in the second after the step: rcl holds it for the length of the step (that is why
the supervisor reads its clock in every callback rather than relying on its watchdog).

Opt-in (``IBVS_CLOCK_STEP_TEST=1``), never in ``make test``: stepping the machine's clock
would disturb everything running beside it (the SITL flights, timeouts on the wall clock).
The clock is set back to where it would have been (monotonic time elapsed) in any case.
Run it alone: ``IBVS_CLOCK_STEP_TEST=1 .venv/bin/python -m pytest -s
ros2_ws/src/ibvs_control/test/test_control_system_clock_step.py``.
"""
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor

from ibvs_control.mode_supervisor_node import ModeSupervisorNode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_control_nodes import call, Feeder, imu_msg, TAG  # noqa: E402

OPT_IN = 'IBVS_CLOCK_STEP_TEST'
STEP_S = 1.0                 # s, the system clock goes back by this
DETECT_WITHIN_S = 0.1        # s of wall time from the step to FAILSAFE (IMU at 100 Hz)
FRAME_S, IMU_S = 0.02, 0.01


class SteppedClock:
    """Step CLOCK_REALTIME back; :meth:`restore` puts it where it would have been."""

    def __init__(self) -> None:
        self._real0 = self._mono0 = None

    def step_back(self, seconds: float) -> None:
        self._mono0 = time.clock_gettime(time.CLOCK_MONOTONIC)
        self._real0 = time.clock_gettime(time.CLOCK_REALTIME)
        time.clock_settime(time.CLOCK_REALTIME, self._real0 - seconds)

    def restore(self) -> None:
        if self._real0 is not None:
            elapsed = time.clock_gettime(time.CLOCK_MONOTONIC) - self._mono0
            time.clock_settime(time.CLOCK_REALTIME, self._real0 + elapsed)
            self._real0 = None


@pytest.fixture()
def stepped_clock():
    if os.environ.get(OPT_IN) != '1':
        pytest.skip(f'steps the system clock: opt-in, set {OPT_IN}=1 and run it alone')
    try:
        now = time.clock_gettime(time.CLOCK_REALTIME)
        time.clock_settime(time.CLOCK_REALTIME, now)
    except PermissionError:
        pytest.skip('setting CLOCK_REALTIME needs root (CAP_SYS_TIME)')
    clock = SteppedClock()
    yield clock
    clock.restore()


def test_a_step_back_of_the_system_clock_in_window_is_failsafe_at_once(stepped_clock):
    context = rclpy.context.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    sup = ModeSupervisorNode(node_name=f'sup_sysstep_{TAG}', context=context)
    feed = Feeder(context, f'feed_sysstep_{TAG}')
    ticks = []
    feed.node.create_timer(0.05, lambda: ticks.append(time.monotonic()))  # ROS clock
    for node in (sup, feed.node):
        executor.add_node(node)
    xi = np.array([-2.0, 0.0, -1.6])
    next_frame = next_imu = time.monotonic()

    def run_for(seconds: float, until=lambda: False) -> bool:
        """Feed IMU (100 Hz) and frames (50 Hz) stamped with the system clock; spin."""
        nonlocal next_frame, next_imu
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            now_m = time.monotonic()
            t = feed.node.get_clock().now().nanoseconds * 1e-9
            if now_m >= next_frame:
                feed.frame(t, xi, front_flow=np.zeros(3))
                next_frame += FRAME_S
            elif now_m >= next_imu:
                feed.imu.publish(imu_msg(t))
                next_imu += IMU_S
            executor.spin_once(timeout_sec=0.002)
        return until()

    try:
        assert run_for(5.0, lambda: feed.modes == [0])
        run_for(0.3)
        assert call(executor, feed.node, 'ibvs/start').success
        assert run_for(1.0, lambda: feed.modes[-1:] == [1])
        run_for(0.5)
        assert feed.modes == [0, 1]
        ticks_before = len(ticks)
        stepped_clock.step_back(STEP_S)
        t_step = time.monotonic()
        detected = run_for(1.5, lambda: feed.modes[-1:] == [5])
        t_failsafe = time.monotonic() - t_step
        run_for(1.5 - t_failsafe)
        after = [t - t_step for t in ticks[ticks_before:]]
        stepped_clock.restore()
        print(f'\nclock stepped back by {STEP_S} s: FAILSAFE after {t_failsafe * 1e3:.1f} ms '
              f'of wall time; the 20 Hz ROS-clock timer fired {len(after)} times in the '
              f'1.5 s after the step, first at {after[0] if after else float("nan"):.3f} s')
        assert detected and t_failsafe <= DETECT_WITHIN_S
        assert 'clock went back by' in sup._core.transitions[-1].reason
    finally:
        stepped_clock.restore()
        executor.shutdown()
        sup.destroy_node()
        feed.node.destroy_node()
        rclpy.try_shutdown(context=context)
