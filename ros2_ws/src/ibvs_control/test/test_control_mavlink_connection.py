"""mavlink_udp.open_mavlink: a udpin port is ours alone, as MAVROS binds it (no port sharing)."""
import errno
import socket

import pytest

from ibvs_control.mavlink.link import LinkConfig, MavlinkLink
from ibvs_common.core.mavlink_connection import open_mavlink, PortInUse, udp_server_address


def reuse_socket() -> socket.socket:
    """A UDP socket as pymavlink's udpin makes it (SO_REUSEADDR set before the bind)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    return s


def test_server_urls_are_recognised_and_others_passed_through():
    assert udp_server_address('udpin:0.0.0.0:14540') == ('0.0.0.0', 14540)
    assert udp_server_address('udp:127.0.0.1:14560') == ('127.0.0.1', 14560)  # old name
    for url in ('udpout:127.0.0.1:14580', 'udpbcast:192.168.1.255:14550', 'tcp:127.0.0.1:5760',
                'tcpin:0.0.0.0:5760', '/dev/ttyUSB0,921600'):
        assert udp_server_address(url) is None, url


def test_a_second_server_on_the_port_is_refused_and_the_port_is_free_after_close():
    first = open_mavlink('udpin:127.0.0.1:0')
    port = first.port.getsockname()[1]
    try:
        with pytest.raises(PortInUse, match=f'UDP port {port} is already bound') as info:
            open_mavlink(f'udpin:127.0.0.1:{port}')
        assert info.value.errno == errno.EADDRINUSE
    finally:
        first.close()
    again = open_mavlink(f'udpin:127.0.0.1:{port}')       # closed: the port can be had again
    assert again.port.getsockname()[1] == port
    again.close()


def test_a_port_held_by_a_reuse_socket_is_refused_though_plain_pymavlink_would_share_it():
    with reuse_socket() as other:
        other.bind(('127.0.0.1', 0))
        port = other.getsockname()[1]
        with reuse_socket() as sharer:                   # what pymavlink alone would do
            sharer.bind(('127.0.0.1', port))             # Linux lets it: the two share
        with pytest.raises(PortInUse):
            open_mavlink(f'udpin:127.0.0.1:{port}')
        with pytest.raises(PortInUse):                   # the wildcard address overlaps too
            open_mavlink(f'udpin:0.0.0.0:{port}')


def test_once_bound_nobody_else_can_share_the_port_even_with_reuse():
    conn = open_mavlink('udpin:127.0.0.1:0')
    port = conn.port.getsockname()[1]
    try:
        for host in ('127.0.0.1', '0.0.0.0'):
            with reuse_socket() as late, pytest.raises(OSError) as info:
                late.bind((host, port))
            assert info.value.errno == errno.EADDRINUSE
    finally:
        conn.close()


def test_kernel_picked_ports_differ_and_a_client_url_binds_nothing():
    a, b = open_mavlink('udpin:127.0.0.1:0'), open_mavlink('udpin:127.0.0.1:0')
    try:
        pa, pb = a.port.getsockname()[1], b.port.getsockname()[1]
        assert pa > 0 and pb > 0 and pa != pb
        out = open_mavlink(f'udpout:127.0.0.1:{pa}')
        assert out.port.getsockname()[1] == 0            # unbound until it sends
        out.close()
    finally:
        a.close()
        b.close()


def test_the_bridge_link_reports_a_taken_port_and_opens_once_it_is_free():
    t = [0.0]
    with reuse_socket() as holder:
        holder.bind(('127.0.0.1', 0))
        port = holder.getsockname()[1]
        link = MavlinkLink(LinkConfig(url=f'udpin:127.0.0.1:{port}', reconnect_period_s=0.5),
                           clock=lambda: t[0])
        assert not link.is_open and link.local_port is None
        assert f'UDP port {port} is already bound' in link.last_error
        assert [lvl for lvl, _ in link.pop_events()] == ['error']
    t[0] = 1.0                                            # a reconnect period later, port free
    link.poll()
    try:
        assert link.is_open and link.local_port == port
    finally:
        link.close()
