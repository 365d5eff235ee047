"""The timing layer (core/timing.py) and one frame's message checks (core/frame_io.py)."""
from unittest import mock

import cv2
import numpy as np
import pytest

from ibvs_control.core.frame_inputs import check_flow, PadPairing
from ibvs_common.core.modes import Mode
from ibvs_common.core import attitude_buffer
from ibvs_common.core.attitude_buffer import AttitudeBuffer, AttitudeBufferConfig
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.frames import (quat_from_rot, R_IB_from_quat_map_base,
                                     rot_map_base_from_R_IB)
from ibvs_common.core.modes import Camera, InputKind, MODE_INPUTS
from ibvs_control.core.timing import FrameAssembler

W, P, FF, FD = InputKind.WINDOW, InputKind.PAD, InputKind.FLOW_FRONT, InputKind.FLOW_DOWN
MS = 1_000_000


def assembler(deadline_s=0.04):
    """The controller's use: a frame is tagged with its mode and waits for that mode's needs."""
    return FrameAssembler(deadline_s, lambda mode: MODE_INPUTS[mode].needed)


def test_each_mode_waits_for_the_products_the_issue_names_and_no_other():
    needs = {m: (MODE_INPUTS[m].camera, MODE_INPUTS[m].needed) for m in Mode}
    assert needs[Mode.WINDOW] == (Camera.FRONT, {W, FF})
    assert needs[Mode.CROSSING] == (Camera.DOWN, {FD})
    assert needs[Mode.LANDING] == (Camera.DOWN, {P, FD})
    assert needs[Mode.IDLE] == (Camera.FRONT, {W})          # its cue to start
    assert needs[Mode.SHUTDOWN][1] == needs[Mode.FAILSAFE][1] == frozenset()


def test_a_frame_leaves_as_soon_as_its_needed_products_are_in_in_either_order():
    a = assembler()
    a.add_input(FF, 100 * MS, 'phi')                 # product before the frame is opened
    assert a.open(100 * MS, Mode.WINDOW, now_ns=100 * MS)
    assert a.release(now_ns=101 * MS) == []          # window missing, deadline not reached
    a.add_input(W, 100 * MS, 'corners')
    (frame,) = a.release(now_ns=101 * MS)
    assert frame.stamp_ns == 100 * MS and not frame.expired and frame.missing == ()
    assert frame.get(W) == 'corners' and frame.get(FF) == 'phi' and frame.tag == Mode.WINDOW


def test_a_product_the_mode_does_not_need_never_delays_a_frame():
    a = assembler()
    a.open(100 * MS, Mode.CROSSING, now_ns=100 * MS)
    a.add_input(FD, 100 * MS, 'phi_t')               # no pad detection (a dead detector)
    (frame,) = a.release(now_ns=100 * MS)
    assert frame.missing == () and frame.get(P) is None
    a.add_input(P, 120 * MS, 'pad')                  # a pad that did come is carried along,
    a.add_input(FD, 120 * MS, 'phi_t')
    a.open(120 * MS, Mode.CROSSING, now_ns=120 * MS)
    (frame,) = a.release(now_ns=120 * MS)
    assert frame.get(P) is None and frame.extras == {P: 'pad'}   # apart from the inputs


def test_a_frame_is_the_same_whether_an_unneeded_product_came_before_or_after_it():
    """The inputs of a frame do not depend on scheduling: unneeded ones are extras or late."""
    early, late = assembler(), assembler()
    early.add_input(P, 100 * MS, 'pad')
    for a in (early, late):
        a.open(100 * MS, Mode.CROSSING, now_ns=100 * MS)
        a.add_input(FD, 100 * MS, 'phi_t')
    (f_early,), (f_late,) = early.release(100 * MS), late.release(100 * MS)
    assert f_early.inputs == f_late.inputs == {FD: 'phi_t'}
    assert f_early.extras == {P: 'pad'} and f_late.extras == {}


