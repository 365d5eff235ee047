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
