"""Telemetry decoding and stream requests, from MAVLink frames built here.

PX4's EVENT (id 410) is not in pymavlink 2.4.50's dialects: a frame is built by hand from the
MAVLink 2 wire format (header 10 bytes, fields by size, trailing zeros truncated) and read back
through pymavlink's parser, as the bridge receives PX4's. The event id and arguments of the
first case are those PX4 v1.16 SITL sent when arming (0x0190caf3 = "commander_armed_by", arg 4).
"""
import os
import struct
from pathlib import Path

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

from ibvs_common.core.frames import GRAVITY  # noqa: E402
from ibvs_control.mavlink.telemetry import (  # noqa: E402
    decode_event, load_px4_events, message_ids, QuietTelemetry, StreamRequests, streams_for,
    Telemetry)
from ibvs_control.mavlink.time_sync import TimeSync  # noqa: E402
from ibvs_common.testing import shared_dir  # noqa: E402

PX4_EVENTS = (shared_dir() or Path('/nonexistent')) / 'px4-sitl' / 'etc' / 'extras' \
    / 'all_events.json.xz'
mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def raw_event_frame(eid, seq, levels, args):
    payload = struct.pack('<IIHBBB40s', eid, 1234, seq, 0, 0, levels, args).rstrip(b'\x00')
    header = bytes([0xFD, len(payload), 0, 0, 7, 1, 1]) + (410).to_bytes(3, 'little')
    return header + payload + b'\x00\x00'        # CRC not checked for an unknown id


def parse(frame):
    m = mavutil.mavlink.MAVLink(None)
    m.robust_parsing = True
    return m.parse_char(frame)


def test_px4_event_decoded_from_the_raw_frame():
    msg = parse(raw_event_frame(0x0190CAF3, 5, 0x66, bytes([4])))
    assert msg.get_type() == 'UNKNOWN_410'
    assert decode_event(msg) == (0x0190CAF3, 5, 0x66, bytes([4]) + bytes(39))
    tel = Telemetry(TimeSync(), clock=lambda: 0.0,
                    px4_events={0x0190CAF3: 'commander_armed_by: Armed by {1}'})
    tel.on_message(msg, None)
    [(level, text)] = tel.pop_events()
    assert level == 'reason-info'                # log level 6 (info) in the low nibble
    assert '0x0190caf3' in text and 'Armed by' in text and 'args 04' in text


@pytest.mark.skipif(not PX4_EVENTS.exists(), reason='../shared/px4-sitl not present')
def test_px4_events_metadata_of_the_sitl():
    events = load_px4_events(str(PX4_EVENTS))
    assert events[0x0190CAF3].startswith('commander_armed_by')


def test_statustext_reasons_once_per_period_and_internal_errors():
    now = [0.0]
    tel = Telemetry(TimeSync(), clock=lambda: now[0])
    msg = mav.statustext_encode(3, b'PreArm: Internal errors 0x100000 l:57 flow_of_ctrl')
    tel.on_message(msg, None)
    tel.on_message(msg, None)                    # the same text again within 5 s: not logged
    events = tel.pop_events()
    assert [lv for lv, _ in events] == ['error', 'reason-error']
    assert '#26865' in events[0][1] and tel.internal_errors == 0x100000
    now[0] = 6.0
    tel.on_message(msg, None)
    assert [lv for lv, _ in tel.pop_events()] == ['reason-error']
    assert tel.reasons == 3


def test_sys_status_armable_and_internal_error_bits_extended_sys_state_landed():
    tel = Telemetry(TimeSync(), clock=lambda: 0.0)
    assert tel.armable is None and tel.landed is None
    tel.on_message(mav.sys_status_encode(0, 0, 1 << 28, 0, 0, -1, -1, 0, 0, 0, 0x10, 0, 0),
                   None)
    assert tel.armable is True and tel.internal_errors == 0x100000
    assert any('#26865' in t for _, t in tel.pop_events())
    tel.on_message(mav.sys_status_encode(0, 0, 0, 0, 0, -1, -1, 0, 0, 0, 0, 0, 0), None)
    assert tel.armable is False
    for state, landed in ((1, True), (2, False), (4, False), (0, None)):
        tel.on_message(mav.extended_sys_state_encode(0, state), None)
        assert tel.landed is landed


def test_specific_force_from_highres_imu_and_scaled_imu_thrust_from_attitude_target():
    tel = Telemetry(TimeSync(), clock=lambda: 0.0)
    _, acc, _ = tel.on_message(mav.highres_imu_encode(2_000_000, 0.1, 0.2, -9.7, *[0.0] * 10,
                                                      0x3F), None)
    assert acc.boot_ns == 2_000_000_000 and np.allclose(acc.f_frd, [0.1, 0.2, -9.7])
    _, acc, _ = tel.on_message(mav.scaled_imu_encode(3000, 10, -20, -1000, 0, 0, 0, 0, 0, 0),
                               None)
    assert acc.boot_ns == 3_000_000_000
    assert np.allclose(acc.f_frd, np.array([10, -20, -1000]) * GRAVITY / 1000)
    _, _, thr = tel.on_message(mav.attitude_target_encode(3000, 7, [1, 0, 0, 0], 0, 0, 0,
                                                          0.47), None)
    assert thr.boot_ns == 3_000_000_000 and thr.thrust == pytest.approx(0.47)


