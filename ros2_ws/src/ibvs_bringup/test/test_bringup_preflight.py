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
    assert 'missing' not in detail
    lossy = CameraTiming()
    for k in range(74):                                    # every 3rd frame lost on the way
        if k % 3 != 2:
            lossy.note(k * 20 * ms, k * 20 * ms + 30 * ms)
    ok, detail = lossy.check(50.0)                         # the rate is the camera's: 50 Hz
    assert ok and detail.endswith('24 of the last 74 frames missing'), detail
    assert not timing.check(30.0)[0]                       # vehicle.yaml says 30 Hz: wrong
    late = CameraTiming()
    for k in range(50):                                    # stamped at the end of a transfer
        late.note(k * 20 * ms, k * 20 * ms + 150 * ms)     # ... or far too late to fly on
    assert not late.check(50.0)[0]
    future = CameraTiming()
    for k in range(50):                                    # stamps far ahead of the clock
        future.note(k * 20 * ms, k * 20 * ms - 150 * ms)
    assert not future.check(50.0)[0]


# --- the autopilot's set-up: failsafe parameters and armability (from /diagnostics) ---------

def _bridge(**values) -> DiagnosticArray:
    """The bridge's /diagnostics with these values in its MAVLink status."""
    return DiagnosticArray(status=[
        DiagnosticStatus(name='mode_supervisor: frames',
                         values=[KeyValue(key='armed', value='True')]),   # not the bridge's
        DiagnosticStatus(name='mavlink_bridge: MAVLink link',
                         values=[KeyValue(key=k, value=v) for k, v in values.items()])])


def _failsafe(**values):
    from ibvs_bringup.preflight import bridge_values, failsafe_setup
    return failsafe_setup(bridge_values(_bridge(**values)))


def test_px4_failsafe_is_go_only_for_land_mode_within_two_seconds():
    ok, detail = _failsafe(autopilot='px4', COM_OBL_RC_ACT='4', COM_OF_LOSS_T='1')
    assert ok and detail.startswith('PX4 COM_OBL_RC_ACT = 4 (Land mode), COM_OF_LOSS_T = 1 s')
    ok, detail = _failsafe(autopilot='px4', COM_OBL_RC_ACT='0', COM_OF_LOSS_T='1')
    assert not ok and 'Position mode needs a position estimate' in detail
    assert detail.endswith('set COM_OBL_RC_ACT = 4 (Land mode)'), detail
    ok, detail = _failsafe(autopilot='px4', COM_OBL_RC_ACT='7', COM_OF_LOSS_T='1')
    assert not ok and 'Disarm stops the motors in the air' in detail
    ok, detail = _failsafe(autopilot='px4', COM_OBL_RC_ACT='4', COM_OF_LOSS_T='5')
    assert not ok and 'set COM_OF_LOSS_T <= 2 s' in detail, detail
    assert _failsafe(autopilot='px4', COM_OBL_RC_ACT='4', COM_OF_LOSS_T='2')[0]   # the limit
    ok, detail = _failsafe(autopilot='px4', COM_OBL_RC_ACT='4')        # one of the pair read
    assert not ok and detail == 'PX4 COM_OBL_RC_ACT / COM_OF_LOSS_T not read yet'
    assert not _failsafe(autopilot='px4', COM_OBL_RC_ACT='four', COM_OF_LOSS_T='nan')[0]


def test_ardupilot_failsafe_is_go_only_with_its_gcs_failsafe_on_this_bridge():
    ok, detail = _failsafe(autopilot='ardupilot', FS_GCS_ENABLE='5', SYSID_MYGCS='1',
                           source_system='1')
    assert ok and detail.startswith('ArduPilot FS_GCS_ENABLE = 5, SYSID_MYGCS = 1 (this bridge)')
    ok, detail = _failsafe(autopilot='ardupilot', FS_GCS_ENABLE='0', SYSID_MYGCS='1',
                           source_system='1')
    assert not ok and 'set FS_GCS_ENABLE = 5 (land)' in detail
    ok, detail = _failsafe(autopilot='ardupilot', FS_GCS_ENABLE='5', SYSID_MYGCS='255',
                           source_system='1')
    assert not ok and "not this bridge's system id 1; set SYSID_MYGCS = 1" in detail
    assert not _failsafe(autopilot='ardupilot', FS_GCS_ENABLE='5', SYSID_MYGCS='1')[0]
    assert not _failsafe(autopilot='ardupilot', source_system='1')[0]     # not read yet
    # its timing, where reported: ArduCopter's defaults (3 s, 5 s) flew a dead bridge's
    # vehicle on for seconds; what the lockstep mission sets (0.5 s, 2 s) is go
    gcs = dict(autopilot='ardupilot', FS_GCS_ENABLE='5', SYSID_MYGCS='1', source_system='1')
    ok, detail = _failsafe(**gcs, GUID_TIMEOUT='3', FS_GCS_TIMEOUT='5')
    assert not ok and detail.endswith('set GUID_TIMEOUT <= 1 s and FS_GCS_TIMEOUT <= 3 s'), \
        detail
    ok, detail = _failsafe(**gcs, GUID_TIMEOUT='0.5', FS_GCS_TIMEOUT='2')
    assert ok and 'GUID_TIMEOUT = 0.5 s, FS_GCS_TIMEOUT = 2 s (this bridge)' in detail, detail
    assert _failsafe(**gcs, GUID_TIMEOUT='1', FS_GCS_TIMEOUT='3')[0]            # the limits
    assert not _failsafe(**gcs, GUID_TIMEOUT='1.5')[0]


