"""The image counters' status: what changed since the last period sets the level."""
from diagnostic_msgs.msg import DiagnosticStatus

from ibvs_perception.image_diagnostics import image_status, ImageCounts, ProcessingTimer


def values(status):
    return {kv.key: kv.value for kv in status.values}


def test_status_is_ok_while_every_grid_frame_is_computed():
    s = image_status('pad_detector', ImageCounts(computed=50, off_grid=50, missed=2,
                                                 superseded=1),
                     ImageCounts(computed=25, off_grid=25, missed=2), 3.25)
    assert s.name == 'pad_detector: images' and s.level == DiagnosticStatus.OK
    assert values(s) == {'images_computed': '50', 'images_off_grid': '50',
                         'grid_frames_missed': '2', 'images_superseded': '1',
                         'images_without_attitude': '0',
                         'processing_median_ms': '3.2'}


def test_status_warns_for_frames_lost_or_attitudes_missing_in_the_last_period():
    lost = image_status('w', ImageCounts(computed=10, missed=3), ImageCounts(missed=1), None)
    assert lost.level == DiagnosticStatus.WARN and lost.message.startswith('2 grid frame(s)')
    assert values(lost)['processing_median_ms'] == 'unknown'
    blind = image_status('w', ImageCounts(no_attitude=4), ImageCounts(no_attitude=3), 1.0)
    assert blind.level == DiagnosticStatus.WARN and '1 image(s) without attitude' in \
        blind.message


def test_processing_timer_keeps_the_duration_even_when_processing_raises():
    timer = ProcessingTimer()
    assert timer.median_ms() is None
    calls = []
    timer.run(calls.append, 1)

    def fail():
        raise RuntimeError('bad frame')
    try:
        timer.run(fail)
    except RuntimeError:
        pass
    assert calls == [1] and timer.median_ms() is not None and timer.median_ms() >= 0.0