def test_stream_lists_per_autopilot():
    px4 = dict(streams_for('px4', 100, 100, 50, 5, 5))
    ap = dict(streams_for('ardupilot', 100, 100, 50, 5, 5))
    assert px4 == {31: 100, 105: 100, 83: 50, 245: 5, 1: 5}       # no HEARTBEAT: PX4 fails it
    assert ap == {31: 100, 26: 100, 83: 50, 245: 5, 1: 5, 0: 5}   # never HIGHRES_IMU (105)


def test_streams_off_follow_the_wanted_ones_and_never_switch_off_what_is_read():
    off = message_ids(['ATTITUDE', 'LOCAL_POSITION_NED', 'attitude_quaternion', 'TIMESYNC',
                       'STATUSTEXT', 'HEARTBEAT', 'ATTITUDE'])
    assert off[:2] == (30, 32)                                  # MAVLink common.xml ids
    px4 = streams_for('px4', 100, 100, 50, 5, 5, off)
    assert px4[:5] == streams_for('px4', 100, 100, 50, 5, 5)    # what is read comes first
    assert px4[5:] == [(30, 0.0), (32, 0.0)]                    # once each, rate 0 = off
    ap = streams_for('ardupilot', 100, 100, 50, 5, 5, message_ids(['HEARTBEAT', 'VFR_HUD']))
    assert ap[-1] == (74, 0.0) and (0, 0.0) not in ap           # its HEARTBEAT is asked for
    with pytest.raises(ValueError, match='ATTITUDEX'):
        message_ids(['ATTITUDEX'])
    r = StreamRequests(px4[5:])
    assert r.step(0.0) == (30, 0.0)
    assert r.on_ack(3) == '' and r.refused == []                # no such stream: nothing lost


def test_stream_requests_one_at_a_time_until_acknowledged():
    r = StreamRequests([(31, 100.0), (105, 100.0), (83, 50.0)], ack_timeout_s=0.5,
                       max_attempts=2)
    assert r.step(0.0) == (31, 100.0)
    assert r.step(0.1) is None                   # in flight
    assert r.on_ack(0) == ''
    assert r.step(0.2) == (105, 100.0)
    assert 'refused' in r.on_ack(2)              # DENIED: not asked again
    assert r.step(0.3) == (83, 50.0)
    assert r.step(0.9) == (83, 50.0)             # no answer: again ...
    assert r.step(1.5) is None and r.complete    # ... then given up
    assert r.refused == [105]
    r.reset()
    assert not r.complete and r.step(2.0) == (31, 100.0)


def test_stream_rate_retargeted_asks_again_even_while_in_flight():
    r = StreamRequests([(31, 100.0), (83, 50.0)])
    assert r.step(0.0) == (31, 100.0)
    assert r.set_rate(31, 10.0)                  # changed while its request is in flight ...
    assert r.on_ack(0) == '' and not r.complete  # ... that ACK does not complete it
    assert r.step(0.1) == (31, 10.0)
    assert r.on_ack(0) == ''
    assert not r.set_rate(31, 10.0)              # the same rate: nothing to ask
    assert r.step(0.2) == (83, 50.0) and 'refused' in r.on_ack(4)
    assert not r.set_rate(83, 5.0) and r.step(0.3) is None and r.complete  # refused: given up
    assert r.rate(31) == 10.0 and r.rate(999) is None


def test_quiet_telemetry_after_the_delay_and_at_once_back():
    q = QuietTelemetry({31: 100.0, 105: 100.0, 83: 50.0, 1: 5.0}, quiet_rate_hz=10.0,
                       delay_s=2.0)
    assert q.update(True, 0.0) is None and q.update(True, 1.99) is None and not q.active
    assert q.update(True, 2.0) == {31: 10.0, 105: 10.0, 83: 10.0, 1: 5.0}   # never faster
    assert q.update(True, 5.0) is None and q.active
    assert q.update(False, 5.01) == {31: 100.0, 105: 100.0, 83: 50.0, 1: 5.0}
    assert q.update(True, 5.02) is None and q.update(True, 6.9) is None     # delay again
    assert q.update(True, 7.02)[31] == 10.0
    assert q.reset()[31] == 100.0 and not q.active
    off = QuietTelemetry({31: 100.0}, quiet_rate_hz=0.0, delay_s=0.0)
    assert off.update(True, 0.0) is None and off.update(True, 100.0) is None and not off.active
