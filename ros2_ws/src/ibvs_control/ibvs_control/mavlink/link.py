"""MAVLink 2 link of the bridge: connection, signing, heartbeats, sending and receiving.

ROS-free (pymavlink only). The link knows nothing about modes or setpoints: it opens a
connection by URL (``udpin:0.0.0.0:14540`` = PX4's companion port, the default;
``udpout:host:port``, ``tcp:host:port``, serial ``/dev/ttyUSB0,921600``), speaks as an onboard
computer, signs what it sends when a key is configured (and then drops every unsigned or wrongly
signed message), learns the autopilot's system/component id from its first HEARTBEAT and
supervises the link from the autopilot's heartbeats.

A lost link (no HEARTBEAT for ``heartbeat_timeout_s``) does not reopen a UDP or TCP connection:
the socket, and so our address, is kept, because PX4 answers the first address it heard (a
udpout socket reopened on a new port was never answered again). UDP needs nothing else; TCP
reconnects once the peer closes (EOF / reset, then every ``reconnect_period_s``); a serial port is
reopened every ``reconnect_period_s`` while lost (a USB adapter may have been re-enumerated).
Everything that decides *what* to send lives in the other ``mavlink_*`` modules.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
import os
from pathlib import Path
import select
import threading
import time
from typing import Callable

import numpy as np

os.environ['MAVLINK20'] = '1'  # before pymavlink.mavutil is imported: MAVLink 2 framing
from pymavlink import mavutil  # noqa: E402  (must follow the MAVLINK20 switch)

from ibvs_common.core.mavlink_connection import local_port, open_mavlink  # noqa: E402
from ibvs_common.core.params import param  # noqa: E402

mavlink = mavutil.mavlink

SIGNING_KEY_LEN = 32            # bytes, MAVLink 2 signing secret key
MIN_HEARTBEAT_TIMEOUT_S = 3.0   # s, >= 3 periods of the autopilots' 1 Hz heartbeat
PEER_CONCURRENT_S = 1.0         # s (wall), a udpin peer heard this recently still sends
UINT32_MAX = 2**32 - 1


class MavType(IntEnum):
    """MAV_TYPE values the bridge uses or recognises."""

    GCS = 6
    ONBOARD_CONTROLLER = 18


class MavAutopilot(IntEnum):
    """MAV_AUTOPILOT values."""

    GENERIC = 0
    ARDUPILOTMEGA = 3
    INVALID = 8
    PX4 = 12


class MavComponent(IntEnum):
    """MAV_COMPONENT ids."""

    AUTOPILOT1 = 1
    ONBOARD_COMPUTER = 191


class MavState(IntEnum):
    """MAV_STATE values used in our HEARTBEAT."""

    ACTIVE = 4


class MavMsgId(IntEnum):
    """Message ids the bridge requests (MAV_CMD_SET_MESSAGE_INTERVAL) or exchanges."""

    HEARTBEAT = 0
    SYS_STATUS = 1
    PARAM_VALUE = 22
    SCALED_IMU = 26
    ATTITUDE_QUATERNION = 31
    COMMAND_ACK = 77
    ATTITUDE_TARGET = 83
    RC_CHANNELS = 65
    HIGHRES_IMU = 105
    TIMESYNC = 111
    EXTENDED_SYS_STATE = 245
    STATUSTEXT = 253
    EVENT = 410


UDP_CLIENT_TIMEOUT_S = 5   # udpin: stop sending to a peer silent this long (one is always kept)


# Message types of the autopilot that mean "someone else", never our peer autopilot.
_NON_AUTOPILOT_TYPES = frozenset({MavType.GCS, MavType.ONBOARD_CONTROLLER})


class SigningError(ValueError):
    """The signing key file is missing or does not hold a 32-byte key."""


def load_signing_key(path: str | os.PathLike) -> bytes:
    """Read a MAVLink 2 signing key: 32 raw bytes, or 64 hexadecimal characters (text).

    Raises SigningError with the path and the reason when the file is unusable.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise SigningError(f'cannot read signing key file {path}: {exc}') from exc
    if len(data) == SIGNING_KEY_LEN:
        return data
    text = data.strip()
    if len(text) == 2 * SIGNING_KEY_LEN:
        try:
            return bytes.fromhex(text.decode('ascii'))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningError(f'signing key file {path} must hold {SIGNING_KEY_LEN} raw bytes or '
                       f'{2 * SIGNING_KEY_LEN} hex characters (found {len(data)} bytes)')


