"""StampSynchronizer and AttitudeHistory of the force controller (pure, no ROS)."""
import numpy as np
import pytest

from ibvs_control.core.frames import rot_z
from ibvs_control.core.modes import Mode
from ibvs_control.core.stamp_sync import (
    AttitudeHistory, InputKind, ModeTracker, PadPairing, StampSynchronizer)

W, P, FF = InputKind.WINDOW, InputKind.PAD, InputKind.FLOW_FRONT


def test_release_rules_order_timeout_and_drops():
    s = StampSynchronizer(timeout_s=0.03, optional=())
    assert s.add(W, 100, 'w1', 0.0) == ([], '')
    out, _ = s.add(P, 100, 'p1', 0.001)                 # both detections: released at once
    assert [b.stamp_ns for b in out] == [100] and not out[0].timed_out
    assert s.add(W, 200, 'w2', 0.02) == ([], '')        # pad never comes for 200
    out, _ = s.add(W, 300, 'w3', 0.025)
    out2, _ = s.add(P, 300, 'p3', 0.026)                # 300 complete: 200 released first
    assert [b.stamp_ns for b in out + out2] == [200, 300]
    assert out2[0].timed_out and out2[0].get(P) is None and not out2[1].timed_out
    assert s.add(W, 200, 'late', 0.03)[1] != ''         # answered stamp: dropped
    s.add(W, 400, 'w4', 0.04)
    assert 'duplicate' in s.add(W, 400, 'again', 0.041)[1]
    assert s.poll(0.05) == []
    out = s.poll(0.071)                                 # 30 ms after the first input
    assert [b.stamp_ns for b in out] == [400] and out[0].timed_out
    assert s.dropped == 2


def test_flow_expected_after_it_came_late_and_forgotten_after_patience():
    s = StampSynchronizer(timeout_s=0.03, flow_patience=3, optional=(FF,))
    s.add(W, 1, 'w', 0.0)
    assert s.add(P, 1, 'p', 0.0)[0] == []               # flows are expected from the start
    assert len(s.poll(0.031)) == 1
    assert s.add(FF, 1, 'f', 0.032)[1] != ''            # late: dropped, still expected
    s.add(W, 2, 'w', 0.02)
    assert s.add(P, 2, 'p', 0.02)[0] == []              # waits for the flow
    out, _ = s.add(FF, 2, 'f', 0.021)
    assert len(out) == 1 and out[0].get(FF) == 'f'
    # one flow missing under load does not make the next frame go without waiting for it
    s.add(W, 3, 'w', 0.04)
    s.add(P, 3, 'p', 0.04)
    assert len(s.poll(0.071)) == 1                      # timed out without its flow
    s.add(W, 4, 'w', 0.08)
    assert s.add(P, 4, 'p', 0.08)[0] == []              # still waited for
    out, _ = s.add(FF, 4, 'f', 0.09)
    assert out[0].get(FF) == 'f'
    # a flow that stopped costs flow_patience timeouts, then no more waiting
    t = 0.1
    for stamp in (5, 6, 7):
        s.add(W, stamp, 'w', t)
        assert s.add(P, stamp, 'p', t)[0] == []
        assert len(s.poll(t + 0.031)) == 1
        t += 0.05
    s.add(W, 8, 'w', t)
    assert len(s.add(P, 8, 'p', t)[0]) == 1


def test_attitude_history_picks_at_or_before():
    h = AttitudeHistory(horizon_ns=1000)
    assert h.at(5) is None
    for k in range(5):
        h.add(100 * k, rot_z(0.1 * k))
    assert np.allclose(h.at(250), rot_z(0.2))
    assert np.allclose(h.at(300), rot_z(0.3))
    assert np.allclose(h.at(-10), rot_z(0.0))           # all newer: the oldest
    assert not h.add(50, np.eye(3))                     # older than the newest: ignored


def test_wait_for_imu_holds_a_complete_bundle_until_the_imu_reaches_its_stamp():
    s = StampSynchronizer(timeout_s=1.0, wait_for_imu=True, optional=())
    s.note_imu(90)
    assert s.add(InputKind.WINDOW, 100, None, now=0.0)[0] == []
    released, _ = s.add(InputKind.PAD, 100, None, now=0.0)
    assert released == []                       # window + pad in, IMU only up to 90 ns
    assert s.note_imu(95) == []
    out = s.note_imu(100)                       # the sample at the stamp completes it
    assert [b.stamp_ns for b in out] == [100] and not out[0].timed_out
    assert s.note_imu(100) == []                # not twice
    assert s.newest_stamp_ns() == 100


