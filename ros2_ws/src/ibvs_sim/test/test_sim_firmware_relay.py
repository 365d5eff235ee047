"""The companion relay between the bridge and a real firmware (no firmware: two UDP peers).

The relay passes datagrams on unchanged, both ways, and reads what the lockstep needs:
the frame a setpoint answers and the newest attitude (both in sim time: the firmware's clock
less the boot offset, within the bridge's clock-sync tolerance), and whether the firmware
flies the graph's setpoints (OFFBOARD while the supervisor's mode flies).
"""
import os
import socket
import time

import pytest

os.environ.setdefault('MAVLINK20', '1')
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from ibvs_sim.core.firmware.relay import (CompanionPort, CompanionRelay,  # noqa: E402
                                          IMU_TOLERANCE_MS, PX4_COMPANION_LISTEN_BASE,
                                          PX4_COMPANION_SEND_BASE)

OFFSET_MS = 24_160


def _free_instance() -> int:
    for i in range(9, -1, -1):
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a, \
                    socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b:
                a.bind(('127.0.0.1', PX4_COMPANION_SEND_BASE + i))
                b.bind(('127.0.0.1', PX4_COMPANION_LISTEN_BASE + i))
            return i
        except OSError:
            continue
    pytest.skip('no free PX4 companion ports (14540-14549, 14580-14589)')


@pytest.fixture()
def link():
    """(relay, bridge socket, firmware socket, pack): the relay between two UDP peers."""
    i = _free_instance()
    relay = CompanionRelay('udpin:127.0.0.1:0', i, OFFSET_MS)
    bridge = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bridge.settimeout(1.0)
    firmware = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    firmware.bind(('127.0.0.1', PX4_COMPANION_LISTEN_BASE + i))
    firmware.settimeout(1.0)
    to_relay_bridge = ('127.0.0.1', relay.local_port)
    to_relay_firmware = ('127.0.0.1', PX4_COMPANION_SEND_BASE + i)
    mav_b = mavlink.MAVLink(None, srcSystem=255, srcComponent=191)
    mav_f = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def from_bridge(msg):
        data = msg.pack(mav_b)
        bridge.sendto(data, to_relay_bridge)
        return data

    def from_firmware(msg):
        data = msg.pack(mav_f)
        firmware.sendto(data, to_relay_firmware)
        return data

    def settle():
        time.sleep(0.05)
        relay.poll()
    yield relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle
    relay.close()
    bridge.close()
    firmware.close()


def test_datagrams_pass_unchanged_both_ways(link):
    relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle = link
    sent = from_bridge(mav_b.heartbeat_encode(6, 8, 0, 0, 0))
    settle()
    assert firmware.recvfrom(1024)[0] == sent
    back = from_firmware(mav_f.heartbeat_encode(2, 12, 129, 4 << 16, 4))
    settle()
    assert bridge.recvfrom(1024)[0] == back
    assert relay.forwarded == {'to_firmware': 1, 'to_bridge': 1, 'unparsed': 0}


def test_setpoint_and_attitude_in_sim_time_within_the_tolerance(link):
    relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle = link
    assert relay.last_setpoint_time_boot_ms is None and relay.last_attitude_ms is None
    from_bridge(mav_b.heartbeat_encode(6, 8, 0, 0, 0))
    # the frame at sim 1.000 s, stamped by the bridge 4 ms early on PX4's clock
    from_bridge(mav_b.set_attitude_target_encode(OFFSET_MS + 996, 1, 1, 7,
                                                 [1, 0, 0, 0], 0, 0, 0, 0.5))
    from_firmware(mav_f.attitude_quaternion_encode(OFFSET_MS + 1020, 1, 0, 0, 0, 0, 0, 0))
    settle()
    assert relay.last_setpoint_sim_ms == 996
    assert relay.last_setpoint_time_boot_ms >= 1000          # answers the frame at 1.000 s
    assert relay.last_setpoint_time_boot_ms < 1020           # never the next one (20 ms on)
    assert relay.newest_attitude_ms == 1020
    assert relay.last_attitude_ms == 1020 - IMU_TOLERANCE_MS
    assert [t for t, _ in relay.new_setpoints] == [996]
    # an older setpoint (a repeat) does not move it back
    from_bridge(mav_b.set_attitude_target_encode(OFFSET_MS + 976, 1, 1, 7,
                                                 [1, 0, 0, 0], 0, 0, 0, 0.5))
    settle()
    assert relay.last_setpoint_sim_ms == 996 and len(relay.new_setpoints) == 1


