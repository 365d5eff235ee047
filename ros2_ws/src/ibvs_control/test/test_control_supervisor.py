"""Mode supervisor as a pure state machine: triggers, once-only switch, staleness, abort."""
import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout
from ibvs_sim.core.world import load_world
from ibvs_common.core.modes import Mode
from ibvs_control.core.supervisor import ModeSupervisor, SupervisorConfig

WORLD = load_world()
CORNERS = WORLD.window.corners_I()
PAD = load_pad_layout()
R = np.eye(3)


def bearings(points, xi):
    P = np.asarray(points) - xi
    return P / np.linalg.norm(P, axis=1, keepdims=True)


def pad_groups(xi, names=('A', 'B')):
    groups = [g for g in PAD.groups if g.name in names]
    return np.concatenate([bearings(g.marker_centres_I(), xi) for g in groups]), \
        [g.name for g in groups]


def feed(sup, t, xi, v, window=True, pad=None, imu=True, down=True):
    if imu:
        sup.on_imu(t, R)
    sup.on_window(t, bearings(CORNERS, xi) if window else None)
    if pad is not None:
        sup.on_pad(t, *pad)
    if xi[0] < WORLD.wall_x:
        sup.on_flow(t, 'front', v / (WORLD.wall_x - xi[0]))
    if down:
        sup.on_flow(t, 'down', v / -xi[2])
    return sup.end_frame(t)             # the frame closed, as the node does


def started(xi=np.array([-2.0, 0.0, -1.6])):
    sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width))
    feed(sup, 0.0, xi, np.zeros(3))
    ok, _ = sup.start(0.0)
    assert ok and sup.mode == Mode.WINDOW
    return sup


def test_start_needs_window_and_imu():
    sup = ModeSupervisor(SupervisorConfig())
    ok, msg = sup.start(0.0)
    assert not ok and 'IMU' in msg and sup.mode == Mode.IDLE
    sup.on_imu(0.0, R)
    ok, msg = sup.start(0.0)
    assert not ok and 'window' in msg


def test_window_lost_far_away_is_failsafe_not_crossing():
    sup = started()
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    for k in range(1, 40):
        feed(sup, 0.02 * k, xi, v, window=False)
    assert sup.mode == Mode.FAILSAFE
    assert 'window stale' in sup.transitions[-1].reason


def test_a_window_lost_far_away_is_noted_once_with_its_angular_height():
    """The loss that ends in staleness says why it is not a crossing: the window's size."""
    sup = started()                                  # 1.5 m from the wall plane
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    feed(sup, 0.02, xi, v)
    height = 2.0 * np.arctan(0.5 * WORLD.window.height / (WORLD.wall_x - xi[0]))  # geometry
    assert sup.window_loss_note == ''
    feed(sup, 0.04, xi, v, window=False)
    note = sup.window_loss_note
    assert note.startswith('forward camera lost the full window at t = 0.040 s while not '
                           'close')
    assert f'angular height {height:.3f} rad < 0.85 rad' in note
    sup.window_loss_note = ''                        # the node logs and clears it
    feed(sup, 0.06, xi, v, window=False)
    assert sup.window_loss_note == ''                # once per loss
    feed(sup, 0.08, xi, v)                           # seen again, then lost again: noted again
    feed(sup, 0.10, xi, v, window=False)
    assert 'at t = 0.100 s' in sup.window_loss_note
    assert sup.mode == Mode.WINDOW


def test_a_window_lost_up_close_is_a_crossing_and_no_note():
    xi, v = np.array([-1.25, 0.0, -1.6]), np.array([0.3, 0, 0])    # 0.75 m: about 1.2 rad
    sup = started(xi)
    feed(sup, 0.02, xi, v)
    feed(sup, 0.04, xi, v, window=False)
    assert sup.mode == Mode.CROSSING and sup.window_loss_note == ''


def lost_after(xi, margin_px, offset_known=True):
    """The mode after one frame of the window seen from xi (its corners margin_px from the
    image border) and the next frame without it."""
    sup = started(xi)
    v = np.array([0.3, 0, 0])
    sup.on_imu(0.02, R)
    sup.on_window(0.02, bearings(CORNERS, xi), margin_px)
    sup.end_frame(0.02)
    feed(sup, 0.04, xi, v, window=False)
    return sup