def test_wait_for_imu_still_times_out_without_imu():
    s = StampSynchronizer(timeout_s=0.03, wait_for_imu=True)
    s.add(InputKind.WINDOW, 100, None, now=0.0)
    s.add(InputKind.PAD, 100, None, now=0.0)
    out = s.poll(now=0.05)
    assert [b.stamp_ns for b in out] == [100] and out[0].timed_out


def test_pad_pairing_pairs_landmarks_with_the_groups_that_follow():
    pairing = PadPairing()
    b8 = np.tile([0.0, 0.0, 1.0], (8, 1))
    pairing.add_landmarks(5, b8)
    stamp, bearings, groups = pairing.add_groups(('A', 'B'))
    assert stamp == 5 and bearings is b8 and groups == ('A', 'B')
    # groups alone (their landmarks were refused) are dropped, never kept for later landmarks
    assert pairing.add_groups(('B', 'C')) is None
    pairing.add_landmarks(6, None)
    assert pairing.add_groups(()) == (6, None, ())
    # a count mismatch is not a pair
    pairing.add_landmarks(7, b8[:4])
    assert pairing.add_groups(('A', 'B')) is None
    assert pairing.unpaired == 2


def test_mode_tracker_flies_the_status_of_the_frame_else_the_latest_mode():
    s = StampSynchronizer(timeout_s=0.03, optional=(InputKind.MODE,))
    modes = ModeTracker()
    s.add(InputKind.MODE, 100, Mode.WINDOW, 0.0)
    s.add(InputKind.WINDOW, 100, None, 0.0)
    (first,), _ = s.add(InputKind.PAD, 100, None, 0.0)
    assert modes.mode_at(first) == Mode.WINDOW
    # the supervisor's CROSSING for frame 120 arrives after a late ibvs/mode LANDING note:
    # frame 120 still flies the mode reported for its own stamp
    s.add(InputKind.WINDOW, 120, None, 0.0)
    s.add(InputKind.PAD, 120, None, 0.0)
    modes.note(Mode.LANDING)
    (bundle,), _ = s.add(InputKind.MODE, 120, Mode.CROSSING, 0.0)
    assert modes.mode_at(bundle) == Mode.CROSSING
    # a frame released without its status (timed out) flies the latest mode known
    modes.note(Mode.FAILSAFE)
    s.add(InputKind.WINDOW, 140, None, 1.0)
    s.add(InputKind.PAD, 140, None, 1.0)
    (late,) = s.poll(2.0)
    assert late.timed_out and modes.mode_at(late) == Mode.FAILSAFE
    assert modes.frames_without_status == 1


def test_synchroniser_waits_for_an_expected_mode_like_a_flow():
    s = StampSynchronizer(timeout_s=0.03, optional=(InputKind.MODE,))
    s.add(InputKind.MODE, 20, Mode.WINDOW, 0.0)     # expected from the start
    s.add(InputKind.WINDOW, 20, None, 0.0)
    released, _ = s.add(InputKind.PAD, 20, None, 0.0)
    assert [b.stamp_ns for b in released] == [20]
    s.add(InputKind.WINDOW, 40, None, 0.0)
    released, _ = s.add(InputKind.PAD, 40, None, 0.0)
    assert released == []                           # waits for the supervisor's status
    released, _ = s.add(InputKind.MODE, 40, Mode.WINDOW, 0.0)
    assert [b.get(InputKind.MODE) for b in released] == [Mode.WINDOW]
    with pytest.raises(ValueError):
        StampSynchronizer(timeout_s=0.03, required=(InputKind.MODE,), optional=(InputKind.MODE,))


def test_a_bundle_says_what_it_was_released_without():
    s = StampSynchronizer(timeout_s=0.03, wait_for_imu=True, optional=(FF,))
    s.note_imu(20)
    s.add(W, 20, None, 0.0)
    s.add(P, 20, None, 0.0)
    (complete,), _ = s.add(FF, 20, None, 0.0)    # an all-NaN "no flow" is an input that came
    assert complete.missing == () and not complete.timed_out
    s.note_imu(40)
    s.add(W, 40, None, 0.0)
    (late,) = s.poll(1.0)                         # no pad, no front flow for 40
    assert late.timed_out and late.missing == ('pad', 'flow_front')
    s.add(W, 60, None, 1.0)
    s.add(P, 60, None, 1.0)
    s.add(FF, 60, None, 1.0)
    (no_imu,) = s.poll(2.0)
    assert no_imu.missing == ('imu',)


def test_check_flow_converts_map_to_the_paper_frame_and_refuses_bad_input():
    from ibvs_control.core.stamp_sync import check_flow
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