def test_the_deadline_counts_on_the_given_clock_from_the_frame_stamp():
    a = assembler(deadline_s=0.04)
    a.open(100 * MS, Mode.LANDING, now_ns=100 * MS)
    a.add_input(FD, 100 * MS, 'phi_t')
    assert a.next_deadline_ns() == 140 * MS
    # a clock that stands still (lockstep) never expires it, however long the wall clock runs
    assert a.release(now_ns=100 * MS) == []
    assert a.release(now_ns=139 * MS) == []
    (frame,) = a.release(now_ns=140 * MS)
    assert frame.expired and frame.missing == (P,) and a.expired == 1
    assert a.next_deadline_ns() is None


def test_a_frame_whose_missing_product_was_passed_leaves_before_its_deadline():
    """Each kind comes in stamp order: a newer one means this frame's will never come."""
    a = assembler(deadline_s=0.04)
    a.open(100 * MS, Mode.CROSSING, now_ns=100 * MS)    # a handover frame of the front camera
    a.add_input(W, 120 * MS, 'corners')                 # another kind passing: no release
    assert a.release(now_ns=101 * MS) == []
    a.add_input(FD, 117 * MS, 'phi_t')                  # the down camera's next image
    (frame,) = a.release(now_ns=118 * MS)
    assert frame.passed and not frame.expired and frame.missing == (FD,)
    assert a.passed == 1 and a.expired == 0 and a.was_skipped(100 * MS)
    # the same stamp arriving is what completes it (synchronised cameras)
    a.open(140 * MS, Mode.CROSSING, now_ns=140 * MS)
    a.add_input(FD, 140 * MS, 'phi_t')
    (frame,) = a.release(now_ns=140 * MS)
    assert frame.complete and not frame.passed
    # after a reset (a clock step), nothing counts as passed
    a.reset()
    a.open(100 * MS, Mode.CROSSING, now_ns=100 * MS)
    assert a.release(now_ns=101 * MS) == []


def test_a_frame_holding_a_shed_flow_takes_the_flow_frame_before_it_never_an_older_one():
    """Flows shed: the frame at 140 ms takes the flow of 120 ms (within 110-130 ms)."""
    a = assembler()
    held = {FF: (110 * MS, 130 * MS)}
    a.add_input(FF, 100 * MS, 'phi_100')              # older than the window: never taken
    a.add_input(W, 140 * MS, 'corners_140')
    assert a.open(140 * MS, Mode.WINDOW, now_ns=140 * MS, held=held)
    assert a.release(now_ns=141 * MS) == []           # the 120 ms flow is not in yet
    a.add_input(FF, 121 * MS, 'phi_121')              # a stamp that jittered by 1 ms
    (frame,) = a.release(now_ns=142 * MS)
    assert frame.complete and frame.get(FF) == 'phi_121' and frame.held == {FF: 121 * MS}
    assert frame.get(W) == 'corners_140'
    # a frame's own flow, if one came anyway, is not what it holds
    a.add_input(FF, 160 * MS, 'phi_160')
    a.add_input(FF, 180 * MS, 'phi_180')
    a.add_input(W, 180 * MS, 'corners_180')
    a.open(180 * MS, Mode.WINDOW, now_ns=180 * MS, held={FF: (150 * MS, 170 * MS)})
    (frame,) = a.release(now_ns=181 * MS)
    assert frame.get(FF) == 'phi_160' and frame.extras == {}
    # the held flow never came and a newer one did: skipped before its deadline
    a.add_input(W, 220 * MS, 'corners_220')
    a.open(220 * MS, Mode.WINDOW, now_ns=220 * MS, held={FF: (190 * MS, 210 * MS)})
    assert a.release(now_ns=221 * MS) == []
    a.add_input(FF, 240 * MS, 'phi_240')
    (frame,) = a.release(now_ns=241 * MS)
    assert frame.passed and frame.missing == (FF,) and frame.held == {}