def angular_height(xi):
    """The window's angular height from xi on its axis (geometry, not the supervisor's)."""
    return 2.0 * np.arctan(0.5 * WORLD.window.height / (WORLD.wall_x - xi[0]))


def test_a_window_that_left_the_image_early_near_its_axis_is_a_crossing():
    """Between 0.72 and 0.85 rad a loss counts when the corners were at the image border and
    the window centre lay within 0.4 m of the camera's axis through it (the PX4 SIH case: the
    vehicle 0.2 m low lost the window's top edge at 0.83 rad)."""
    xi = np.array([-1.65, 0.1, -1.4])      # 1.15 m from the wall, 0.2 m low, 0.1 m aside
    assert 0.72 < angular_height(xi) < 0.85
    assert lost_after(xi, 30.0).mode == Mode.CROSSING


@pytest.mark.parametrize('xi, margin_px, why', [
    ((-1.65, 0.1, -1.4), 100.0, 'margin 100 px'),       # lost in the middle of the image
    ((-1.65, 0.1, -1.4), None, 'margin unknown'),        # no camera model: the old rule
    ((-1.65, 0.45, -1.4), 30.0, 'margin 30 px'),        # 0.49 m off the axis: no crossing
    ((-1.90, 0.0, -1.6), 30.0, 'margin 30 px'),         # 0.71 rad: too far
])
def test_a_window_lost_early_is_no_crossing_in_the_middle_off_axis_or_far(xi, margin_px, why):
    sup = lost_after(np.array(xi), margin_px)
    assert sup.mode == Mode.WINDOW
    assert 'while not close' in sup.window_loss_note and why in sup.window_loss_note


def fly_through_the_window(sup, floor_flow_in_window=True):
    """Approach at 0.25 m/s until the window is lost up close, cross until LANDING.

    Returns (t, xi, v, travelled after T2). The pad is visible through the window long before
    the vehicle is through: the mode must stay CROSSING until the crossing length is flown.
    """
    v = np.array([0.25, 0.0, 0.0])
    xi = np.array([-1.5, 0.0, -1.6])
    t = 0.0
    while sup.mode == Mode.WINDOW:
        t += 0.02
        xi = xi + v * 0.02
        feed(sup, t, xi, v, window=xi[0] < -1.2, down=floor_flow_in_window)
    assert sup.mode == Mode.CROSSING and xi[0] < -1.19
    t_cross = t
    while sup.mode == Mode.CROSSING:
        t += 0.02
        xi = xi + v * 0.02
        feed(sup, t, xi, v, window=False, pad=pad_groups(xi))
        assert sup.mode == Mode.CROSSING or \
            xi[0] >= WORLD.wall_x + sup.config.crossing_margin_m - 0.1
    return t, xi, v, v[0] * (t - t_cross)


