"""The safety policy's detectors in closed form (the table in docs: tests/repo)."""
import pytest

from ibvs_common.core.frames import GRAVITY
from ibvs_control.mavlink.safety import SafetyConfig, SafetyMonitor

MS = 1_000_000


def test_inputs_lost_after_hold_last_s_of_vehicle_time_only():
    m = SafetyMonitor(SafetyConfig(hold_last_s=0.25))
    assert not m.inputs_lost(100.0)              # no force yet, no engagement: nothing to judge
    m.start_count(100.0)                         # an engagement starts without any force
    assert m.inputs_lost(100.3)
    m.on_force(100.3)
    assert not m.inputs_lost(100.55) and m.inputs_lost(100.56)
    assert not m.inputs_lost(None)               # no ROS time (no /clock): no judgement
    m.start_count(200.0)                         # a force came already: the count stands
    assert m.forces_silent_s(100.4) == pytest.approx(0.1)


def test_a_ros_clock_stepped_back_in_flight_counts_as_inputs_lost():
    # the companion's system clock steps back 3 s after the last force (chrony makestep):
    # counting from 0 again would keep the last setpoint for 3 s on a silent controller
    m = SafetyMonitor(SafetyConfig(hold_last_s=0.25))
    m.on_force(1000.0)
    assert m.inputs_lost(997.1)
    assert m.forces_silent_s(997.1) == float('inf')
    # readings a little out of order (two threads), or a short step: within hold_last_s
    assert not m.inputs_lost(999.9) and m.forces_silent_s(999.9) == 0.0
    assert not m.inputs_lost(999.75) and m.inputs_lost(999.74)


def feed(m, seconds, f_g, thrust, hover=0.5, t0=0, dt_ms=10):
    t = t0
    for _ in range(int(seconds * 1000 / dt_ms)):
        m.on_accel(t, f_g * GRAVITY, thrust, hover)
        t += dt_ms * MS
    return t


def test_touchdown_rule_ground_carries_the_vehicle_at_low_thrust():
    m = SafetyMonitor(SafetyConfig(disarm_force_after_s=1.0))
    t = feed(m, 0.99, 1.0, 0.0)                  # resting: |f| = g at zero thrust
    assert not m.touchdown
    feed(m, 0.02, 1.0, 0.0, t0=t)
    assert m.touchdown and not m.airborne_at_low_thrust
    feed(m, 0.01, 1.0, 0.4)                      # thrust above half hover: no evidence
    assert not m.touchdown


def test_airborne_at_low_thrust_no_ground_contact():
    m = SafetyMonitor(SafetyConfig(airborne_s=0.4))
    t = feed(m, 2.0, 1.0, 0.5)                   # hovering: not low thrust
    assert not m.airborne_at_low_thrust and not m.touchdown
    t = feed(m, 0.39, 0.3, 0.1, t0=t)            # thrust 0.2 hover, |f| 0.3 g: falling
    assert not m.airborne_at_low_thrust
    feed(m, 0.02, 0.3, 0.1, t0=t)
    assert m.airborne_at_low_thrust and not m.touchdown
    m.reset_contact()
    assert not m.airborne_at_low_thrust


def test_thresholds_validated():
    with pytest.raises(ValueError):
        SafetyConfig(airborne_g=0.9, supported_g=0.8)
    with pytest.raises(ValueError):
        SafetyConfig(hold_last_s=0.0)
