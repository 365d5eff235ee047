"""Open a pymavlink connection; a UDP server port (``udpin:``) is this process's alone.

pymavlink binds ``udpin:`` sockets with SO_REUSEADDR. On Linux a second socket that also sets
SO_REUSEADDR may then bind the same address and port, and unicast datagrams go to only one of
the two: a second bridge, or a second sim, started on the port would silently steal the
autopilot's stream (or the companion's setpoints). MAVROS binds without reuse (asio's default),
so its second instance stops with "Address already in use". :func:`open_mavlink` does the same:

- before pymavlink binds, a plain bind of the port (no SO_REUSEADDR) tells whether any socket
  holds it; if one does, it raises :class:`PortInUse`;
- once bound, SO_REUSEADDR is cleared on our socket, so every later bind of the port fails.

Port 0 (``udpin:127.0.0.1:0``) needs no check: the kernel picks a port nobody holds.
"""
from __future__ import annotations

import errno
import os
import random
import socket

os.environ['MAVLINK20'] = '1'  # before pymavlink.mavutil is imported: MAVLink 2 framing
from pymavlink import mavutil  # noqa: E402  (must follow the MAVLINK20 switch)

#: pymavlink URL prefixes that bind a UDP server socket (``udp:`` is its old name of udpin).
UDP_SERVER_PREFIXES = ('udpin:', 'udp:')


class PortInUse(OSError):
    """The UDP port of a ``udpin:`` URL is bound by another socket (EADDRINUSE)."""


def udp_server_address(url: str) -> tuple[str, int] | None:
    """Return (host, port) a ``udpin:``/``udp:`` URL binds, None for every other URL."""
    for prefix in UDP_SERVER_PREFIXES:
        if url.startswith(prefix):
            host, _, port = url[len(prefix):].rpartition(':')
            return host, int(port)
    return None


def open_mavlink(url: str, **kwargs) -> mavutil.mavfile:
    """``mavutil.mavlink_connection(url, **kwargs)``, exclusive on a UDP server port.

    Raise :class:`PortInUse` when another socket holds the port of a ``udpin:`` URL, and
    whatever pymavlink raises for a bad URL or device. See the module docstring.
    """
    address = udp_server_address(url)
    if address is not None and address[1] != 0:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(address)
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE:
                    raise
                raise PortInUse(errno.EADDRINUSE, f'UDP port {address[1]} is already bound '
                                f'by another socket (a second bridge or sim?): {url}') from None
    conn = mavutil.mavlink_connection(url, **kwargs)
    if address is not None:
        conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
    return conn


def local_port(conn: mavutil.mavfile | None) -> int | None:
    """Port of a pymavlink connection's socket; None when closed (None) or a serial port.

    The kernel's pick for ``udpin:HOST:0``; 0 for a ``udpout`` that has not sent yet.
    """
    try:
        return int(conn.port.getsockname()[1])
    except (AttributeError, OSError, IndexError):   # closed, serial, unix socket
        return None


#: Where free_udp_port looks. Below the UDP ports Fast DDS binds in every ROS process: its
#: well-known ports (7400 + 250 x domain + ...) and, measured (Jazzy, Fast DDS 2.14), one
#: socket on 0.0.0.0:7000 + k, the first k free, per participant process (a graph of 10
#: processes holds 7000-7009; a sim started after the check lost port 7003 that way in CI).
#: Below the kernel's ephemeral range (32768-60999 by default) too, and above the UDP ports PX4
#: and ArduPilot SITL bind (4560, 5501-5510) and the usual local services (mDNS 5353, SIP 5060).
SERVER_PORTS = range(6100, 6900)
PORT_TRIES = 50


def free_udp_port(rng: random.Random | None = None) -> int:
    """Return a UDP port on 127.0.0.1, free right now, for a server another process binds later.

    The sim's autopilot binds it a few seconds after this check, when its process is up. A
    port the kernel hands out (bind to port 0) lies in the ephemeral range, where every client
    socket opened meanwhile (a bridge's udpout, a DDS participant of another domain) may take
    it: a CI run once lost the sim to "Address already in use" that way. So the port is drawn
    at random from SERVER_PORTS, which nothing takes without asking for it by number.
    Between this check and the bind, another process may still take it: a server in this
    process binds port 0 instead and reads its port back (the links' ``local_port``).
    """
    rng = rng or random.SystemRandom()
    for _ in range(PORT_TRIES):
        port = rng.choice(SERVER_PORTS)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(('127.0.0.1', port))
            except OSError:
                continue
        return port
    raise OSError(f'no free UDP port in {SERVER_PORTS.start}-{SERVER_PORTS.stop - 1} after '
                  f'{PORT_TRIES} tries')
