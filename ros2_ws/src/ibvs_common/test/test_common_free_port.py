"""mavlink_connection.free_udp_port: a port for a server that another process binds later."""
import random
import socket

import pytest

from ibvs_common.core.mavlink_connection import free_udp_port, PORT_TRIES, SERVER_PORTS


def ephemeral_range() -> range:
    with open('/proc/sys/net/ipv4/ip_local_port_range') as f:
        lo, hi = (int(x) for x in f.read().split())
    return range(lo, hi + 1)


def test_the_port_is_free_and_outside_the_ranges_others_take_ports_from():
    port = free_udp_port()
    assert port in SERVER_PORTS
    assert port not in ephemeral_range()          # client sockets' ports
    assert port < 7000                  # Fast DDS: 7000 + k per process, 7400 + 250 x domain
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', port))               # free: the caller's server can bind it


def test_a_port_in_use_is_passed_over():
    first = free_udp_port(random.Random(7))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', first))              # someone else's now
        assert free_udp_port(random.Random(7)) != first   # same draws: the next one is taken


class AlwaysThis:
    def __init__(self, port: int) -> None:
        self.port, self.calls = port, 0

    def choice(self, ports):
        self.calls += 1
        return self.port


def test_no_free_port_raises_after_the_tries():
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', port))
        rng = AlwaysThis(port)
        with pytest.raises(OSError, match='no free UDP port'):
            free_udp_port(rng)
        assert rng.calls == PORT_TRIES