def test_frames_leave_in_stamp_order_and_a_late_or_repeated_one_is_refused():
    a = assembler()
    a.open(120 * MS, Mode.SHUTDOWN, now_ns=121 * MS)      # needs nothing: ready at once
    a.open(100 * MS, Mode.WINDOW, now_ns=121 * MS)        # older, waiting
    assert a.release(now_ns=121 * MS) == []               # 120 does not overtake 100
    assert a.release(now_ns=160 * MS) == []               # 100 opened at 121: waits 40 ms
    out = a.release(now_ns=161 * MS)                      # 100 expires, then 120 goes
    assert [f.stamp_ns for f in out] == [100 * MS, 120 * MS]
    assert not out[0].complete and out[1].complete and a.was_skipped(100 * MS)
    assert not a.open(110 * MS, Mode.IDLE, now_ns=141 * MS)   # older than one answered
    assert not a.open(120 * MS, Mode.IDLE, now_ns=141 * MS)   # answered already
    a.open(160 * MS, Mode.IDLE, now_ns=161 * MS)
    assert not a.open(160 * MS, Mode.IDLE, now_ns=161 * MS)   # open already
    assert a.add_input(W, 160 * MS, 'x') and not a.add_input(W, 160 * MS, 'y')


def test_latest_before_is_strictly_older_and_bounded_in_age():
    a = assembler()
    for t in (40, 60, 80):
        a.add_input(W, t * MS, t)
    assert a.latest_before(W, 80 * MS, 100 * MS) == (60 * MS, 60)
    assert a.latest_before(W, 81 * MS, 100 * MS) == (80 * MS, 80)
    assert a.latest_before(W, 200 * MS, 100 * MS) is None      # 80 ms is 120 ms old
    assert a.latest_before(W, 40 * MS, 100 * MS) is None


def test_the_assembler_refuses_a_bad_deadline():
    with pytest.raises(ValueError):
        assembler(deadline_s=0.0)
    with pytest.raises(ValueError):
        assembler(deadline_s=float('nan'))
    with pytest.raises(ValueError):
        AttitudeBufferConfig(max_extrapolation_s=-1.0)


def rot(rotvec):
    """Rotation matrix of a rotation vector by OpenCV's Rodrigues (a second implementation)."""
    return cv2.Rodrigues(np.asarray(rotvec, dtype=float).reshape(3, 1))[0]


def test_attitude_at_a_stamp_is_interpolated_or_propagated_never_waited_for():
    w = np.array([0.3, -0.2, 0.5])                   # rad/s, constant body rate
    buf = AttitudeBuffer(AttitudeBufferConfig())
    for k in range(5):                               # 100 Hz samples of R(t) = exp(S(w) t)
        t = 1.0 + 0.01 * k
        buf.add(t, rot(w * (t - 1.0)), w)
    # between samples: the geodesic interpolation is exact for a constant rate
    assert np.allclose(buf.attitude_at(1.015), rot(w * 0.015), atol=1e-9)
    # after the newest sample: propagated with its rate, exact for a constant rate
    assert np.allclose(buf.attitude_at(1.07), rot(w * 0.07), atol=1e-9)
    assert buf.attitude_at(1.04 + 0.051) is None     # beyond max_extrapolation_s (0.05)
    assert buf.attitude_at(0.99) is None             # before the first sample
    with pytest.raises(ValueError):
        buf.add(1.1, np.full((3, 3), np.nan), w)


def test_a_sample_that_comes_after_a_propagated_query_of_its_moment_is_counted_late():
    """An image answered beyond the newest sample, then the sample of its moment: one late."""
    w = np.array([0.3, -0.2, 0.5])
    buf = AttitudeBuffer(AttitudeBufferConfig())
    buf.add(1.00, rot(w * 0.00), w)
    buf.add(1.01, rot(w * 0.01), w)
    assert buf.attitude_at(1.005) is not None       # interpolated: no late sample can follow
    buf.add(1.02, rot(w * 0.02), w)
    assert buf.late_samples == 0 and buf.last_late is None
    assert buf.attitude_at(1.03) is not None        # propagated 10 ms beyond 1.02
    buf.add(1.03, rot(w * 0.03), w)                 # the sample of that image's moment
    assert buf.late_samples == 1 and buf.last_late == (1.03, 1.03)
    buf.add(1.04, rot(w * 0.04), w)                 # after it: on time
    assert buf.late_samples == 1
    # the derotation's gyro integral beyond the newest sample is a propagation too
    assert buf.gyro_rotation(1.03, 1.045) is not None
    buf.add(1.045, rot(w * 0.045), w)
    assert buf.late_samples == 2 and buf.last_late == (1.045, 1.045)
    # a clock step back forgets the queries of the old time: samples after it are not late
    assert buf.attitude_at(1.06) is not None
    assert buf.add(0.5, rot(w * 0.06), w) is True and buf.late_samples == 2


