"""The sim autopilot's MAVLink endpoint: UDP socket, signing, reading, dispatch, addressing.

``url`` (pymavlink, e.g. ``udpin:127.0.0.1:14560``): the autopilot listens and learns its peer
from the first datagram; nothing is sent before a peer has written. With a signing key every
message sent is signed (link id 0) and every unsigned or wrongly signed one is rejected.
Malformed, truncated, unknown and foreign input is counted and dropped; one bad message never
takes the autopilot down. No clocks here: the handlers get the ground truth of the poll.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

from ibvs_sim.core.autopilot.config import (AutopilotConfig, AutopilotCounters, RateLimitedLog,
                                            VehicleStateView)
from ibvs_common.core.mavlink_connection import local_port, open_mavlink
from ibvs_sim.core.autopilot.protocol import (BROADCAST_ID, mavlink, MAVLINK_DIALECT,
                                              STATUSTEXT_LEN)

# A handler of one message type: (decoded pymavlink message, ground truth of the poll).
Handler = Callable[[Any, VehicleStateView], None]


def load_signing_key(path: str) -> bytes:
    """Read a 32-byte MAVLink 2 signing key: raw 32 bytes, or 64 hex characters.

    Raises ValueError (with the path) when the file cannot be read or holds anything else.
    """
    try:
        with open(path, 'rb') as f:
            data = f.read()
    except OSError as exc:
        raise ValueError(f'cannot read signing key file {path}: {exc}') from exc
    key_len = 32
    if len(data) == key_len:
        return data
    text = data.strip()
    if len(text) == 2 * key_len:
        try:
            return bytes.fromhex(text.decode('ascii'))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ValueError(f'{path}: a signing key is 32 raw bytes or 64 hex characters')


class AutopilotLink:
    """The autopilot's MAVLink endpoint (system ``config.system_id``, ``component_id``).

    UDP, or a serial port (``/dev/...,baud``: a byte stream, read as one). Opens it on
    construction (and sets up signing when ``config.signing_key_file``).
    """

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 warn: RateLimitedLog) -> None:
        """Open ``config.url``; raise ValueError for an unreadable or malformed signing key."""
        self.config = config
        self.counters = counters
        self._warn = warn
        self._known_peers = 0
        self._conn = open_mavlink(config.url, source_system=config.system_id,
                                  source_component=config.component_id,
                                  dialect=MAVLINK_DIALECT)
        self._datagrams = hasattr(self._conn.port, 'recvfrom')   # UDP: whole messages
        if config.signing_key_file:
            key = load_signing_key(config.signing_key_file)
            self._conn.setup_signing(key, sign_outgoing=True,
                                     allow_unsigned_callback=lambda _mav, _msg_id: False,
                                     link_id=0)

    @property
    def mav(self) -> mavlink.MAVLink:
        """The pymavlink MAVLink object to send with (``mav.<message>_send``)."""
        return self._conn.mav

    def fileno(self) -> int:
        """File descriptor of the MAVLink socket (to wait on it with select)."""
        return self._conn.port.fileno()

    @property
    def local_port(self) -> int | None:
        """UDP port the endpoint is bound to (the kernel's pick for ``udpin:HOST:0``)."""
        return local_port(self._conn)

    def close(self) -> None:
        """Close the UDP endpoint."""
        try:
            self._conn.close()
        except OSError:
            pass

    def peer_known(self) -> bool:
        """Tell whether sends can go out ('udpin' learns its peer from the first packet)."""
        if getattr(self._conn, 'udp_server', False):
            return bool(self._conn.clients)
        return True

    def statustext(self, severity: int, text: str) -> None:
        """Send a STATUSTEXT (ASCII, cut to 50 characters)."""
        self._conn.mav.statustext_send(severity, text.encode('ascii', 'replace')[:STATUSTEXT_LEN])

    def for_us(self, target_system: int, target_component: int) -> bool:
        """Tell whether a message addressed so is for this autopilot (0 = broadcast); count not."""
        ok = (target_system in (BROADCAST_ID, self.config.system_id)
              and target_component in (BROADCAST_ID, self.config.component_id))
        if not ok:
            self.counters.foreign_target += 1
            self._warn.warning('foreign', 'ignored a message for %d/%d', target_system,
                               target_component)
        return ok

    def receive(self, state: VehicleStateView, handlers: Mapping[str, Handler],
                on_new_peer: Callable[[], None]) -> None:
        """Read every pending datagram (at most max_messages_per_poll) and dispatch its messages.

        ``handlers`` maps a message type to its handler, called with ``state``; a HEARTBEAT is
        read and dropped, other types are counted as unknown. ``on_new_peer`` is called when the
        number of peers heard from changes (greet a new peer at once). Never blocks.
        """
        mav = self._conn.mav
        for _ in range(self.config.max_messages_per_poll):
            try:
                data = self._conn.recv()
            except OSError as exc:
                self.counters.socket_errors += 1
                self._warn.warning('socket', 'UDP receive error: %s', exc)
                return
            if not data:
                return
            peers = len(getattr(self._conn, 'clients', ()))
            if peers != self._known_peers:
                self._known_peers = peers
                on_new_peer()
            rejected_before = mav.signing.reject_count
            try:
                msgs = mav.parse_buffer(data) or []
            except Exception as exc:  # pymavlink raises assorted errors on hostile input
                self.counters.malformed += 1
                self._warn.warning('parse', 'MAVLink parser error: %s', exc)
                msgs = []
            if self._datagrams and mav.buf_len() > 0:
                # A datagram carries whole messages: a leftover is a truncated one. Drop it so
                # it cannot swallow the next datagram. (A serial read may end inside a message:
                # the rest comes with the next read.)
                self.counters.malformed += 1
                mav.buf = bytearray()
                mav.buf_index = 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
            self.counters.signing_rejected += mav.signing.reject_count - rejected_before
            for msg in msgs:
                try:
                    self._dispatch(msg, state, handlers)
                except Exception as exc:  # never let one message take the autopilot down
                    self.counters.malformed += 1
                    self._warn.warning('dispatch', 'error handling %s: %r', msg.get_type(), exc)

    def _dispatch(self, msg, state: VehicleStateView, handlers: Mapping[str, Handler]) -> None:
        mtype = msg.get_type()
        if mtype == 'BAD_DATA':
            if getattr(msg, 'reason', '') == 'Invalid signature':
                self._warn.warning('signing', 'rejected an unsigned or wrongly signed message')
            else:
                self.counters.malformed += 1
                self._warn.warning('bad', 'malformed MAVLink input: %s',
                                   getattr(msg, 'reason', '?'))
            return
        self.counters.messages_received += 1
        if mtype.startswith('UNKNOWN'):
            self.counters.unknown_messages += 1
            self._warn.warning('unknown', 'unknown MAVLink message %s', mtype)
            return
        if mtype == 'HEARTBEAT':
            return  # a GCS / companion heartbeat: nothing to do
        handler = handlers.get(mtype)
        if handler is None:
            self.counters.unknown_messages += 1
            self._warn.warning('unhandled', 'MAVLink %s not handled by the sim autopilot', mtype)
            return
        handler(msg, state)
