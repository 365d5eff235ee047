"""Force / heading pairing and SET_ATTITUDE_TARGET shaping, without I/O."""
import numpy as np
import pytest

from ibvs_common.core.frames import GRAVITY
from ibvs_control.mavlink.setpoints import (
    HeadingPairing, RAMP_STALL_S, SetpointShaper, SetpointSource, ShaperConfig, ShutdownRamp)
from ibvs_common.core.modes import Mode

MASS = 1.676
HOVER_F = np.array([0.0, 0.0, MASS * GRAVITY])


def shaper(**kw):
    return SetpointShaper(ShaperConfig(mass=MASS, max_thrust_factor=2.0, **kw))


def test_pairing_by_exact_stamp_never_waits():
    F = np.array([0.0, 0.0, 10.0])
    p = HeadingPairing()
    f = p.on_force(10, F)                          # no heading yet: the current yaw (None)
    assert (f.stamp_ns, f.yaw, f.paired) == (10, None, False) and p.missing == 1
    p.on_heading(10, 0.1)                          # late: counted, becomes the latest
    assert p.late == 1 and p.latest_yaw == 0.1
    p.on_heading(19, 0.19)                         # another frame's (1 ns away is another)
    p.on_heading(20, 0.2)
    f = p.on_force(20, F)
    assert (f.yaw, f.paired) == (0.2, True)
    f = p.on_force(30, F)                          # its heading never came: the latest, at once
    assert (f.yaw, f.paired) == (0.2, False) and p.missing == 2
    p.on_heading(40, None)                         # refused heading: its force takes the latest
    f = p.on_force(40, F)
    assert (f.yaw, f.paired) == (0.2, False) and p.missing == 3


def test_level_hover_thrust_and_tilted_thrust():
    s = shaper()
    q, thrust = s.force_target(HOVER_F, 0.3, hover=0.45)
    assert thrust == pytest.approx(0.45)
    assert np.allclose(q, [np.cos(0.15), 0, 0, np.sin(0.15)])
    tilt = np.radians(20.0)
    F = MASS * GRAVITY * np.array([np.tan(tilt), 0.0, 1.0])        # level flight, 20 deg
    assert s.force_target(F, 0.0, 0.4)[1] == pytest.approx(0.4 / np.cos(tilt))    # PX4: |F|
    s.tilt_boost_by_autopilot = True                                 # ArduPilot boost = 1
    assert s.force_target(F, 0.0, 0.4)[1] == pytest.approx(0.4)     # F_z: boosted once


def test_content_computed_once_held_on_vehicle_time_then_level_or_held_when_engaged():
    s = shaper(hold_last_s=0.25)
    F = MASS * np.array([-1.0, 0.0, GRAVITY])
    assert s.on_force(10.0, F, 0.0, 0.5) == ''
    t1 = s.target(10.2, Mode.WINDOW, 0.7, 0.5, 123, 10.0, 0.0)
    assert t1.source == SetpointSource.IBVS and t1.time_boot_ms == 123
    assert s.on_force(10.2, np.array([np.nan, 0, 1.0]), 0.0, 0.5) != ''
    t2 = s.target(10.21, Mode.WINDOW, 0.7, 0.6, 124, 10.2, 0.0)      # hover changed: the
    assert t2.source == SetpointSource.HOLD_LAST                     # content is not recomputed
    assert np.array_equal(t2.q_wxyz, t1.q_wxyz) and t2.thrust == t1.thrust
    t3 = s.target(10.3, Mode.WINDOW, 0.7, 0.5, 124, 10.2, 0.0)       # 0.3 s > hold_last_s
    assert t3.source == SetpointSource.LEVEL_HOVER                   # not engaged
    assert np.allclose(t3.q_wxyz, [np.cos(0.35), 0, 0, np.sin(0.35)]) and t3.thrust == 0.5
    t4 = s.target(10.3, Mode.WINDOW, 0.7, 0.5, 124, 10.2, 0.0, engaged=True)
    assert t4.source == SetpointSource.HOLD_LAST and t4.thrust == t1.thrust
    t5 = s.target(10.3, Mode.FAILSAFE, 0.7, 0.48, 124, 10.2, 0.0, engaged=True)
    assert t5.source == SetpointSource.LEVEL_HOLD and t5.thrust == 0.48   # no descent of ours
    # the ROS clock stepped back 3 s: the force is not fresh (level when not engaged, held
    # when engaged: the safety monitor's inputs_lost acts then); 0.1 s back: still fresh
    assert s.on_force(20.0, F, 0.0, 0.5) == ''
    assert s.target(17.0, Mode.WINDOW, 0.7, 0.5, 125, 20.0, 0.0).source == \
        SetpointSource.LEVEL_HOVER
    assert s.target(17.0, Mode.WINDOW, 0.7, 0.5, 125, 20.0, 0.0, engaged=True).source == \
        SetpointSource.HOLD_LAST
    assert s.target(19.9, Mode.WINDOW, 0.7, 0.5, 125, 20.0, 0.0).source == SetpointSource.IBVS


