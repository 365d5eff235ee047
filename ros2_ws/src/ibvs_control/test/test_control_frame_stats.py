"""The supervisor's frame counts: rate held over a second of stamps, skipped, delivery."""
from ibvs_control.core.frame_stats import FrameStats

MS = 1_000_000


def test_rate_held_is_complete_frames_per_second_of_stamps():
    s = FrameStats()
    for k in range(100):                     # 2 s at 50 Hz, every other frame skipped
        s.frame(k * 20 * MS, ('flow_front',) if k % 2 else ())
    newest = 99 * 20 * MS
    assert s.rate_hz(newest) == 25.0 and s.skipped_recently(newest) == 25
    assert (s.complete, s.skipped) == (50, 50)
    v = s.values(newest, 2, 'front')
    assert v['control_rate_hz'] == '25.0' and v['frame_stride'] == '2'
    assert v['frames_skipped_without_flow_front'] == '50'


def test_delivery_latency_is_the_median_first_arrival_after_the_stamp():
    s = FrameStats()
    assert s.delivery_ms('front') is None
    for k, late in enumerate((31, 29, 30, 45, 30)):
        s.opened('front', k * 20 * MS, k * 20 * MS + late * MS)
    assert s.delivery_ms('front') == 30.0
    assert s.values(0, 1, 'front')['front_delivery_latency_ms'] == '30.0'