def test_late_imu_samples_are_reported_in_one_throttled_warning_with_the_count():
    from ibvs_common.node_common import LateImuReport
    from ibvs_common.throttled_log import ThrottledLog
    w, now = np.zeros(3), [0.0]
    logger = mock.Mock()
    report = LateImuReport(ThrottledLog(logger, clock=lambda: now[0]), 2.0, 'node: ')
    lines = logger.warning.call_args_list
    buf = AttitudeBuffer(AttitudeBufferConfig())
    buf.add(1.00, np.eye(3), w)
    report.check(buf)
    assert lines == []                              # nothing late: nothing said
    for k in (1, 2, 3):                             # three images answered before their IMU
        buf.attitude_at(1.00 + 0.01 * k)
        buf.add(1.00 + 0.01 * k, np.eye(3), w)
        report.check(buf)
        now[0] += 0.5
    assert len(lines) == 1                          # throttled: 2 s
    first = lines[0].args[0]
    assert first.startswith('node: imu/data sample of t = 1.010 s ')
    assert LateImuReport.TEXT in first and '1 late sample(s) in all' in first
    now[0] += 2.0
    report.check(buf)                               # still unreported ones: said once more
    report.check(buf)
    assert len(lines) == 2 and '3 late sample(s) in all' in lines[1].args[0]
    assert 'image of t = 1.030 s' in lines[1].args[0]


def test_a_sample_given_by_its_ros_quaternion_is_converted_only_when_read(monkeypatch):
    converted = []
    convert = attitude_buffer.R_IB_from_quat_map_base
    monkeypatch.setattr(attitude_buffer, 'R_IB_from_quat_map_base',
                        lambda q: converted.append(q) or convert(q))
    w = np.array([0.3, -0.2, 0.5])
    R0 = rot([0.1, 0.2, 0.3])
    eager, lazy = AttitudeBuffer(), AttitudeBuffer()
    for k in range(50):                              # 0.5 s of 100 Hz samples
        t = 1.0 + 0.01 * k
        q_map_base = quat_from_rot(rot_map_base_from_R_IB(R0 @ rot(w * (t - 1.0))))
        eager.add(t, R_IB_from_quat_map_base(q_map_base), w)
        lazy.add_map_base(t, tuple(q_map_base), w)
    assert converted == []                           # nothing computed before a query
    for t in (1.0, 1.015, 1.2, 1.49, 1.52):
        assert np.array_equal(lazy.attitude_at(t), eager.attitude_at(t))
    assert np.allclose(lazy.attitude_at(1.2), R0 @ rot(w * 0.2), atol=1e-9)   # geometry
    assert len(converted) <= 8                       # only the samples around the stamps read
    for q, omega in (((np.nan, 0.0, 0.0, 0.0), w), ((1.2, 0.0, 0.0, 0.0), w),
                     ((1.0, 0.0, 0.0, 0.0), (np.inf, 0.0, 0.0))):
        with pytest.raises(ValueError):
            lazy.add_map_base(2.0, q, omega)
    assert len(lazy) == 50


def test_pad_pairing_pairs_by_stamp_in_either_order():
    pairing = PadPairing()
    b8 = np.tile([0.0, 0.0, 1.0], (8, 1))
    assert pairing.add_landmarks(5, b8) is None
    stamp, bearings, groups, weights = pairing.add_groups(5, ['A', 'B'], (1.0, 0.25))
    assert stamp == 5 and bearings is b8 and groups == ('A', 'B') and weights == (1.0, 0.25)
    assert pairing.add_groups(6, ()) is None                 # groups first
    assert pairing.add_landmarks(6, None) == (6, None, (), None)
    # a count mismatch is not a pair
    pairing.add_landmarks(7, b8[:4])
    assert pairing.add_groups(7, ('A', 'B')) is None
    assert pairing.unpaired == 1