def test_awaits_setpoints_in_offboard_while_the_graph_flies(link):
    relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle = link
    from_firmware(mav_f.heartbeat_encode(2, 12, 129, (4 << 16) | (3 << 24), 4))  # AUTO.LOITER
    settle()
    assert not relay.flying_mode and not relay.awaits_setpoints
    from_firmware(mav_f.heartbeat_encode(2, 12, 129, 6 << 16, 4))                # OFFBOARD
    settle()
    assert relay.awaits_setpoints
    relay.graph_flies = lambda: False          # SHUTDOWN: no frame is answered any more
    assert not relay.awaits_setpoints


def test_firmware_datagrams_of_the_preroll_are_dropped(link):
    relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle = link
    from_bridge(mav_b.heartbeat_encode(6, 8, 0, 0, 0))
    settle()
    firmware.recvfrom(1024)
    from_firmware(mav_f.attitude_quaternion_encode(5, 1, 0, 0, 0, 0, 0, 0))
    time.sleep(0.05)
    relay.discard_firmware()
    relay.poll()
    bridge.settimeout(0.1)
    with pytest.raises(socket.timeout):
        bridge.recvfrom(1024)
    assert relay.newest_attitude_ms is None


def test_relay_needs_a_udpin_endpoint():
    with pytest.raises(ValueError, match='udpin'):
        CompanionRelay('tcp:127.0.0.1:5760', 0, 0)


def test_timesync_answer_passes_within_the_same_poll(link):
    """A TIMESYNC request is answered before poll returns: the bridge gets the answer at the
    ROS time it asked (the sim has not stepped), so its clock offset is exact."""
    import threading
    relay, bridge, firmware, mav_b, mav_f, from_bridge, from_firmware, settle = link

    def firmware_answers():
        data, _ = firmware.recvfrom(1024)
        request = mavlink.MAVLink(None).parse_buffer(data)[0]
        from_firmware(mav_f.timesync_encode(25_000_000_000, request.ts1))
    answerer = threading.Thread(target=firmware_answers)
    answerer.start()
    from_bridge(mav_b.timesync_encode(0, 1_000_000_000))
    time.sleep(0.02)
    relay.poll()                      # one poll: request out, answer back
    answerer.join()
    answer = mavlink.MAVLink(None).parse_buffer(bridge.recvfrom(1024)[0])[0]
    assert (answer.tc1, answer.ts1) == (25_000_000_000, 1_000_000_000)
    assert relay.timesync_unanswered == 0
    # a firmware that does not answer costs one bounded wait, counted
    from_bridge(mav_b.timesync_encode(0, 2_000_000_000))
    time.sleep(0.02)
    relay.poll()
    assert relay.timesync_unanswered == 1


@pytest.fixture()
def ardupilot_link():
    """(relay, bridge, firmware, mav_b, mav_f, to_relay_bridge, to_relay_firmware): ArduPilot.

    ArduPilot's SERIAL1 sends to 14540 + i from a port of its own and takes datagrams only
    from 14540 + i: the firmware socket here is bound to an ephemeral port.
    """
    i = _free_instance()
    relay = CompanionRelay('udpin:127.0.0.1:0', i, OFFSET_MS, port=CompanionPort.ardupilot(i))
    bridge = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bridge.settimeout(1.0)
    firmware = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    firmware.bind(('127.0.0.1', 0))
    firmware.settimeout(1.0)
    mav_b = mavlink.MAVLink(None, srcSystem=255, srcComponent=191)
    mav_f = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    yield (relay, bridge, firmware, mav_b, mav_f, ('127.0.0.1', relay.local_port),
           ('127.0.0.1', PX4_COMPANION_SEND_BASE + i))
    relay.close()
    bridge.close()
    firmware.close()


