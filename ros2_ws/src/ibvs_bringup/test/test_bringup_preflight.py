"""Preflight go/no-go: the clock sync, stamp agreement and keep-up checks (pure parts)."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ibvs_bringup.preflight import (diag_value, KEEP_UP_MAX_DELAY_S, KEEP_UP_MIN_FRAMES, KeepUp,
                                    STAMP_AGREEMENT_S, stamps_agree)

S = 1_000_000_000


def test_stamps_on_one_clock_agree_and_a_driver_on_another_clock_fails():
    now = 1_795_000_000 * S                                     # system time, ns
    ms = 1_000_000

    def got(delay_ms, at_ns=now):
        """(stamp, receipt) of a message received at at_ns, stamped delay_ms before."""
        return at_ns - delay_ms * ms, at_ns
    ok, detail = stamps_agree({'front camera': got(20), 'down camera': got(25),
                               'imu': got(5)})
    assert ok and 'front camera -20 ms' in detail
    # the 10 Hz imu/data of a vehicle at rest: its latest sample came 95 ms before the
    # cameras' (with a 5 ms delay): on the same clock, so it agrees
    assert stamps_agree({'front camera': got(20), 'down camera': got(25),
                         'imu': got(5, now - 95 * ms)})[0]
    # a camera driver stamping since its own boot (or an IMU left on the autopilot's boot
    # clock: the 1970 stamps of an unsynced bridge) is far from the others
    ok, _ = stamps_agree({'front camera': (12 * S, now), 'down camera': got(0),
                          'imu': got(0)})
    assert not ok
    late = int((STAMP_AGREEMENT_S + 0.05) * 1e3)                # an IMU 150 ms behind
    assert not stamps_agree({'front camera': got(0), 'down camera': got(0),
                             'imu': got(late)})[0]
    ok, detail = stamps_agree({'front camera': got(0), 'down camera': None, 'imu': got(0)})
    assert not ok and 'down camera' in detail


def test_the_bridge_diagnostics_values_are_read_from_its_mavlink_status():
    msg = DiagnosticArray(status=[
        DiagnosticStatus(name='other', values=[KeyValue(key='clock_synced', value='no')]),
        DiagnosticStatus(name='mavlink_bridge: MAVLink link',
                         values=[KeyValue(key='clock_synced', value='yes'),
                                 KeyValue(key='clock_offset_ms', value='-2.1')])])
    assert diag_value(msg, 'clock_synced') == 'yes'
    assert diag_value(msg, 'clock_offset_ms') == '-2.1'
    assert diag_value(msg, 'missing') is None


# --- the perception keeps up with the front camera (KeepUp) ---------------------------------

MS = 1_000_000
T0 = 1_795_000_000 * S                       # system time, ns
PERIOD = 20 * MS                             # 50 Hz
CAMERA_LATENCY = 35 * MS                     # capture (stamp) -> the frame's arrival


def _frames(keep: KeepUp, n: int, answer_after_ms=None, answered=lambda k: True) -> int:
    """Feed n frames at 50 Hz from T0, arriving CAMERA_LATENCY after their stamp and answered
    answer_after_ms after their arrival; return the last arrival (ns)."""
    for k in range(n):
        t = T0 + k * PERIOD
        rx = t + CAMERA_LATENCY
        keep.note_frame(t, rx)
        keep.note_frame(t, rx + 3 * MS)      # camera_info of the same frame twice: one frame
        if answer_after_ms is not None and answered(k):
            keep.note_answer(t, rx + int(answer_after_ms * MS))
            keep.note_answer(t, rx + int(5 * answer_after_ms * MS))  # a repeat: the first counts
    return T0 + (n - 1) * PERIOD + CAMERA_LATENCY


def test_keep_up_passes_a_detector_that_answers_every_frame_within_a_period():
    keep = KeepUp()
    last = _frames(keep, 80, answer_after_ms=8.0)
    ok, detail = keep.check(last)
    # the last 50 frames are kept; those that arrived less than 0.25 s ago are not judged
    # yet: 37 of them are; the camera's own 35 ms latency is not the graph's
    assert ok, detail
    assert detail == '37 / 37 frames answered, median 8.0 ms after the frame arrived'


def test_keep_up_fails_a_detector_that_skips_frames_or_answers_late():
    keep = KeepUp()
    last = _frames(keep, 80, answer_after_ms=8.0, answered=lambda k: k % 10 != 0)
    ok, detail = keep.check(last)
    assert not ok and detail.startswith('33 / 37 frames answered'), detail   # 89 % < 95 %
    keep = KeepUp()
    last = _frames(keep, 80, answer_after_ms=KEEP_UP_MAX_DELAY_S * 1e3 + 5.0)  # 25 ms
    ok, detail = keep.check(last)
    assert not ok and 'median 25.0 ms' in detail, detail
    keep = KeepUp()
    last = _frames(keep, 80)                                       # a detector not running
    assert keep.check(last) == (False, '0 / 37 frames answered')


def test_keep_up_judges_nothing_too_early_and_restarts_after_a_clock_step_back():
    keep = KeepUp()
    last = _frames(keep, 30, answer_after_ms=8.0)     # 0.58 s of frames: 17 older than 0.25 s
    ok, detail = keep.check(last)
    assert not ok and detail == f'17 frames to judge yet (needs {KEEP_UP_MIN_FRAMES})'
    last = _frames(keep, 80, answer_after_ms=8.0)
    assert keep.check(last)[0]
    keep.note_frame(T0 - S, T0 - S)                   # the system clock stepped back by 1 s
    ok, detail = keep.check(T0 - S)
    assert not ok and 'to judge yet' in detail


def test_camera_timing_judges_the_rate_from_the_stamps_and_the_delivery_latency():
    from ibvs_bringup.preflight import CameraTiming
    ms = 1_000_000
    timing = CameraTiming()
    assert not timing.check(50.0)[0]                       # nothing yet
    for k in range(50):                                    # 50 Hz, delivered 30 ms later
        timing.note(k * 20 * ms, k * 20 * ms + (30 + k % 3) * ms)
    ok, detail = timing.check(50.0)
    assert ok and '50.0 Hz' in detail and '31.0 ms after the stamp' in detail, detail
    assert not timing.check(30.0)[0]                       # vehicle.yaml says 30 Hz: wrong
    late = CameraTiming()
    for k in range(50):                                    # stamped at the end of a transfer
        late.note(k * 20 * ms, k * 20 * ms + 150 * ms)     # ... or far too late to fly on
    assert not late.check(50.0)[0]
    future = CameraTiming()
    for k in range(50):                                    # stamps far ahead of the clock
        future.note(k * 20 * ms, k * 20 * ms - 150 * ms)
    assert not future.check(50.0)[0]