def test_pad_group_weights_are_read_only_when_one_valid_weight_per_group():
    from builtin_interfaces.msg import Time
    from ibvs_common.node_common import pad_group_weights, pad_groups_msg
    stamp = Time(sec=1)
    assert pad_group_weights(pad_groups_msg(stamp, 'f', ['A', 'B'], [1.0, 0.2])) == (1.0, 0.2)
    for names, weights in ((['A', 'B'], []), (['A', 'B'], [1.0]), (['A'], [-0.1]),
                           (['A'], [float('nan')]), (['A', 'B'], [0.0, 0.0]), ([], [])):
        assert pad_group_weights(pad_groups_msg(stamp, 'f', names, weights)) is None


def test_pad_pairing_never_labels_landmarks_with_another_images_groups():
    """The executor-lag order at a group switch: frame k+1's landmarks before frame k's groups.

    Pairing by arrival (the held landmarks with the next groups) labelled frame k+1's A,B
    bearings with frame k's B,C (same count): the supervisor's pad-image height then used a
    group's bearings with another group's size.
    """
    pairing = PadPairing()
    ab, bc = np.tile([0.0, 0.0, 1.0], (8, 1)), np.tile([0.0, 0.1, 0.995], (8, 1))
    assert pairing.add_landmarks(20, bc) is None             # frame k: B, C
    assert pairing.add_landmarks(40, ab) is None             # frame k+1: A, B (taken first)
    stamp, bearings, groups, _ = pairing.add_groups(20, ('B', 'C'))
    assert stamp == 20 and bearings is bc and groups == ('B', 'C')
    stamp, bearings, groups, _ = pairing.add_groups(40, ('A', 'B'))
    assert stamp == 40 and bearings is ab and groups == ('A', 'B')
    assert pairing.unpaired == 0
    # a lost half: the other one is dropped once a newer pair completes, never mispaired
    pairing.add_landmarks(60, bc)                            # its groups are lost
    assert pairing.add_groups(80, ('A', 'B')) is None        # its landmarks are late
    assert pairing.add_landmarks(80, ab) == (80, ab, ('A', 'B'), None)
    assert pairing.unpaired == 1
    # refused landmarks: their groups are forgotten
    pairing.add_groups(100, ('A', 'B'))
    pairing.drop(100)
    assert pairing.add_landmarks(100, ab) is None
    # halves that never pair are bounded by depth
    for k in range(10):
        pairing.add_groups(200 + k, ('A',))
    assert pairing.unpaired == 1 + 10 - pairing.depth


def test_check_flow_converts_map_to_the_paper_frame_and_refuses_bad_input():
    # map is ENU, {I} is (north, east, down): a flow east in map is +y in {I}
    phi_I, err = check_flow(np.array([1.0, 0.0, 0.0]), 'map')
    assert err == '' and np.allclose(phi_I, [0.0, 1.0, 0.0])
    phi_I, err = check_flow(np.array([0.0, 0.0, 2.0]), 'map')
    assert np.allclose(phi_I, [0.0, 0.0, -2.0])
    phi_I, err = check_flow(np.array([np.nan, 0.0, 0.0]), 'map')     # partly NaN: refused
    assert phi_I is None and 'non-finite' in err
    phi_I, err = check_flow(np.array([np.inf, np.inf, np.inf]), 'map')
    assert phi_I is None and err
    # all three NaN: "no valid flow at this stamp", an input that came, not an error
    assert check_flow(np.full(3, np.nan), 'map') == (None, '')
    assert check_flow(np.full(3, np.nan), 'odom')[1]                 # wrong frame still refused
    phi_I, err = check_flow(np.zeros(3), 'odom')
    assert phi_I is None and 'odom' in err


def test_the_backstep_watch_reports_a_step_back_beyond_its_tolerance_once():
    watch = BackstepWatch(max_backstep_s=0.1)
    assert [watch.observe(t * MS) for t in (0, 20, 40, 40, 35)] == [0] * 5  # 5 ms: jitter
    assert watch.newest_ns == 40 * MS
    assert watch.observe(-61 * MS) == 101 * MS and watch.steps == 1     # 101 ms back
    assert watch.observe(-41 * MS) == 0 and watch.newest_ns == -41 * MS  # from the step on
    assert watch.observe(-141 * MS) == 0                                 # exactly 0.1 s back
    with pytest.raises(ValueError):
        BackstepWatch(max_backstep_s=0.0)


