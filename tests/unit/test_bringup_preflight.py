"""Preflight go/no-go: the clock sync and stamp agreement checks (pure functions)."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ibvs_bringup.preflight import diag_value, STAMP_AGREEMENT_S, stamps_agree

S = 1_000_000_000


def test_stamps_on_one_clock_agree_and_a_driver_on_another_clock_fails():
    now = 1_795_000_000 * S                                     # system time, ns
    ok, detail = stamps_agree({'front camera': now - 20_000_000,
                               'down camera': now - 25_000_000, 'imu': now - 5_000_000}, now)
    assert ok and 'front camera -20 ms' in detail
    # a camera driver stamping since its own boot (or an IMU left on the autopilot's boot
    # clock: the 1970 stamps of an unsynced bridge) is far from the others
    ok, _ = stamps_agree({'front camera': 12 * S, 'down camera': now, 'imu': now}, now)
    assert not ok
    late = now - int((STAMP_AGREEMENT_S + 0.05) * S)             # an IMU 150 ms behind
    assert not stamps_agree({'front camera': now, 'down camera': now, 'imu': late}, now)[0]
    ok, detail = stamps_agree({'front camera': now, 'down camera': None, 'imu': now}, now)
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
