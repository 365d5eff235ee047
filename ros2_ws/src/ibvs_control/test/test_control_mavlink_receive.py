"""MavlinkLink's receive: every message of a datagram or a byte stream, in order, none twice.

The link reads with its own loop over pymavlink's ``recv`` and parser instead of ``recv_msg``
(mavlink_link.MavlinkLink._next_message). These tests pin what that loop must keep: several
messages packed in one UDP datagram (PX4 sends its streams so), a message split across TCP
reads, and the rejection of a frame with a bad checksum, on real sockets.
"""
import socket
import time

from ibvs_control.mavlink.link import LinkConfig, MavlinkLink, mavlink

ATTITUDE_QUATERNION = (1234, 1.0, 0.0, 0.0, 0.0, 0.1, -0.2, 0.3)


def _encoder() -> mavlink.MAVLink:
    """A MAVLink 2 encoder speaking as the autopilot (system 1, component 1)."""
    return mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def _frames(enc: mavlink.MAVLink) -> list[bytes]:
    """HEARTBEAT, ATTITUDE_QUATERNION, HIGHRES_IMU as the autopilot would send them."""
    return [
        enc.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                             0).pack(enc),
        enc.attitude_quaternion_encode(*ATTITUDE_QUATERNION).pack(enc),
        enc.highres_imu_encode(5_000_000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0, 0, 0, 0, 0, 0,
                               0, 0).pack(enc),
    ]


def _poll_until(link: MavlinkLink, count: int, timeout_s: float = 2.0) -> list:
    got = []
    end = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < end:
        got += link.poll()
        time.sleep(0.002)
    return got


def test_a_datagram_of_three_messages_gives_all_three_in_order_once():
    link = MavlinkLink(LinkConfig(url='udpin:127.0.0.1:0'))
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sender.sendto(b''.join(_frames(_encoder())), ('127.0.0.1', link.local_port))
        got = _poll_until(link, 3)
        assert [m.get_type() for m in got] == ['HEARTBEAT', 'ATTITUDE_QUATERNION',
                                               'HIGHRES_IMU']
        q = got[1]
        assert (q.time_boot_ms, q.q1) == (1234, 1.0) and abs(q.rollspeed - 0.1) < 1e-6
        assert link.poll() == [] and link.counters.received == 3
        assert link.target_system == 1              # learnt from the HEARTBEAT
    finally:
        link.close()
        sender.close()


def test_a_message_split_across_tcp_reads_is_parsed_once_whole():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(('127.0.0.1', 0))
    server.listen(1)
    link = MavlinkLink(LinkConfig(url=f'tcp:127.0.0.1:{server.getsockname()[1]}'))
    peer, _ = server.accept()
    try:
        heartbeat, attitude, imu = _frames(_encoder())
        peer.sendall(heartbeat + attitude[:10])     # a whole frame and a piece of the next
        assert [m.get_type() for m in _poll_until(link, 1)] == ['HEARTBEAT']
        time.sleep(0.05)
        assert link.poll() == []                   # the piece alone is no message
        peer.sendall(attitude[10:] + imu)
        got = _poll_until(link, 2)
        assert [m.get_type() for m in got] == ['ATTITUDE_QUATERNION', 'HIGHRES_IMU']
        assert got[0].time_boot_ms == ATTITUDE_QUATERNION[0]
        assert link.counters.received == 3 and link.counters.bad_data == 0
    finally:
        link.close()
        peer.close()
        server.close()


def test_a_frame_with_a_bad_checksum_is_bad_data_and_the_next_one_is_read():
    link = MavlinkLink(LinkConfig(url='udpin:127.0.0.1:0'))
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        heartbeat, attitude, _ = _frames(_encoder())
        broken = bytearray(attitude)
        broken[-1] ^= 0xFF                          # CRC's high byte
        sender.sendto(heartbeat, ('127.0.0.1', link.local_port))
        sender.sendto(bytes(broken), ('127.0.0.1', link.local_port))
        sender.sendto(attitude, ('127.0.0.1', link.local_port))
        got = _poll_until(link, 2)
        assert [m.get_type() for m in got] == ['HEARTBEAT', 'ATTITUDE_QUATERNION']
        assert link.counters.bad_data >= 1
    finally:
        link.close()
        sender.close()