def test_a_window_detection_after_t2_does_not_turn_the_crossings_travel():
    # the window leaving the view: a detection 0.2 s after T2 (past the corner-jump check's
    # gap) whose normal is off by 80 deg; the travel is measured along the wall normal of T2,
    # so the switch to LANDING still comes d_o(T2) + margin after T2
    sup = started()
    v = np.array([0.25, 0.0, 0.0])
    xi, t = np.array([-1.5, 0.0, -1.6]), 0.0
    while sup.mode == Mode.WINDOW:
        t += 0.02
        xi = xi + v * 0.02
        feed(sup, t, xi, v, window=xi[0] < -1.2)
    t_cross, c = t, np.mean(CORNERS, axis=0)
    a = np.radians(80.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    skewed = (np.asarray(CORNERS) - c) @ Rz.T + c
    k = 0
    while sup.mode == Mode.CROSSING and k < 400:     # the crossing: ~240 frames
        k += 1
        t += 0.02
        xi = xi + v * 0.02
        if k == 10:
            sup.on_window(t, bearings(skewed, xi))
        feed(sup, t, xi, v, window=False, pad=pad_groups(xi))
    assert sup.mode == Mode.LANDING
    assert abs(v[0] * (t - t_cross) - (0.7 + sup.config.crossing_margin_m)) < 0.03


def test_whole_sequence_with_crossing_length_from_images():
    sup = started()
    t, xi, v, travelled = fly_through_the_window(sup)
    # d_o(T2) = 0.7 m plus the margin: the switch comes that far after T2 (+- one frame)
    assert sup.mode == Mode.LANDING
    assert abs(travelled - (0.7 + sup.config.crossing_margin_m)) < 0.02
    # the log's note of the measure: the window plane 0.7 m ahead, the floor 1.6 m below (the
    # wall flow of the frame before T2: 1 % far)
    note = sup.crossing_note
    assert 'd_o(T2) 0.700 m' in note, note
    assert abs(float(note.split('floor ')[1].split(' m below')[0]) - 1.6) < 0.02, note
    travel, needed = sup.crossing_progress    # the switch came once flown (within 2 frames)
    assert needed is not None and needed <= travel < needed + 2 * 0.25 * 0.02 / 1.6 + 1e-9
    # descend over the pad: mode 4 below 0.14 m from the smallest complete group
    xi = np.array([0.0, 0.0, -0.5])
    v = np.array([0.0, 0.0, 0.2])
    while sup.mode == Mode.LANDING and xi[2] < -0.05:
        t += 0.02
        xi = xi + v * 0.02
        feed(sup, t, xi, v, window=False, pad=pad_groups(xi, ('C', 'D')))
    assert sup.mode == Mode.SHUTDOWN and abs(-xi[2] - 0.14) < 0.01
    assert [tr.to_mode for tr in sup.transitions] == [Mode.WINDOW, Mode.CROSSING,
                                                      Mode.LANDING, Mode.SHUTDOWN]


def test_one_wrong_pad_frame_in_the_air_does_not_shut_down():
    """A group's bearings labelled with a smaller group's size read too low for one frame.

    At 0.6 m, A's bearings read as D (c 0.36 -> 0.045 m) give a height 8 times too small
    (0.075 m, below the 0.14 m shutdown height): one such frame must not cut the motors;
    the same reading on two consecutive frames (shutdown_confirm_s 0.02 s) does.
    """
    sup = started()
    t, xi, v, _ = fly_through_the_window(sup)
    assert sup.mode == Mode.LANDING
    xi, v = np.array([0.0, 0.0, -0.6]), np.zeros(3)
    a_bearings, _ = pad_groups(xi, ('A',))
    for k in range(3):                          # right, wrong, right, ...
        t += 0.02
        feed(sup, t, xi, v, window=False, pad=(a_bearings, ['D']) if k == 1 else
             pad_groups(xi, ('A', 'B')))
        assert sup.mode == Mode.LANDING
    assert sup.height_estimate > 0.5
    for k in range(2):                          # wrong twice in a row: confirmed
        t += 0.02
        feed(sup, t, xi, v, window=False, pad=(a_bearings, ['D']))
        assert sup.mode == (Mode.LANDING if k == 0 else Mode.SHUTDOWN)
    assert abs(sup.height_estimate - 0.6 * 0.045 / 0.36) < 0.01


def test_the_crossing_length_waits_for_the_first_floor_flow_of_crossing():
    # mode gating: the floor flow is computed only from the switch on; the first one of
    # CROSSING (stamped T2) gives d_t(T2), and the switch to LANDING comes d_o + margin
    # after T2 as when the floor flow was there all along (the fallback would be 1.6 m)
    sup = started()
    _, _, _, travelled = fly_through_the_window(sup, floor_flow_in_window=False)
    assert sup.mode == Mode.LANDING
    assert abs(travelled - (0.7 + sup.config.crossing_margin_m)) < 0.03


def test_landing_switch_happens_only_once_and_stale_flow_is_failsafe():
    sup = started()
    sup._landing_entered = True       # as if mode 3 had already been entered once
    sup.mode = Mode.CROSSING
    sup._travel_needed = 0.0
    xi = np.array([0.0, 0.0, -1.5])
    feed(sup, 1.0, xi, np.zeros(3), window=False, pad=pad_groups(xi))
    assert sup.mode == Mode.CROSSING
    # the down flow stops: failsafe after its timeout
    for k in range(1, 40):
        sup.on_imu(1.0 + 0.02 * k, R)
        sup.update(1.0 + 0.02 * k)
    assert sup.mode == Mode.FAILSAFE and 'down_flow' in sup.transitions[-1].reason


def test_imu_stale_and_abort():
    sup = started()
    feed(sup, 0.02, np.array([-2.0, 0, -1.6]), np.zeros(3), imu=False)
    sup.update(0.5)
    assert sup.mode == Mode.FAILSAFE and 'IMU' in sup.transitions[-1].reason
    sup = started()
    ok, _ = sup.abort(0.1)
    assert ok and sup.mode == Mode.FAILSAFE
    assert not sup.abort(0.2)[0]


def test_corner_jump_counts_as_loss():
    sup = started(np.array([-1.25, 0.0, -1.6]))   # close: angular height above threshold
    xi = np.array([-1.25, 0.0, -1.6])
    feed(sup, 0.02, xi, np.array([0.2, 0, 0]))
    sup.on_window(0.04, bearings(CORNERS + [0, 0.8, 0], xi))   # another rectangle, 0.8 m away
    sup.update(0.04)
    assert sup.mode == Mode.CROSSING and 'jumped' in sup.transitions[-1].reason


def test_bad_parameters_refused():
    import pytest
    with pytest.raises(ValueError):
        SupervisorConfig.from_params({'imu_timeout_s': -1.0})
    with pytest.raises(ValueError):
        SupervisorConfig.from_params({'no_such_thing': 1.0})


def test_auto_start_at_the_first_frame_at_or_after_its_time_and_only_once():
    sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width, auto_start_at_s=0.05))
    xi = np.array([-2.0, 0.0, -1.6])
    sup.on_imu(0.0, R)
    assert sup.end_frame(0.0) == [] and sup.auto_start_refusal == ''   # not yet due
    sup.on_imu(0.06, R)
    sup.end_frame(0.06)                           # due, but no window yet: refused, retried
    assert sup.mode == Mode.IDLE and 'window' in sup.auto_start_refusal
    sup.on_imu(0.08, R)
    sup.on_window(0.08, bearings(CORNERS, xi))
    (tr,) = sup.end_frame(0.08)
    assert (tr.to_mode, tr.t) == (Mode.WINDOW, 0.08) and 'auto-start' in tr.reason
    sup.abort(0.1)
    sup.on_imu(0.12, R)
    sup.on_window(0.12, bearings(CORNERS, xi))
    sup.end_frame(0.12)
    assert sup.mode == Mode.FAILSAFE               # never started again by itself