def test_ardupilot_answered_at_the_port_it_sends_from_and_flies_in_guided_nogps(ardupilot_link):
    relay, bridge, firmware, mav_b, mav_f, to_bridge_side, to_firmware_side = ardupilot_link
    # GUIDED (4): ArduPilot's own hold; the relay learns where ArduPilot listens
    firmware.sendto(mav_f.heartbeat_encode(2, 3, 129, 4, 4).pack(mav_f), to_firmware_side)
    time.sleep(0.05)
    relay.discard_firmware()            # the pre-roll's datagrams: dropped, the port learnt
    sent = mav_b.heartbeat_encode(6, 8, 0, 0, 0).pack(mav_b)
    bridge.sendto(sent, to_bridge_side)
    time.sleep(0.05)
    relay.poll()
    assert firmware.recvfrom(1024)[0] == sent
    assert not relay.flying_mode
    firmware.sendto(mav_f.heartbeat_encode(2, 3, 129, 20, 4).pack(mav_f), to_firmware_side)
    time.sleep(0.05)
    relay.poll()
    assert relay.flying_mode and relay.awaits_setpoints      # GUIDED_NOGPS (20)
    # a PX4 heartbeat's custom mode means nothing to an ArduPilot relay
    firmware.sendto(mav_f.heartbeat_encode(2, 12, 129, 6 << 16, 4).pack(mav_f),
                    to_firmware_side)
    time.sleep(0.05)
    relay.poll()
    assert relay.flying_mode


def test_ardupilot_timesync_answer_passes_between_deliveries_telemetry_waits(ardupilot_link):
    """ArduPilot answers TIMESYNC as its clock steps: the answer goes on at the step that
    brought it (before the next /clock), the telemetry with it at the next delivery's poll,
    in order, and the poll does not wait for an answer the frozen firmware cannot make. The
    answer sets the relay's clock offset as the bridge reads it: tc1 less the sim time the
    request was passed on at."""
    from types import SimpleNamespace
    relay, bridge, firmware, mav_b, mav_f, to_bridge_side, to_firmware_side = ardupilot_link
    firmware.sendto(mav_f.heartbeat_encode(2, 3, 129, 4, 4).pack(mav_f), to_firmware_side)
    time.sleep(0.05)
    relay.discard_firmware()
    bridge.sendto(mav_b.timesync_encode(0, 123_000).pack(mav_b), to_bridge_side)
    time.sleep(0.05)
    t0 = time.monotonic()
    relay.poll(SimpleNamespace(t=1.0))               # the delivery at sim 1.000 s
    assert time.monotonic() - t0 < 0.02              # no wait for the answer
    assert relay.timesync_unanswered == 0
    firmware.recvfrom(1024)                          # the request reached the firmware
    # ArduPilot stamps the request 2 ms after the sim time it was passed on at
    attitude = mav_f.attitude_quaternion_encode(OFFSET_MS + 1012, 1, 0, 0, 0, 0, 0,
                                                0).pack(mav_f)
    answer = mav_f.timesync_encode((OFFSET_MS + 1002) * 1_000_000, 123_000).pack(mav_f)
    firmware.sendto(attitude, to_firmware_side)
    firmware.sendto(answer, to_firmware_side)
    time.sleep(0.05)
    relay.pass_timesync()                            # a physics step between deliveries
    bridge.settimeout(0.2)
    assert bridge.recvfrom(1024)[0] == answer
    with pytest.raises(socket.timeout):
        bridge.recvfrom(1024)                        # the attitude waits for the delivery
    assert relay.newest_attitude_ms is None
    assert relay.boot_offset_ms == OFFSET_MS + 2     # the bridge's offset from that answer
    relay.poll(SimpleNamespace(t=1.02))
    assert bridge.recvfrom(1024)[0] == attitude
    assert relay.newest_attitude_ms == 1010          # on the bridge's map of the clock
    # an answer to a request the relay never passed on does not move the offset
    firmware.sendto(mav_f.timesync_encode(5 * 10**12, 999).pack(mav_f), to_firmware_side)
    time.sleep(0.05)
    relay.pass_timesync()
    assert relay.boot_offset_ms == OFFSET_MS + 2