@dataclass(frozen=True)
class LinkConfig:
    """Connection and link supervision (node parameters; the key is read from its file)."""

    url: str = param(
        'udpin:0.0.0.0:14540',
        "MAVLink endpoint (pymavlink URL): PX4 'udpin:0.0.0.0:14540', serial "
        "'/dev/ttyUSB0,921600'; a udpin port is ours alone (one another socket holds is "
        'refused and retried every reconnect_period_s)')
    source_system: int = param(1, "our MAVLink system id (the vehicle's)", 1, 255)
    source_component: int = MavComponent.ONBOARD_COMPUTER
    target_system: int = param(0, 'autopilot system id; 0 = learn from its first HEARTBEAT',
                               0, 255)
    target_component: int = param(
        0, 'autopilot component id; 0 = learn from its first HEARTBEAT', 0, 255)
    heartbeat_timeout_s: float = param(
        3.5, 's (steady clock; the ROS clock under use_sim_time), no autopilot HEARTBEAT this '
        'long: link lost; '
        f'>= {MIN_HEARTBEAT_TIMEOUT_S} (3 heartbeat periods)', MIN_HEARTBEAT_TIMEOUT_S, None)
    reconnect_period_s: float = param(
        1.0, 's (steady clock), reopen a broken socket / serial port this often', 0.0, None)
    signing_key: bytes | None = None         # 32 bytes: sign outgoing, reject unsigned input
    signing_link_id: int = param(0, 'MAVLink 2 signing link id', 0, 255)

    def __post_init__(self):
        if not self.url:
            raise ValueError('mavlink url must not be empty')
        if self.heartbeat_timeout_s <= 0.0 or self.reconnect_period_s <= 0.0:
            raise ValueError('heartbeat_timeout_s and reconnect_period_s must be > 0')
        if self.signing_key is not None and len(self.signing_key) != SIGNING_KEY_LEN:
            raise ValueError(f'signing key must be {SIGNING_KEY_LEN} bytes')


@dataclass
class LinkCounters:
    """Counters reported on /diagnostics."""

    received: int = 0
    sent: int = 0
    bad_data: int = 0             # unparsable or rejected (bad/missing signature) packets
    foreign: int = 0              # valid messages from other systems, ignored
    reconnects: int = 0           # link up again after a loss
    reopens: int = 0              # connection (re)opened after an error or a serial loss
    link_losses: int = 0
    send_errors: int = 0
    peers: int = 0                # addresses a udpin link heard from (1 = the autopilot only)


@dataclass(frozen=True)
class AutopilotHeartbeat:
    """The autopilot's last HEARTBEAT, decoded."""

    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int

    @property
    def armed(self) -> bool:
        """MAV_MODE_FLAG_SAFETY_ARMED of base_mode."""
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