def test_after_a_clock_step_back_no_attitude_mixes_samples_of_two_moments():
    """IMU samples before and after a 0.5 s step back share stamps, not attitudes."""
    w = np.array([0.0, 0.0, 1.0])                    # yaw at 1 rad/s
    buf = AttitudeBuffer(AttitudeBufferConfig())
    added = [buf.add(10.0 + 0.01 * k, rot(w * 0.01 * k), w)   # real time 0 .. 0.5 s,
             for k in range(51)]                                 # stamps 10.0 .. 10.5 s
    # the clock steps back by 0.497 s: real time 0.51 s is stamped 10.013 s
    added += [buf.add(10.013, rot(w * 0.51), w), buf.add(10.023, rot(w * 0.52), w)]
    # 10.018 s is real time 0.515 s: interpolated between the two new samples only (mixed
    # with the old ones, e.g. 10.02 s of real time 0.02 s, it would be far off)
    assert np.allclose(buf.attitude_at(10.018), rot(w * 0.515), atol=1e-9)
    assert buf.attitude_at(10.3) is None             # the old samples are gone
    assert added == [False] * 51 + [True, False] and len(buf) == 2   # dropped once
    # a little out of order (5 ms, within MAX_BACKSTEP_S) is sorted in as before
    assert buf.add(10.018, rot(w * 0.515), w) is False and len(buf) == 3


def test_after_a_clock_step_back_frames_start_again_instead_of_being_refused():
    """Without the reset, every frame of the next 1 s would be 'older than one released'."""
    a = assembler()
    for t in (1000, 1020):
        a.add_input(W, t * MS, 'corners')
        a.add_input(FF, t * MS, 'phi')
        a.open(t * MS, Mode.WINDOW, now_ns=t * MS)
    assert [f.stamp_ns for f in a.release(1020 * MS)] == [1000 * MS, 1020 * MS]
    a.add_input(W, 1040 * MS, 'corners')             # a frame waiting for its flow
    a.open(1040 * MS, Mode.WINDOW, now_ns=1040 * MS)
    # the clock steps back by 1 s: the same stamps come again, from new images
    assert a.add_input(W, 40 * MS, 'new corners')    # not a duplicate of a kept product
    assert a.clock_steps == 1 and not a.has_pending  # the frame of 1040 ms is gone
    assert a.open(40 * MS, Mode.WINDOW, now_ns=40 * MS)
    a.add_input(FF, 40 * MS, 'new phi')              # the flow's go-back: no second reset
    assert a.clock_steps == 1
    (frame,) = a.release(41 * MS)
    assert frame.inputs == {W: 'new corners', FF: 'new phi'} and not frame.expired
    a.add_input(W, 20 * MS, 'x')                     # the watches go on from the step
    assert a.clock_steps == 1
    # a flow still on its way from before the step opens nothing by itself; the go-back
    # of its kind after it is a (second) step: the frame at hand is lost, not a second
    a.add_input(FF, 1060 * MS, 'old phi')
    a.add_input(W, 60 * MS, 'corners 60')
    a.open(60 * MS, Mode.WINDOW, now_ns=60 * MS)
    a.add_input(FF, 60 * MS, 'phi 60')
    assert a.clock_steps == 2 and not a.has_pending
    for t in (80, 100):
        a.add_input(W, t * MS, 'corners')
        a.add_input(FF, t * MS, 'phi')
        assert a.open(t * MS, Mode.WINDOW, now_ns=t * MS)
    assert [f.stamp_ns for f in a.release(101 * MS)] == [80 * MS, 100 * MS]
    # a product late but in its kind's order (older than frames released) is no step
    a.add_input(FD, 30 * MS, 'x')
    a.add_input(FD, 50 * MS, 'x')
    assert a.clock_steps == 2
    a.reset()                                        # a reset restarts every watch
    a.add_input(FD, 10 * MS, 'x')
    assert a.clock_steps == 2