def test_a_start_request_is_checked_at_once_and_applied_at_the_next_frame():
    """ibvs/start between frames: the mode changes at the next frame closed, not between.

    So that frame's status announces WINDOW before any WINDOW frame needs the front flow,
    which the perception's mode gating computes only once a status says so.
    """
    sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width))
    xi = np.array([-2.0, 0.0, -1.6])
    ok, msg = sup.request_start(0.0)
    assert not ok and 'IMU' in msg                       # the checks of start(), at once
    sup.on_imu(0.0, R)
    sup.on_window(0.0, bearings(CORNERS, xi))
    assert sup.end_frame(0.0) == [] and sup.mode == Mode.IDLE
    ok, msg = sup.request_start(0.01)                    # between the frames 0.00 and 0.02
    assert ok and 'next frame' in msg and sup.mode == Mode.IDLE and sup.transitions == []
    sup.on_imu(0.02, R)
    sup.on_window(0.02, bearings(CORNERS, xi))
    (tr,) = sup.end_frame(0.02)
    assert (tr.to_mode, tr.t, tr.reason) == (Mode.WINDOW, 0.02, 'ibvs/start, window detected')
    assert sup.request_start(0.03) == (False, 'cannot start from mode WINDOW')


def test_a_start_request_lapses_without_a_frame_on_abort_and_when_checks_fail():
    xi = np.array([-2.0, 0.0, -1.6])

    def ready():
        sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width, window_timeout_s=0.5))
        sup.on_imu(0.0, R)
        sup.on_window(0.0, bearings(CORNERS, xi))
        assert sup.request_start(0.0)[0]
        return sup

    sup = ready()                                        # frames stopped for 1 s
    sup.on_imu(1.0, R)
    sup.on_window(1.0, bearings(CORNERS, xi))
    assert sup.end_frame(1.0) == [] and sup.mode == Mode.IDLE
    assert 'no frame within 0.5 s' in sup.start_refusal
    assert sup.end_frame(1.02) == [] and sup.start_refusal == ''   # applied once, or never
    sup = ready()
    sup.abort(0.01)
    assert sup.mode == Mode.FAILSAFE and sup.end_frame(0.02) == []
    sup = ready()                                        # the IMU stale by the next frame
    assert sup.end_frame(0.3) == [] and sup.mode == Mode.IDLE     # imu_timeout_s 0.2 s
    assert 'IMU' in sup.start_refusal