def test_shutdown_ramp_from_the_last_thrust_on_vehicle_time():
    s = shaper(shutdown_ramp_s=2.0)
    s.on_force(10.0, 0.8 * HOVER_F, 0.0, 0.5)
    first = s.target(10.0, Mode.LANDING, 0.0, 0.5, 0, 10.0, 100.0)
    assert first.thrust == pytest.approx(0.4)
    r0 = s.target(10.0, Mode.SHUTDOWN, 0.0, 0.5, 0, 10.0, 100.0)
    r1 = s.target(11.0, Mode.SHUTDOWN, 0.0, 0.5, 0, 11.0, 100.5)
    assert r0.thrust == pytest.approx(0.4) and r1.thrust == pytest.approx(0.2)
    assert not s.ramp_done(100.5)
    s.target(12.0, Mode.SHUTDOWN, 0.0, 0.5, 0, 12.0, 101.0)
    assert s.ramp_done(101.0)
    # the land mode asked for during a shutdown: level hold instead of the ramp
    assert s.target(12.0, Mode.SHUTDOWN, 0.0, 0.5, 0, 12.0, 101.0,
                    level_hold=True).source == SetpointSource.LEVEL_HOLD


def test_shutdown_ramp_never_starts_above_the_hover_thrust():
    """A last force above hover (braking a climb near the floor) must not be held level."""
    s = shaper(shutdown_ramp_s=2.0)
    s.on_force(10.0, 1.6 * HOVER_F, 0.0, 0.5)
    assert s.target(10.0, Mode.LANDING, 0.0, 0.5, 0, 10.0, 100.0).thrust == pytest.approx(0.8)
    r0 = s.target(10.02, Mode.SHUTDOWN, 0.0, 0.5, 0, 10.02, 100.0)
    assert r0.source == SetpointSource.SHUTDOWN_RAMP and r0.thrust == pytest.approx(0.5)
    r1 = s.target(11.02, Mode.SHUTDOWN, 0.0, 0.5, 0, 11.02, 101.0)
    assert r1.thrust == pytest.approx(0.25)


def test_shutdown_ramp_runs_on_vehicle_time_and_on_the_wall_after_a_stall():
    r = ShutdownRamp(0.5, t_vehicle=10.0, t_wall=100.0)
    r.advance(10.2, 100.9)                 # lockstep: 0.2 s of vehicle time in 0.9 s of wall
    assert r.elapsed(100.9) == pytest.approx(0.2)
    r.advance(10.2, 101.5)                 # stamps stopped: nothing yet ...
    assert r.elapsed(101.5) == pytest.approx(0.2)
    assert r.elapsed(100.9 + RAMP_STALL_S + 0.5) == pytest.approx(0.7)   # ... then the wall


def test_a_force_of_an_old_image_is_refused_and_counted():
    """max_force_age_s on the ROS clock: received at t, answering the image of stamp_t."""
    s = shaper(max_force_age_s=0.25)
    F = MASS * np.array([-1.0, 0.0, GRAVITY])
    assert s.on_force(10.0, F, 0.0, 0.5, stamp_t=10.0) == ''         # lockstep: age 0
    assert s.on_force(10.3, F, 0.0, 0.5, stamp_t=10.05) == ''        # 0.25 s: the limit
    reason = s.on_force(10.6, F, 0.0, 0.5, stamp_t=10.3001)
    assert 'ms old' in reason and (s.rejected, s.stale) == (1, 1)
    t = s.target(10.6, Mode.WINDOW, 0.0, 0.5, 1, 10.3, 0.0, engaged=True)
    assert t.source == SetpointSource.HOLD_LAST                       # held, not flown
    assert s.on_force(10.6, np.array([np.nan, 0, 1.0]), 0.0, 0.5, stamp_t=10.6) != ''
    assert (s.rejected, s.stale) == (2, 1)                           # bad content: not stale
    assert s.on_force(20.0, F, 0.0, 0.5) == ''                       # stamp unknown: no check
    off = shaper(max_force_age_s=0.0)
    assert off.on_force(20.0, F, 0.0, 0.5, stamp_t=10.0) == ''       # 0 = off
    with pytest.raises(ValueError, match='max_force_age_s'):
        shaper(max_force_age_s=-0.1)


def test_refused_forces():
    s = shaper()
    for bad in (np.array([np.nan, 0.0, 9.0]), np.array([0.0, 0.0, 1e4]),
                np.array([0.0, 0.0, -5.0]), np.zeros(2)):
        assert s.check_force(bad) != ''
    assert s.check_force(HOVER_F) == ''
