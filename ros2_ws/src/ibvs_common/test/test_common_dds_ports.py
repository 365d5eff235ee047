"""The ports free_udp_port hands out are not among those a ROS process's Fast DDS binds.

run_scenario checks a port, then starts the graph; the sim binds the port seconds later. Every
process started meanwhile creates a DDS participant, which binds UDP ports of its own (measured:
7400 + ... and one on 0.0.0.0:7000 + k, the first k free). A check range that overlapped those
lost the sim its port in CI ("Address already in use" on 7003). This test reads the ports this
process's participant really bound, from /proc.
"""
import os
from pathlib import Path
import time

import pytest
import rclpy

from ibvs_common.core.mavlink_connection import SERVER_PORTS


def udp_ports_of_this_process() -> set[int]:
    """Local ports of this process's UDP (IPv4 and IPv6) sockets, from /proc/self and /proc/net."""
    inodes = set()
    for fd in Path('/proc/self/fd').iterdir():
        try:
            target = os.readlink(fd)
        except OSError:                      # closed meanwhile
            continue
        if target.startswith('socket:['):
            inodes.add(target[len('socket:['):-1])
    ports = set()
    for table in ('/proc/net/udp', '/proc/net/udp6'):
        if not os.path.exists(table):
            continue
        with open(table) as f:
            next(f)                          # header
            for line in f:
                fields = line.split()
                if fields[9] in inodes:      # local_address is HEXIP:HEXPORT; inode column 9
                    ports.add(int(fields[1].rsplit(':', 1)[1], 16))
    return ports


@pytest.mark.skipif(not os.path.exists('/proc/net/udp'), reason='needs Linux /proc/net/udp')
def test_a_participant_binds_no_port_free_udp_port_hands_out(context):
    node = rclpy.create_node(f'dds_ports_{os.getpid()}_{int(time.monotonic() * 1e3)}',
                             context=context)
    try:
        dds = udp_ports_of_this_process()
        assert dds, 'no UDP socket found for the participant'
        assert not dds & set(SERVER_PORTS), (
            f'Fast DDS bound {sorted(dds & set(SERVER_PORTS))} inside free_udp_port\'s range '
            f'{SERVER_PORTS.start}-{SERVER_PORTS.stop - 1}; all its UDP ports: {sorted(dds)}')
    finally:
        node.destroy_node()