def test_auto_start_is_off_by_default_and_needs_a_finite_time():
    sup = ModeSupervisor(SupervisorConfig())
    sup.on_imu(5.0, R)
    sup.on_window(5.0, bearings(CORNERS, np.array([-2.0, 0.0, -1.6])))
    assert sup.end_frame(5.0) == [] and sup.mode == Mode.IDLE
    for bad in (float('nan'), float('inf')):
        try:
            SupervisorConfig.from_params({'auto_start_at_s': bad})
        except ValueError as exc:
            assert 'auto_start_at_s' in str(exc)
        else:
            raise AssertionError(f'auto_start_at_s = {bad} accepted')


def test_the_staleness_watchdog_leaves_image_cues_to_the_frames():
    """A requested transition (an image cue) happens at a frame, never at a watchdog tick."""
    from ibvs_common.core.modes import Mode
    from ibvs_control.core.supervisor import ModeSupervisor, SupervisorConfig
    sup = ModeSupervisor(SupervisorConfig())
    sup.mode = Mode.WINDOW
    sup._request(Mode.CROSSING, 'test cue')
    sup.on_imu(1.0, None)
    sup._last.update({'window': 1.0, 'front_flow': 1.0})
    assert sup.update(1.0, apply_requests=False) == [] and sup.mode == Mode.WINDOW
    assert [tr.to_mode for tr in sup.update(1.0)] == [Mode.CROSSING]


def test_a_clock_step_back_in_flight_is_failsafe_and_in_idle_needs_fresh_inputs():
    """Without the step rule, the inputs of 1.0 s would look 0.2 s *younger* than fresh."""
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    sup = started()
    for k in range(1, 50):
        feed(sup, 0.02 * k, xi, v)
    assert sup.mode == Mode.WINDOW
    # the clock read 0.98 s; it now reads 0.80 s, and the window is gone: by ages alone the
    # window (stamped 0.98) would count as fresh until the clock reached 1.48 s
    done = sup.clock_stepped_back(0.8, 0.18)
    assert sup.mode == Mode.FAILSAFE and done == sup.transitions[-1:]
    assert done[0].t == 0.8 and 'clock went back by 0.180 s' in done[0].reason
    # in IDLE: no transition, but a start needs inputs taken after the step
    sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width))
    feed(sup, 1.0, xi, np.zeros(3))
    assert sup.clock_stepped_back(0.5, 0.5) == [] and sup.mode == Mode.IDLE
    ok, msg = sup.start(0.55)
    assert not ok and 'IMU' in msg
    feed(sup, 0.56, xi, np.zeros(3))
    assert sup.start(0.56)[0]
    # FAILSAFE and SHUTDOWN stay what they are
    sup = started()
    sup.abort(0.1)
    assert sup.clock_stepped_back(0.05, 0.2) == [] and sup.mode == Mode.FAILSAFE