def test_failsafe_is_no_go_before_the_autopilot_or_the_bridge_is_known():
    from ibvs_bringup.preflight import bridge_values, failsafe_setup
    ok, detail = _failsafe(autopilot='unknown', COM_OBL_RC_ACT='4', COM_OF_LOSS_T='1')
    assert not ok and detail == 'autopilot unknown: its failsafe parameters are not known'
    assert bridge_values(DiagnosticArray()) is None
    ok, detail = failsafe_setup(None)
    assert not ok and 'not reported' in detail


def test_armability_is_armed_or_armable_and_says_why_not():
    from ibvs_bringup.preflight import armability, bridge_values
    assert armability(bridge_values(_bridge(armed='True', armable='False'))) == (True, 'armed')
    ok, detail = armability(bridge_values(_bridge(armed='False', armable='True')))
    assert ok and detail.startswith('disarmed, armable')
    ok, detail = armability(bridge_values(_bridge(
        armed='False', armable='False', last_autopilot_reason='Preflight Fail: Accels')))
    assert not ok and '(its last message: Preflight Fail: Accels)' in detail
    ok, detail = armability(bridge_values(_bridge(armed='False', armable='unknown')))
    assert not ok and detail == 'armability not reported yet (SYS_STATUS)'
    assert not armability(None)[0]


# --- the pad in view (PadInView), the summary line and the verdict --------------------------

def test_pad_in_view_needs_complete_groups_in_most_of_the_last_images():
    from ibvs_bringup.preflight import PAD_TRIES, PadInView
    pad = PadInView()
    for _ in range(PAD_TRIES - 1):
        pad.note(('A', 'B'))
    ok, detail = pad.check()
    assert not ok and detail == f'{PAD_TRIES - 1} down images tried yet (needs {PAD_TRIES})'
    pad.note(())                                       # one image without a complete group
    ok, detail = pad.check()
    assert ok and detail == 'complete groups in 9 of the last 10 down images (A, B)', detail
    for _ in range(5):
        pad.note_error('CameraInfo size 640x480 != image size 752x480')
    ok, detail = pad.check()
    assert not ok and detail.startswith('complete groups in 4 of the last 10'), detail
    assert detail.endswith('last error: CameraInfo size 640x480 != image size 752x480')


def test_the_summary_line_is_go_with_skips_and_no_go_names_what_failed():
    from ibvs_bringup.preflight import Check, format_checklist, go, summary_line, verdict_msg
    from ibvs_common.node_common import preflight_verdict
    checks = [Check('imu/data flowing', True, '50 messages'),
              Check('pad in view of the down camera', False, 'not checked', skipped=True),
              Check('armed or armable', True, 'armed')]
    assert go(checks)
    assert summary_line(checks) == ('PREFLIGHT GO: 2 checks passed, 1 skipped (pad in view of '
                                    'the down camera)')
    assert format_checklist(checks).splitlines()[1] == \
        '  [SKIP] pad in view of the down camera: not checked'
    checks.append(Check('autopilot failsafe when the bridge stops', False, 'PX4 ...'))
    assert not go(checks)
    line = summary_line(checks)
    assert line == ('PREFLIGHT NO-GO: 1 of 3 checks failed: autopilot failsafe when the '
                    'bridge stops')
    msg = verdict_msg(checks, 5 * S)
    assert preflight_verdict(msg) == (False, line)
    assert {kv.key: kv.value for kv in msg.status[0].values}['armed or armable'] == 'OK: armed'