class MavlinkLink:
    """One MAVLink 2 connection to one autopilot, polled (non-blocking) by its owner.

    ``clock`` returns monotonic seconds (injected for tests). The owner calls :meth:`poll`
    often; it returns the autopilot's messages (HEARTBEATs are also decoded into
    :attr:`heartbeat`) and, while the link is lost, reopens the connection every
    ``reconnect_period_s``. ``heartbeat_clock`` (default: ``clock``) times the HEARTBEATs for
    ``heartbeat_timeout_s``: the node gives it the ROS clock under simulated time, where the
    autopilot's 1 Hz HEARTBEAT is 1 Hz of simulated time (a firmware in lockstep, slower than
    real time on a busy machine), as MAVROS's connection timeout runs on ROS time.
    """

    def __init__(self, config: LinkConfig,
                 clock: Callable[[], float] = time.monotonic,
                 heartbeat_clock: Callable[[], float] | None = None) -> None:
        self.config = config
        self._clock = clock
        self._heartbeat_clock = clock if heartbeat_clock is None else heartbeat_clock
        self.counters = LinkCounters()
        self.target_system = config.target_system
        self.target_component = config.target_component
        self.heartbeat: AutopilotHeartbeat | None = None
        self._last_heartbeat_t: float | None = None
        self.heartbeat_at: float | None = None     # ``clock`` s of the newest HEARTBEAT
        self._link_up = False
        self._last_open_t = -np.inf
        self._conn = None
        self._events: list[tuple[str, str]] = []
        self._reported_error = ''       # last_error as last reported (each text once per loss)
        self._peers: list = []          # udpin: addresses heard from, in order
        self.last_error = ''
        self.open()

    # --- connection --------------------------------------------------------------------
    def open(self) -> None:
        """(Re)open the connection; errors are kept for the diagnostics, never raised."""
        self.close()
        self._last_open_t = self._clock()
        self.last_error = ''
        url = self.config.url
        try:
            # TCP: one connect attempt, never a blocking retry loop inside a poll (a failed
            # reconnect raises out of recv; poll() then reopens every reconnect_period_s).
            self._conn = open_mavlink(
                url, source_system=self.config.source_system,
                source_component=self.config.source_component, autoreconnect=True,
                retries=0, udp_timeout=UDP_CLIENT_TIMEOUT_S)
        except Exception as exc:  # OSError, serial errors, bad URL: reported, retried
            self._conn = None
            self._error(f'cannot open {self.config.url}: {exc}')
            return
        self._conn.mav.robust_parsing = True
        if self.config.signing_key is not None:
            # No allow_unsigned_callback: pymavlink then rejects unsigned and badly signed
            # input (it arrives as BAD_DATA, counted in bad_data).
            self._conn.setup_signing(self.config.signing_key, sign_outgoing=True,
                                     allow_unsigned_callback=None,
                                     link_id=self.config.signing_link_id)

    def close(self) -> None:
        """Close the connection if open."""
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing a broken socket/serial port: nothing left to do
                pass
            self._conn = None

    @property
    def is_serial(self) -> bool:
        """Whether the URL is a serial device (``/dev/...,baud``, ``COMn``)."""
        return not self.config.url.split(':', 1)[0] in ('udpin', 'udpout', 'udp', 'udpbcast',
                                                        'tcp', 'tcpin')

    @property
    def is_open(self) -> bool:
        """Whether a connection object exists (says nothing about the peer)."""
        return self._conn is not None

    @property
    def link_up(self) -> bool:
        """Whether an autopilot HEARTBEAT arrived within heartbeat_timeout_s."""
        return self._link_up

    @property
    def local_port(self) -> int | None:
        """Port of this end's socket; None while closed or on a serial port (``local_port``)."""
        return local_port(self._conn)

    def fileno(self) -> int | None:
        """File descriptor of the connection (socket or serial port), None while closed."""
        fd = getattr(self._conn, 'fd', None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def heartbeat_age(self) -> float:
        """Seconds since the autopilot's last HEARTBEAT (inf if none)."""
        if self._last_heartbeat_t is None:
            return float('inf')
        return self._heartbeat_clock() - self._last_heartbeat_t

    # --- receiving ---------------------------------------------------------------------
    def poll(self, max_messages: int = 200) -> list:
        """Read every pending message (at most max_messages) and supervise the link.

        Returns the valid messages of the target autopilot system (after learning it).
        """
        messages = []
        if self._conn is not None:
            for _ in range(max_messages):
                try:
                    msg = self._next_message()
                except Exception as exc:  # socket/serial error: reopen on the next period
                    self._error(f'receive failed on {self.config.url}: {exc}')
                    self.close()
                    break
                if msg is None:
                    break
                if msg.get_type() == 'BAD_DATA':
                    self.counters.bad_data += 1
                    continue
                if self._accept(msg):
                    self.counters.received += 1
                    messages.append(msg)
                else:
                    self.counters.foreign += 1
            self._check_peers()
        self._supervise()
        return messages

    def _next_message(self):
        """Return the next message pending on the connection, or None.

        pymavlink's ``recv_msg`` without its ``post_message``: that bookkeeping (per-system
        message dictionaries, sequence-loss counts, flight-mode strings) is used nowhere here,
        and it took a third of the CPU of each of the ~280 messages a second of the attitude,
        IMU and thrust streams (benchmarks/bench_mavlink_receive.py: 14.0 -> 8.7 us a message,
        docs/performance.md "Idle CPU"). Kept from ``recv_msg``: the read
        (``recv``; a UDP server learns its clients there), the switch to the MAVLink version of
        the first bytes, and the parse (signature checks included: a rejected message is
        BAD_DATA). A UDP read is one datagram, a stream read what the parser needs next.
        """
        conn = self._conn
        while True:
            data = conn.recv(conn.mav.bytes_needed())
            if data and conn.first_byte:
                conn.auto_mavlink_version(data)
            msg = conn.mav.parse_char(data)
            if msg is not None or not data:
                return msg

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) since the last call: connection errors, a second UDP peer.

        An error text is reported once, and again only after the link was up in between (a
        port that cannot be opened is retried every ``reconnect_period_s`` silently).
        """
        events, self._events = self._events, []
        return events

    def _error(self, text: str) -> None:
        self.last_error = text
        if text != self._reported_error:
            self._reported_error = text
            self._events.append(('error', f'MAVLink link: {text}'))

    def _check_peers(self) -> None:
        """udpin: warn once per new sender address while another one sends (a length test).

        pymavlink's udpin connection sends everything to every address it has heard from
        (dropping one silent for ``udp_timeout``), so a second MAVLink sender on this port (a
        GCS tool, a second autopilot or simulator) receives our setpoints and commands too, and
        its HEARTBEATs may be taken for the autopilot's when it uses the same system id. A new
        address while the earlier ones are silent (ArduPilot sends from an ephemeral port, so a
        restart changes it) is only noted.
        """
        clients = getattr(self._conn, 'clients', None)
        if not isinstance(clients, set) or len(clients) == len(self._peers):
            return
        alive = getattr(self._conn, 'clients_last_alive', {})
        now = time.time()                   # pymavlink's clock for clients_last_alive
        for address in sorted(clients - set(self._peers), key=str):
            others = [a for a in self._peers
                      if now - alive.get(a, -np.inf) < PEER_CONCURRENT_S]
            self._peers.append(address)
            here = f'{address[0]}:{address[1]}'
            if others:
                self._events.append(('warn', (
                    f'MAVLink link {self.config.url}: datagrams from a second address {here} '
                    f'while {others[0][0]}:{others[0][1]} sends too; the bridge sends to both. '
                    'Give every other MAVLink sender its own port (docs/mavlink.md "Link")')))
            elif len(self._peers) > 1:      # the old one went silent: a restart, likely
                self._events.append(('info', (
                    f'MAVLink link {self.config.url}: datagrams now from {here} (the earlier '
                    'address is silent: an autopilot restarted on a new source port?)')))
        self.counters.peers = len(self._peers)

    def _accept(self, msg) -> bool:
        """Filter to the autopilot; learn its ids from its first HEARTBEAT."""
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        is_hb = msg.get_type() == 'HEARTBEAT'
        if is_hb and (msg.type in _NON_AUTOPILOT_TYPES
                      or msg.autopilot == MavAutopilot.INVALID):
            return False
        if self.target_system == 0:
            if not is_hb:
                return False
            self.target_system = sysid
        if sysid != self.target_system:
            return False
        if is_hb:
            if self.target_component == 0:
                self.target_component = compid
            if compid != self.target_component:
                return False
            self.heartbeat = AutopilotHeartbeat(msg.autopilot, msg.type, msg.base_mode,
                                                msg.custom_mode, msg.system_status)
            self._last_heartbeat_t = self._heartbeat_clock()
            self.heartbeat_at = self._clock()
        return True

    def _supervise(self) -> None:
        now = self._clock()
        up = (self._last_heartbeat_t is not None
              and self._heartbeat_clock() - self._last_heartbeat_t
              <= self.config.heartbeat_timeout_s)
        if self._link_up and not up:
            self.counters.link_losses += 1
        elif up and not self._link_up and self.counters.link_losses:
            self.counters.reconnects += 1
        self._link_up = up
        if up:
            self._reported_error = ''       # a later failure is news again
        if up or now - self._last_open_t < self.config.reconnect_period_s:
            return
        # Lost (or never up): a broken connection is reopened; a serial port too once it was
        # heard; a working UDP/TCP socket is kept (the autopilot answers the address it knows).
        if self._conn is None or (self.is_serial and self._last_heartbeat_t is not None):
            self.counters.reopens += 1
            self.open()
        else:
            self._last_open_t = now

    # --- sending -----------------------------------------------------------------------
    def _send(self, encode: str, *args) -> bool:
        """Encode with ``mav.<encode>(*args)`` and send; errors counted, never raised."""
        if self._conn is None:
            return False
        try:
            self._conn.mav.send(getattr(self._conn.mav, encode)(*args))
        except Exception as exc:  # socket/serial error: counted, reopened by poll()
            self.counters.send_errors += 1
            self._error(f'send failed on {self.config.url}: {exc}')
            return False
        self.counters.sent += 1
        return True

    def send_heartbeat(self) -> bool:
        """HEARTBEAT as an onboard controller (MAV_TYPE 18, MAV_AUTOPILOT_INVALID 8)."""
        return self._send('heartbeat_encode', MavType.ONBOARD_CONTROLLER, MavAutopilot.INVALID,
                          0, 0, MavState.ACTIVE)

    def send_attitude_target(self, time_boot_ms: int, q_wxyz: np.ndarray, thrust: float,
                             type_mask: int) -> bool:
        """SET_ATTITUDE_TARGET (82): attitude FRD in NED as (w, x, y, z), thrust in [0, 1]."""
        if self.target_system == 0:
            return False
        q = [float(x) for x in q_wxyz]
        return self._send('set_attitude_target_encode', int(time_boot_ms) & UINT32_MAX,
                          self.target_system, self.target_component, int(type_mask), q,
                          0.0, 0.0, 0.0, float(thrust))

    def send_timesync(self, tc1: int, ts1: int) -> bool:
        """TIMESYNC (111), times in ns: a request is (0, our time), an answer (our time, ts1).

        Not addressed: the common dialect of pymavlink 2.4.x has no TIMESYNC target fields.
        """
        if self.target_system == 0:
            return False
        return self._send('timesync_encode', int(tc1), int(ts1))

    def send_command_long(self, command: int, params: tuple[float, ...],
                          confirmation: int = 0) -> bool:
        """COMMAND_LONG to the autopilot; params padded to 7."""
        if self.target_system == 0:
            return False
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return self._send('command_long_encode', self.target_system, self.target_component,
                          int(command), confirmation, *p)

    def request_param(self, name: str) -> bool:
        """PARAM_REQUEST_READ by name (param_index -1)."""
        if self.target_system == 0:
            return False
        return self._send('param_request_read_encode', self.target_system,
                          self.target_component, name.encode('ascii'), -1)

    def set_message_interval(self, msg_id: int, rate_hz: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL (511): param1 message id, param2 interval in us."""
        interval_us = 1e6 / rate_hz if rate_hz > 0.0 else -1.0
        return self.send_command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                      (float(msg_id), interval_us))