def land_until_the_pad_is_lost(sup, t, xi0, v, lost_below_m):
    """LANDING frames from xi0 at v; the pad's groups C and D seen above lost_below_m only.

    Returns the last frame's t and xi, and the first t at or below 0.14 m.
    """
    xi, t_014 = xi0, None
    while sup.mode == Mode.LANDING and xi[2] < -0.09:
        t += 0.02
        xi = xi + v * 0.02
        seen = -xi[2] > lost_below_m
        if t_014 is None and -xi[2] <= 0.14:
            t_014 = t
        feed(sup, t, xi, v, window=False, pad=pad_groups(xi, ('C', 'D')) if seen else None)
    return t, xi, t_014


def test_the_carried_height_shuts_down_near_the_pad_and_off_it_only_at_the_floor():
    """Mode 3 -> 4 on the pad-image height carried by the floor flow (pad_prediction.py).

    The pad lost at 0.2 m (the smallest group out of the down camera's view near the floor),
    descending at 0.1 m/s to 0.09 m, then still. Over the pad the carried height switches on
    the same frame as the measured one would (0.14 m, within a frame). 6 cm off the pad (more
    than shutdown_carried_offset_m) it waits shutdown_carried_wait_s (0.5 s) below the
    shutdown height, for the controller to bring the vehicle back, then switches wherever it
    is. With pad_prediction_s 0 the pad goes stale instead.
    """
    for offset_x, carry, expected in ((0.0, 1.5, Mode.SHUTDOWN), (0.06, 1.5, Mode.SHUTDOWN),
                                      (0.0, 0.0, Mode.FAILSAFE)):
        sup = ModeSupervisor(SupervisorConfig(r_w=WORLD.window.width, pad_prediction_s=carry))
        feed(sup, 0.0, np.array([-2.0, 0.0, -1.6]), np.zeros(3))
        sup.start(0.0)
        t, _, _, _ = fly_through_the_window(sup)
        assert sup.mode == Mode.LANDING
        t, xi, t_014 = land_until_the_pad_is_lost(sup, t, np.array([offset_x, 0.0, -0.3]),
                                                  np.array([0.0, 0.0, 0.1]), 0.2)
        while sup.mode == Mode.LANDING:                 # still on the floor, no pad
            t += 0.02
            feed(sup, t, xi, np.zeros(3), window=False)
        last = sup.transitions[-1]
        assert sup.mode == expected, (offset_x, carry, last)
        if offset_x == 0.0 and carry:
            assert abs(last.t - t_014) < 0.03 and '0.0 cm off' in last.reason, last
        elif offset_x:
            assert abs(last.t - t_014 - 0.5) < 0.03 and '6.0 cm off' in last.reason, last
        else:
            assert 'pad stale' in last.reason


def test_pad_prediction_parameters_are_checked():
    for bad in ({'pad_prediction_s': -0.1}, {'shutdown_carried_offset_m': 0.0},
                {'shutdown_carried_wait_s': 0.0}):
        try:
            SupervisorConfig.from_params(bad)
        except ValueError:
            continue
        raise AssertionError(f'accepted {bad}')


def test_skipped_frames_end_a_flying_mode_after_their_timeout_a_complete_one_resets_it():
    """Frames skipped in a row (a needed product late or lost) for > 0.2 s: FAILSAFE.

    Each skipped frame is counted and nothing of it is used; a complete frame between ends
    the run. Decided on the frames' stamps, before the bridge's 0.25 s hold runs out.
    """
    sup = started()
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    feed(sup, 0.02, xi, v)                             # a complete frame at 0.02
    for k in range(2, 12):                             # skipped 0.04 ... 0.22: 0.2 s
        assert sup.frame_skipped(0.02 * k, ('flow_front',)) == []
        sup.on_imu(0.02 * k, R)
    feed(sup, 0.24, xi, v)                             # complete: the run ends
    assert sup.mode == Mode.WINDOW and sup.skipped_frames == 10
    for k in range(13, 24):                            # skipped 0.26 ... 0.46
        sup.on_imu(0.02 * k, R)
        done = sup.frame_skipped(0.02 * k, ('window',))
        if 0.02 * k - 0.24 <= 0.2 + 1e-9:
            assert done == [] and sup.mode == Mode.WINDOW
    assert sup.mode == Mode.FAILSAFE
    reason = sup.transitions[-1].reason
    assert 'skipped in a row without window (lost' in reason and '0.2 s' in reason
    assert sup.transitions[-1].t == pytest.approx(0.46)


