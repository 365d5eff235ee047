"""The sim autopilot's mode machine, setpoint stream and references in isolation (no socket).

ibvs_sim.core.autopilot.{setpoints, modes, references}: driven with fake setpoint messages, a
fake wall clock and ground-truth states. Expected values are written out (PX4's rules as
docs/sim_autopilot.md states them, point-mass physics), not recomputed with the module's code.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ibvs_common.core.frames import GRAVITY, rot_from_euler_zyx
from ibvs_sim.core.autopilot.config import (AutopilotConfig, AutopilotCounters, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.modes import FlightModeMachine
from ibvs_sim.core.autopilot.protocol import FlightMode
from ibvs_sim.core.autopilot.references import AttitudeReferences
from ibvs_sim.core.autopilot.setpoints import OffboardSetpoints

AIR = (-2.0, 0.1, -1.82)          # {I} NED, m: 1.82 m above the floor
GROUND = (0.0, 0.0, -0.05)        # 5 cm above the floor: landed


class Wall:
    """A wall clock the test advances by hand (s)."""

    def __init__(self) -> None:
        self.now = 500.0

    def __call__(self) -> float:
        return self.now


def state(t: float, xi=AIR, v=(0.0, 0.0, 0.0), yaw: float = 0.0) -> VehicleStateView:
    R = rot_from_euler_zyx(0.0, 0.0, yaw)
    return VehicleStateView(t=t, xi_I=np.array(xi, float), v_I=np.array(v, float), R_IB=R,
                            Omega_B=np.zeros(3), accel_B_specific=np.array([0, 0, -GRAVITY]))


def setpoint(time_boot_ms: int, q=(1.0, 0.0, 0.0, 0.0), thrust: float = 0.6,
             type_mask: int = 7) -> SimpleNamespace:
    return SimpleNamespace(time_boot_ms=time_boot_ms, type_mask=type_mask, q=list(q),
                           thrust=thrust, body_roll_rate=0.0, body_pitch_rate=0.0,
                           body_yaw_rate=0.0)


class Parts:
    """Setpoints, references and the mode machine wired as the facade wires them."""

    def __init__(self, **cfg) -> None:
        self.config = AutopilotConfig(**cfg)
        self.wall = Wall()
        self.counters = AutopilotCounters()
        warn = RateLimitedLog(5.0, self.wall)
        self.setpoints = OffboardSetpoints(self.config, self.counters, warn, self.wall)
        self.refs = AttitudeReferences(self.config, self.counters, warn)
        self.holds: list[float] = []

        def on_hold(s: VehicleStateView) -> None:
            self.holds.append(s.t)
            self.refs.set_hold_target(s)

        self.modes = FlightModeMachine(self.config, self.counters, self.setpoints, on_hold)

    def stream(self, t0: float, t1: float, period: float = 0.02) -> float:
        """Send setpoints every period from sim time t0 to t1 (wall advances alike)."""
        t = t0
        while t <= t1 + 1e-9:
            self.wall.now += period if t > t0 else 0.0
            assert self.setpoints.receive(setpoint(int(round(t * 1000))), state(t))
            t += period
        return t - period


def test_offboard_needs_half_a_second_of_stream_then_is_accepted():
    p = Parts()
    assert not p.modes.request_offboard(state(1.0))                 # no stream at all
    p.stream(1.0, 1.4)                                              # 0.4 s < 0.5 s
    assert not p.modes.request_offboard(state(1.4))
    assert p.modes.mode is FlightMode.POSCTL
    p.stream(1.42, 1.52)                                            # now 0.52 s of stream
    assert p.modes.request_offboard(state(1.52))
    assert p.modes.mode is FlightMode.OFFBOARD and not p.modes.failsafe_active


def test_a_gap_longer_than_the_timeout_restarts_the_stream():
    p = Parts()
    p.stream(0.0, 1.0)
    p.wall.now += 1.1
    p.stream(2.1, 2.3)                         # 1.1 s gap > 1 s: a new stream from 2.1 s
    assert not p.setpoints.healthy(2.3)
    p.stream(2.32, 2.6)
    assert p.setpoints.healthy(2.6)


def test_stream_loss_on_sim_time_and_on_the_wall_clock():
    p = Parts()
    p.stream(0.0, 1.0)
    assert p.setpoints.lost(2.0) == (False, False)                  # exactly 1 s: not lost
    assert p.setpoints.lost(2.01) == (True, False)
    p.wall.now += 2.01                                              # sim time stalled
    assert p.setpoints.lost(1.0) == (False, True)
    assert OffboardSetpoints(p.config, p.counters, RateLimitedLog(5.0, p.wall),
                             p.wall).lost(0.0) == (True, True)      # nothing yet


def test_offboard_loss_enters_the_land_failsafe_once_and_it_stays():
    p = Parts()
    p.stream(0.0, 1.0)
    assert p.modes.request_offboard(state(1.0))
    assert not p.modes.check_offboard_loss(state(1.9))              # COM_OF_LOSS_T 1 s
    assert p.modes.check_offboard_loss(state(2.1))
    assert (p.modes.mode, p.modes.failsafe_active) == (FlightMode.AUTO_LAND, True)
    assert p.counters.failsafe_events == 1
    assert not p.modes.check_offboard_loss(state(2.2))              # not in OFFBOARD any more
    p.wall.now += 1.2
    p.stream(2.2, 2.4)                                              # setpoints come back
    assert p.modes.mode is FlightMode.AUTO_LAND                     # the failsafe stays
    p.stream(2.42, 2.8)
    assert p.modes.request_offboard(state(2.8))
    assert (p.modes.mode, p.modes.failsafe_active) == (FlightMode.OFFBOARD, False)


def test_disarmed_offboard_never_fails_safe():
    p = Parts(start_armed=False)
    p.stream(0.0, 1.0)
    assert p.modes.request_offboard(state(1.0))
    assert not p.modes.check_offboard_loss(state(5.0))
    assert p.modes.mode is FlightMode.OFFBOARD


def test_arming_in_offboard_needs_the_stream_and_arming_in_hold_holds_here():
    p = Parts(start_armed=False)
    p.stream(0.0, 1.0)
    assert p.modes.request_offboard(state(1.0))
    assert not p.modes.arm(state(3.0))                              # stream stopped 2 s ago
    assert not p.modes.armed
    p.wall.now += 2.0
    p.stream(3.0, 3.6)
    assert p.modes.arm(state(3.6)) and p.modes.armed
    q = Parts(start_armed=False)
    assert q.modes.arm(state(2.0, xi=(1.0, 2.0, -3.0)))
    assert q.holds == [2.0]
    np.testing.assert_array_equal(q.refs.hold_xi, [1.0, 2.0, -3.0])


def test_disarm_in_the_air_needs_force_on_the_ground_not():
    p = Parts()
    assert not p.modes.disarm(state(1.0), forced=False) and p.modes.armed
    assert p.modes.disarm(state(1.0), forced=True) and not p.modes.armed
    assert p.modes.disarm(state(1.0), forced=False)                 # already disarmed
    q = Parts()
    assert q.modes.disarm(state(1.0, xi=GROUND), forced=False) and not q.modes.armed


def test_landed_detector_height_and_vertical_speed():
    m = Parts().modes
    assert m.landed(state(0.0, xi=(0, 0, -0.15)))                  # 0.15 m: landed
    assert not m.landed(state(0.0, xi=(0, 0, -0.16)))
    assert m.landed(state(0.0, xi=GROUND, v=(5.0, 0.0, 0.3)))      # |v_z| 0.3 m/s: landed
    assert not m.landed(state(0.0, xi=GROUND, v=(0.0, 0.0, -0.31)))


def test_auto_disarm_after_two_seconds_landed_in_auto_land_only():
    p = Parts()
    p.modes.set_mode(FlightMode.AUTO_LAND, state(0.0))
    p.modes.check_auto_disarm(state(10.0, xi=GROUND))
    p.modes.check_auto_disarm(state(11.99, xi=GROUND))
    assert p.modes.armed
    p.modes.check_auto_disarm(state(12.0, xi=GROUND))
    assert not p.modes.armed
    q = Parts()                                                     # POSCTL: stays armed
    for t in (10.0, 13.0, 20.0):
        q.modes.check_auto_disarm(state(t, xi=GROUND))
    assert q.modes.armed
    r = Parts()                                                     # a bounce restarts the count
    r.modes.set_mode(FlightMode.AUTO_LAND, state(0.0))
    r.modes.check_auto_disarm(state(10.0, xi=GROUND))
    r.modes.check_auto_disarm(state(11.0, xi=AIR))
    r.modes.check_auto_disarm(state(12.5, xi=GROUND))
    r.modes.check_auto_disarm(state(14.0, xi=GROUND))
    assert r.modes.armed
    r.modes.check_auto_disarm(state(14.5, xi=GROUND))
    assert not r.modes.armed


def test_hold_modes_capture_the_hold_point_only_when_entered_anew():
    p = Parts()
    p.modes.set_mode(FlightMode.AUTO_LOITER, state(1.0))
    p.modes.set_mode(FlightMode.AUTO_LOITER, state(2.0))            # same mode: no new point
    p.modes.set_mode(FlightMode.AUTO_LAND, state(3.0))
    p.modes.set_mode(FlightMode.POSCTL, state(4.0))
    assert p.holds == [1.0, 4.0]


def test_invalid_setpoints_are_counted_and_change_nothing():
    p = Parts()
    bad = [setpoint(1, q=(1.0, 1.0, 0.0, 0.0)), setpoint(2, q=(math.nan, 0, 0, 0)),
           setpoint(3, thrust=1.01), setpoint(4, thrust=-0.01)]
    nan_rates = setpoint(5, type_mask=0)
    nan_rates.body_yaw_rate = math.nan
    for msg in bad + [nan_rates]:
        assert not p.setpoints.receive(msg, state(1.0))
    assert (p.counters.setpoints_invalid, p.counters.setpoints_received) == (5, 0)
    assert p.setpoints.last_time_boot_ms is None and p.setpoints.q_wxyz is None
    assert not p.setpoints.new_setpoints


def test_setpoint_fields_held_across_ignored_ones_and_new_stamps_logged():
    p = Parts()
    p.wall.now = 700.0
    assert p.setpoints.receive(setpoint(10, q=(0.0, 0.0, 0.0, 1.004), thrust=0.3), state(1.0))
    np.testing.assert_allclose(p.setpoints.q_wxyz, [0, 0, 0, 1], atol=1e-15)   # renormalised
    assert p.setpoints.receive(setpoint(10, q=(1, 0, 0, 0), thrust=0.9, type_mask=7 | 128),
                               state(1.02))
    np.testing.assert_allclose(p.setpoints.q_wxyz, [0, 0, 0, 1], atol=1e-15)   # attitude kept
    assert p.setpoints.thrust == pytest.approx(0.9)
    assert p.setpoints.receive(setpoint(30, q=(1, 0, 0, 0), thrust=0.1, type_mask=7 | 64),
                               state(1.04))
    assert p.setpoints.thrust == pytest.approx(0.9)                 # thrust kept
    assert list(p.setpoints.new_setpoints) == [(10, 700.0), (30, 700.0)]       # 10 once
    assert p.setpoints.last_time_boot_ms == 30


def test_references_of_each_mode():
    p = Parts(hover_thrust=0.5)
    s = state(0.0, yaw=0.7)
    ref = p.refs.reference(s, armed=True, mode=FlightMode.POSCTL, setpoint_q=None,
                           setpoint_thrust=None)
    # at the hold point, at rest: level, the held yaw, hover thrust
    level_07 = [math.cos(0.35), 0.0, 0.0, math.sin(0.35)]
    np.testing.assert_allclose(ref.q_IB_wxyz, level_07, atol=1e-12)
    assert (ref.thrust_norm, ref.source) == (pytest.approx(0.5), 'hold')
    # 1 m below the hold point, at rest: a* = 3 m/s^2 up, thrust 0.5 (g + 3) / g
    ref = p.refs.reference(state(0.0, xi=(AIR[0], AIR[1], AIR[2] + 1.0), yaw=0.7), True,
                           FlightMode.AUTO_LOITER, None, None)
    assert ref.thrust_norm == pytest.approx(0.5 * (GRAVITY + 3.0) / GRAVITY)
    # land: descending at 0.4 m/s = hover; at rest: 0.5 (g - 2 * 0.4) / g
    ref = p.refs.reference(state(0.0, v=(0, 0, 0.4)), True, FlightMode.AUTO_LAND, None, None)
    assert (ref.thrust_norm, ref.source) == (pytest.approx(0.5), 'failsafe')
    ref = p.refs.reference(state(0.0), True, FlightMode.AUTO_LAND, None, None)
    assert ref.thrust_norm == pytest.approx(0.5 * (GRAVITY - 0.8) / GRAVITY)
    # offboard: the setpoint, else level with the current yaw at hover thrust
    ref = p.refs.reference(s, True, FlightMode.OFFBOARD, np.array([0.0, 1.0, 0.0, 0.0]), 0.7)
    np.testing.assert_array_equal(ref.q_IB_wxyz, [0.0, 1.0, 0.0, 0.0])
    assert (ref.thrust_norm, ref.source) == (0.7, 'offboard')
    ref = p.refs.reference(s, True, FlightMode.OFFBOARD, None, None)
    np.testing.assert_allclose(ref.q_IB_wxyz, level_07, atol=1e-12)
    assert ref.thrust_norm == 0.5
    # disarmed: zero thrust; non-finite truth: level hover (counted)
    assert p.refs.reference(s, False, FlightMode.OFFBOARD, None, None).thrust_norm == 0.0
    bad = state(0.0, v=(math.nan, 0, 0))
    ref = p.refs.reference(bad, True, FlightMode.POSCTL, None, None)
    assert (ref.thrust_norm, ref.source, p.counters.state_invalid) == (0.5, 'failsafe', 1)


def test_hold_tilt_is_limited_to_35_degrees():
    p = Parts()
    p.refs.set_hold_target(state(0.0))
    far = state(0.0, xi=(AIR[0] - 100.0, AIR[1], AIR[2]))          # 100 m behind the hold point
    ref = p.refs.reference(far, True, FlightMode.POSCTL, None, None)
    tilt = 2.0 * math.acos(min(1.0, abs(ref.q_IB_wxyz[0])))         # yaw 0: pure pitch
    assert tilt == pytest.approx(math.radians(35.0), abs=1e-9)
    # thrust: lift g, horizontal g tan 35 deg -> g / cos 35 deg
    assert ref.thrust_norm == pytest.approx(0.5 / math.cos(math.radians(35.0)))


def test_imu_fault_windows_are_half_open_in_sim_time():
    from ibvs_sim.core.autopilot import AutopilotConfig
    cfg = AutopilotConfig(imu_off_s=(2.0, 3.0), imu_nan_s=(5.0, 5.1))
    assert [cfg.imu_fault_at(t) for t in (1.99, 2.0, 2.99, 3.0, 5.05, 5.1)] == \
        ['', 'off', 'off', '', 'nan', '']
    assert AutopilotConfig().imu_fault_at(0.0) == ''       # [0, 0]: never