class MavlinkReader:
    """Handle MAVLink input as it arrives: a thread waits on the link, then calls back.

    The thread blocks in ``select`` on the link's file descriptor (no poll timer) and, when
    input is pending, calls ``on_readable()`` with ``lock`` held; the owner takes the same lock
    around every other use of the link and of what it feeds, so that ``on_readable`` (which
    reads and handles every pending message) never runs beside them. While the link is closed,
    or after a wait of ``wait_s`` (steady clock) without input, it looks at the link's
    descriptor again: a reopened link is followed within ``wait_s``. It never reopens or
    supervises the link itself (the owner's timer does). MAVROS's libmavconn reads in its own
    I/O thread in the same way.
    """

    def __init__(self, link: MavlinkLink, lock: threading.Lock,
                 on_readable: Callable[[], None], wait_s: float = 0.1,
                 on_error: Callable[[str], None] | None = None) -> None:
        if not wait_s > 0.0:
            raise ValueError(f'wait_s must be > 0, got {wait_s}')
        self._link = link
        self._lock = lock
        self._on_readable = on_readable
        self._on_error = on_error
        self._wait_s = wait_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.wakeups = 0                    # times on_readable was called
        self.errors = 0                     # exceptions of on_readable, given to on_error
        self.last_error = ''

    def start(self) -> None:
        """Start the reader thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name='mavlink_reader',
                                            daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the thread and wait for it (at most ``timeout_s``, steady clock)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _readable(self) -> bool:
        fd = self._link.fileno()
        if fd is None:
            self._stop.wait(self._wait_s)
            return False
        try:
            ready, _, _ = select.select([fd], [], [], self._wait_s)
        except (OSError, ValueError):       # closed under us (reopen): look again
            self._stop.wait(self._wait_s)
            return False
        return bool(ready)

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._readable():
                continue
            error = ''
            with self._lock:
                if self._stop.is_set():
                    return
                self.wakeups += 1
                try:
                    self._on_readable()
                except Exception as exc:    # a bug must not end the reading: reported
                    self.errors += 1
                    error = self.last_error = f'{type(exc).__name__}: {exc}'
            if error:
                if self._on_error is not None:
                    self._on_error(error)
                self._stop.wait(self._wait_s)   # not a busy loop on a persistent error