def test_skipped_frames_in_idle_do_not_fail_safe():
    sup = ModeSupervisor(SupervisorConfig())
    for k in range(50):
        sup.on_imu(0.02 * k, R)
        assert sup.frame_skipped(0.02 * k, ('window',)) == []
    assert sup.mode == Mode.IDLE


def test_at_a_coarse_stride_it_takes_three_skipped_frames_as_well_as_the_timeout():
    sup = started()
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    feed(sup, 0.08, xi, v)                             # complete, then every 80 ms skipped
    for k, t in enumerate((0.16, 0.24, 0.32)):
        sup.on_imu(t, R)
        sup.frame_skipped(t, ('flow_front',))
        assert sup.mode == (Mode.WINDOW if k < 2 else Mode.FAILSAFE), (t, sup.mode)


def skipped_window_frames(products):
    """WINDOW with a complete frame at 0.02 s, then frames 0.04-0.78 s skipped for want of the
    window and front flow; ``products(k, t)``: the (name, stamp) of the products that came
    meanwhile. Checks that the mode holds for 0.5 s; returns the supervisor."""
    sup = started()
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    feed(sup, 0.02, xi, v)
    for k in range(2, 40):
        t = 0.02 * k
        sup.on_imu(t, R)
        sup.frame_skipped(t, ('window', 'flow_front'))
        for name, stamp in products(k, t):
            sup.product_seen(name, stamp)
        if t <= 0.02 + 0.5:
            assert sup.mode == Mode.WINDOW, t
    return sup


def test_products_that_come_late_are_not_lost_the_staleness_timeouts_judge_them():
    """A computer that falls behind: the frames are skipped, their products come late.

    Not the skipped-frames rule (for products that never come) but the 0.5 s staleness of
    the window and front flow ends the mode, if the lateness lasts.
    """
    sup = skipped_window_frames(lambda k, t: (('window', t), ('flow_front', t)))
    assert sup.mode == Mode.FAILSAFE
    assert 'stale' in sup.transitions[-1].reason


def test_products_of_newer_frames_show_a_node_behind_not_a_dead_one():
    """Nodes behind skip images for the newest: the products of the skipped frames never
    come, those of later frames do (not complete: the other product is for yet another)."""
    sup = skipped_window_frames(
        lambda k, t: (('window' if k % 2 else 'flow_front', t + 0.02),))
    assert 'stale' in sup.transitions[-1].reason


def test_a_product_older_than_the_skipped_frames_does_not_show_its_node_alive():
    sup = started()
    xi, v = np.array([-2.0, 0.0, -1.6]), np.array([0.3, 0, 0])
    feed(sup, 0.02, xi, v)
    for k in range(2, 30):
        t = 0.02 * k
        sup.on_imu(t, R)
        sup.frame_skipped(t, ('window',))
        sup.product_seen('window', 0.02)             # a replay of the last complete frame's
    assert sup.mode == Mode.FAILSAFE and '(lost' in sup.transitions[-1].reason


def test_a_product_the_new_mode_switched_on_gets_its_staleness_timeout_to_appear():
    """At WINDOW's start the front flow computes its first frames (a slow computer: longer
    than the 0.2 s of the skipped-frames rule): not lost, but stale after 0.5 s if it never
    comes."""
    sup = started()                                  # WINDOW at t = 0, no front flow yet
    for k in range(1, 40):
        t = 0.02 * k
        sup.on_imu(t, R)
        sup.frame_skipped(t, ('flow_front',))
        if t <= 0.5:
            assert sup.mode == Mode.WINDOW, t
    assert sup.mode == Mode.FAILSAFE
    reason = sup.transitions[-1].reason
    assert reason.endswith('stale for more than 0.5 s in WINDOW') and '(lost' not in reason
    assert sup.transitions[-1].t == pytest.approx(0.52)
