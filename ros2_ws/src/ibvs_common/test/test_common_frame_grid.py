"""The frame grid: every node picks the same frames from the same stamps."""
import pytest

from ibvs_common.core.frame_grid import FrameGrid, MAX_STRIDE, period_ns

MS = 1_000_000


def test_stride_one_takes_every_frame():
    grid = FrameGrid(20 * MS)
    assert all(grid.on_grid(k * 20 * MS + 3) for k in range(100))


def test_every_stride_th_frame_from_the_reference_frame_despite_jitter():
    # a 50 Hz camera whose stamps start at an arbitrary phase and jitter by +-4 ms
    ref = 1_700_000_000_123_456_789
    jitter = [0, 3, -4, 2, -1, 4, -3, 1]
    stamps = [ref + k * 20 * MS + jitter[k % len(jitter)] * MS for k in range(40)]
    for stride in (2, 4):
        grid = FrameGrid(20 * MS, stride, ref)
        picked = [k for k, s in enumerate(stamps) if grid.on_grid(s)]
        assert picked == list(range(0, 40, stride))


def test_two_nodes_with_references_a_stride_apart_pick_the_same_frames():
    stamps = [5 * MS + k * 33_333_333 for k in range(30)]       # 30 Hz
    p = period_ns(30.0)
    a = FrameGrid(p, 2, stamps[4])
    b = FrameGrid(p, 2, stamps[10])      # a later status: the same grid
    assert [a.on_grid(s) for s in stamps] == [b.on_grid(s) for s in stamps]


def test_with_stride_keeps_the_period_and_moves_the_reference():
    grid = FrameGrid(20 * MS).with_stride(4, 100 * MS)
    assert (grid.period_ns, grid.stride, grid.ref_ns) == (20 * MS, 4, 100 * MS)
    assert grid.on_grid(180 * MS) and not grid.on_grid(160 * MS)


@pytest.mark.parametrize('period, stride', [(0, 1), (-5, 1), (20 * MS, 0),
                                            (20 * MS, MAX_STRIDE + 1)])
def test_a_bad_grid_is_refused(period, stride):
    with pytest.raises(ValueError):
        FrameGrid(period, stride)


def test_period_of_a_rate():
    assert period_ns(50.0) == 20 * MS and period_ns(30.0) == 33_333_333
    with pytest.raises(ValueError):
        period_ns(0.0)


def test_a_follower_keeps_the_old_grid_before_a_smaller_strides_reference():
    """Stride 2 from frame 0; then stride 1 announced from frame 10: frames 1-9 are still
    judged on stride 2 (the supervisor expects them so), every frame from 10 on; a larger
    stride applies at once."""
    from ibvs_common.core.frame_grid import GridFollower
    period = 20_000_000
    f = GridFollower(period)
    assert all(f.on_grid_at(k * period) for k in range(5))
    f.update(2, 0)
    assert [f.on_grid_at(k * period) for k in range(4)] == [True, False, True, False]
    f.update(1, 10 * period)
    assert [f.on_grid_at(k * period) for k in (7, 8, 9, 10, 11)] == [
        False, True, False, True, True]
    f.update(4, 12 * period)
    assert [f.on_grid_at(k * period) for k in (9, 12, 13, 16)] == [False, True, False, True]


def test_the_grid_and_held_flow_messages_round_trip_and_refuse_bad_values():
    from diagnostic_msgs.msg import KeyValue
    from ibvs_common.node_common import (frame_grid_msg, grid_from_msg, held_from_status,
                                         held_key, supervisor_status_msg)
    msg = frame_grid_msg({'front': (1, 100, 2, 120), 'down': (2, 40)}, 0)
    assert grid_from_msg(msg, 'front') == (1, 100)
    assert grid_from_msg(msg, 'front', flow=True) == (2, 120)
    assert grid_from_msg(msg, 'down', flow=True) == (2, 40)     # no flow grid: the frame grid
    assert grid_from_msg(msg, 'side') is None
    status = supervisor_status_msg(140, 1, 'WINDOW', b'\x00', {held_key('flow_front'): 120},
                                   'front')
    assert held_from_status(status) == ({'flow_front': 120}, '')
    status.status[0].values.append(KeyValue(key=held_key('flow_down'), value='12.5'))
    held, err = held_from_status(status)
    assert held == {} and 'flow_down_from_ns' in err and 'not an integer' in err
