"""FrameGate: frames leave in order, when their inputs are in, after the wait, or on overflow."""
import numpy as np
import pytest

from ibvs_perception.core.attitude_buffer import AttitudeBuffer, AttitudeBufferConfig
from ibvs_perception.core.frame_gate import FrameGate


def test_held_until_ready_then_released_once():
    gate = FrameGate(max_wait_s=0.05)
    assert gate.push(1.00, 'a', now_s=10.0) is None
    inputs_in = set()
    assert gate.release(lambda s: s in inputs_in, now_s=10.01) == []
    inputs_in.add(1.00)
    (frame,) = gate.release(lambda s: s in inputs_in, now_s=10.02)
    assert (frame.stamp_s, frame.payload) == (1.00, 'a')
    assert gate.release(lambda s: True, now_s=10.03) == []
    assert gate.released_without_inputs == 0


def test_released_after_the_wait_without_inputs():
    gate = FrameGate(max_wait_s=0.05)
    gate.push(2.0, 'b', now_s=0.0)
    assert gate.release(lambda s: False, now_s=0.049) == []
    assert [f.payload for f in gate.release(lambda s: False, now_s=0.050)] == ['b']
    assert gate.released_without_inputs == 1


def test_a_newer_frame_does_not_make_the_held_one_skip_its_inputs():
    # lockstep start: frame 1 arrives before the IMU sample of frame 0
    gate = FrameGate(max_wait_s=1.0)
    inputs_in = set()
    assert gate.push(1.00, 'f0', now_s=0.0) is None
    assert gate.push(1.02, 'f1', now_s=0.001) is None
    assert gate.release(lambda s: s in inputs_in, now_s=0.002) == []
    inputs_in.add(1.02)                       # frame 1's inputs first: it still waits its turn
    assert gate.release(lambda s: s in inputs_in, now_s=0.003) == []
    inputs_in.add(1.00)
    assert [f.payload for f in gate.release(lambda s: s in inputs_in, now_s=0.004)] == [
        'f0', 'f1']
    assert gate.released_without_inputs == 0


def test_overflow_hands_back_the_oldest_frame_in_order():
    gate = FrameGate(max_wait_s=1.0, max_held=2)
    gate.push(1.00, 'a', now_s=0.0)
    gate.push(1.02, 'b', now_s=0.0)
    assert gate.push(1.04, 'c', now_s=0.0).payload == 'a'
    assert [f.payload for f in gate.held] == ['b', 'c']
    assert gate.released_without_inputs == 1


def test_negative_wait_or_no_room_is_refused():
    with pytest.raises(ValueError):
        FrameGate(max_wait_s=-0.1)
    with pytest.raises(ValueError):
        FrameGate(max_wait_s=0.1, max_held=0)


def test_attitude_buffer_covers_a_stamp_only_up_to_its_newest_sample():
    buf = AttitudeBuffer(AttitudeBufferConfig())
    assert buf.newest_stamp is None and not buf.covers(0.0)
    buf.add(1.0, np.eye(3), np.zeros(3))
    buf.add(1.01, np.eye(3), np.zeros(3))
    assert buf.newest_stamp == 1.01
    assert buf.covers(1.01) and buf.covers(1.005) and not buf.covers(1.0100001)
