"""The autopilot's telemetry, decoded for the bridge (ROS-free, no I/O).

What comes in (docs/mavlink.md "Telemetry"):

- ATTITUDE_QUATERNION -> an imu/data sample (ENU/FLU as MAVROS converts; stamp = time_boot_ms
  on the ROS clock by the TIMESYNC offset, nothing while unsynced), the current yaw and tilt;
- HIGHRES_IMU (PX4, m/s^2) or SCALED_IMU (ArduPilot, which has no HIGHRES_IMU; milli-g) -> the
  specific force in body FRD: imu/data's linear_acceleration, the hover-thrust estimator's
  measurement and the touchdown rule's evidence;
- ATTITUDE_TARGET -> the collective thrust the autopilot's attitude controller applies (in any
  mode: the estimator's input);
- EXTENDED_SYS_STATE -> landed state; SYS_STATUS -> armable (MAV_SYS_STATUS_PREARM_CHECK health
  bit, as both PX4 and ArduPilot report it) and ArduPilot's internal-error mask;
- STATUSTEXT and PX4's EVENT (id 410; pymavlink 2.4.50 does not know it: decoded here from the
  raw payload) -> the autopilot's reasons, logged.

:class:`StreamRequests` asks for the streams with MAV_CMD_SET_MESSAGE_INTERVAL at their
documented rates, one request at a time until each is acknowledged, again after every link loss
and autopilot reboot (an autopilot forgets them), whatever it streams by default. A refused
request (ArduPilot has no HIGHRES_IMU: it answers DENIED and tells the pilot's GCS) is not
repeated; the lists per autopilot never ask for what it lacks.
"""
from __future__ import annotations

from dataclasses import dataclass
import json
import lzma
import math
import re
import struct
from typing import Any, Iterable

import numpy as np

from ibvs_common.core.frames import (
    GRAVITY, quat_ned_frd_to_enu_flu, vec_frd_to_flu, yaw_and_cos_tilt_from_quat)
from ibvs_control.mavlink.link import mavlink, MavMsgId
from ibvs_control.mavlink.time_sync import TimeSync

NS_PER_MS = 1_000_000
NS_PER_US = 1_000
MILLI_G = GRAVITY / 1000.0                 # SCALED_IMU acceleration unit, m/s^2
QUAT_NORM_TOLERANCE = 0.1                  # |q| in [0.9, 1.1], else the sample is dropped
IMU_DROP_WARN_PERIOD_S = 2.0               # s (monotonic) between "IMU dropped" warnings
REASON_REPEAT_S = 5.0                      # the same reason text is logged once per this
MAX_SPECIFIC_FORCE = 8.0 * GRAVITY         # m/s^2, a larger specific force is a bad sample
SYS_STATUS_PREARM_CHECK = 1 << 28          # MAV_SYS_STATUS_PREARM_CHECK
AP_INTERNAL_ERROR_FLOW_OF_CONTROL = 0x100000   # ArduPilot InternalError flow_of_ctrl (#26865)
EVENT_PAYLOAD = struct.Struct('<IIHBBB40s')    # MAVLink EVENT (410), wire order
MAVLINK2_HEADER_LEN = 10


class LandedState:
    """MAV_LANDED_STATE of EXTENDED_SYS_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


@dataclass(frozen=True)
class ImuSample:
    """One imu/data message in ROS conventions (ENU/FLU as MAVROS converts them)."""

    stamp_ns: int                   # ROS time
    q_wxyz: np.ndarray              # base_link (FLU) in map (ENU), (w, x, y, z)
    angular_velocity_flu: np.ndarray  # rad/s
    linear_acceleration_flu: np.ndarray | None  # m/s^2 (specific force), None: not streamed


@dataclass(frozen=True)
class AccelSample:
    """Specific force measured by the autopilot's IMU, body FRD."""

    boot_ns: int                    # the autopilot's boot time of the sample
    f_frd: np.ndarray               # m/s^2 ((0, 0, -g) at rest)
    cos_tilt: float                 # cos of the tilt of the latest attitude (1 if unknown)


@dataclass(frozen=True)
class ThrustSample:
    """The collective thrust the autopilot's attitude controller applies (ATTITUDE_TARGET)."""

    boot_ns: int
    thrust: float                   # normalised [0, 1]


def decode_event(msg: Any) -> tuple[int, int, int, bytes] | None:
    """(id, sequence, log_levels, arguments) of a PX4 EVENT (410), or None.

    pymavlink 2.4.50's dialects lack EVENT: it arrives as UNKNOWN_410 whose ``data`` is the
    whole MAVLink 2 frame; the payload (zero-truncated on the wire) is unpacked here. A newer
    pymavlink decodes it: its fields are used.
    """
    if msg.get_type() == 'EVENT':
        return int(msg.id), int(msg.sequence), int(msg.log_levels), bytes(msg.arguments)
    data = bytes(getattr(msg, 'data', b''))
    if len(data) < MAVLINK2_HEADER_LEN or data[0] != 0xFD:
        return None
    payload = data[MAVLINK2_HEADER_LEN:MAVLINK2_HEADER_LEN + data[1]]
    payload = payload.ljust(EVENT_PAYLOAD.size, b'\x00')[:EVENT_PAYLOAD.size]
    eid, _t_ms, seq, _dcomp, _dsys, levels, args = EVENT_PAYLOAD.unpack(payload)
    return eid, seq, levels, args


def load_px4_events(path: str) -> dict[int, str]:
    """Event id -> 'name: message' from PX4's events metadata (all_events.json[.xz]).

    The id on the wire is (component id << 24) | event id, as PX4 builds it.
    """
    opener = lzma.open if str(path).endswith('.xz') else open
    with opener(path, 'rt') as f:
        data = json.load(f)
    out = {}
    for cid, comp in data.get('components', {}).items():
        for group in comp.get('event_groups', {}).values():
            for eid, ev in group.get('events', {}).items():
                text = f"{ev.get('name', '?')}: {ev.get('message', '')}"
                out[(int(cid) << 24) | int(eid)] = text
    return out


def internal_errors_text(mask: int) -> str:
    """Explain ArduPilot's internal-error mask (the one bit we know the story of)."""
    text = f'ArduPilot reports internal errors 0x{mask:x}'
    if mask & AP_INTERNAL_ERROR_FLOW_OF_CONTROL:
        text += (' = flow_of_ctrl (0x100000): ArduCopter 4.5 raises it after a take-off with '
                 'SET_ATTITUDE_TARGET thrust (GUID_OPTIONS bit 3; ArduPilot issue #26865, '
                 'fixed in 4.6); it refuses to arm again until rebooted')
    return text


class Telemetry:
    """Decodes the autopilot's messages into what the bridge uses (see the module doc)."""

    def __init__(self, time_sync: TimeSync, clock, px4_events: dict | None = None) -> None:
        self.time_sync = time_sync
        self._clock = clock
        self._px4_events = px4_events or {}
        self.yaw_now = 0.0                       # NED yaw of the latest attitude (rad)
        self.cos_tilt_now = 1.0                  # cos tilt of the latest attitude
        self.accel: AccelSample | None = None    # latest specific force
        self.thrust: ThrustSample | None = None  # latest applied thrust
        self.landed_state: int | None = None     # MAV_LANDED_STATE, None: never reported
        self.armable: bool | None = None         # SYS_STATUS pre-arm health bit
        self.internal_errors: int = 0            # ArduPilot's mask (SYS_STATUS or STATUSTEXT)
        self.imu_dropped_unsynced = 0
        self.reasons = 0                         # STATUSTEXT / EVENT messages received
        self.last_reason = ''
        self._events: list[tuple[str, str]] = []
        self._imu_drop_reported = 0
        self._imu_drop_warned_t = -math.inf
        self._reason_logged: dict[str, float] = {}
        self._ros_ns: int | None = None

    @property
    def landed(self) -> bool | None:
        """True on the ground, False in the air (take-off, landing too), None unknown."""
        if self.landed_state in (None, LandedState.UNDEFINED):
            return None
        return self.landed_state == LandedState.ON_GROUND

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) since the last call; level 'reason' = the autopilot's own words."""
        events, self._events = self._events, []
        return events

    def reset(self) -> None:
        """Forget per-boot state (link back, autopilot reboot)."""
        self.accel = self.thrust = None
        self.landed_state = None
        self.armable = None

    # --- messages ------------------------------------------------------------------------------
    def on_message(self, msg: Any, ros_ns: int | None) -> tuple:
        """Take one autopilot message; return what it produced: (IMU, accel, thrust) samples."""
        self._ros_ns = ros_ns
        kind = msg.get_type()
        if kind == 'ATTITUDE_QUATERNION':
            return self._attitude(msg), None, None
        if kind == 'HIGHRES_IMU':
            return None, self._accel(int(msg.time_usec) * NS_PER_US,
                                     (msg.xacc, msg.yacc, msg.zacc)), None
        if kind == 'SCALED_IMU':
            return None, self._accel(int(msg.time_boot_ms) * NS_PER_MS,
                                     (msg.xacc * MILLI_G, msg.yacc * MILLI_G,
                                      msg.zacc * MILLI_G)), None
        if kind == 'ATTITUDE_TARGET':
            thrust = float(msg.thrust)
            if math.isfinite(thrust) and 0.0 <= thrust <= 1.0:
                self.thrust = ThrustSample(int(msg.time_boot_ms) * NS_PER_MS, thrust)
                return None, None, self.thrust
        elif kind == 'EXTENDED_SYS_STATE':
            self.landed_state = int(msg.landed_state)
        elif kind == 'SYS_STATUS':
            self._sys_status(msg)
        elif kind == 'STATUSTEXT':
            self._statustext(msg)
        elif kind in ('EVENT', 'UNKNOWN_410'):
            self._event_msg(msg)
        return None, None, None

    def _attitude(self, msg) -> ImuSample | None:
        q = (float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4))
        w = (float(msg.rollspeed), float(msg.pitchspeed), float(msg.yawspeed))
        if (not all(map(math.isfinite, q + w))
                or abs(math.sqrt(sum(v * v for v in q)) - 1.0) > QUAT_NORM_TOLERANCE):
            self._events.append(('error', f'ATTITUDE_QUATERNION out of range (q={q}, rates={w}): '
                                          'dropped'))
            return None
        self.yaw_now, self.cos_tilt_now = yaw_and_cos_tilt_from_quat(q)
        boot_ms = int(msg.time_boot_ms)
        self._events += self.time_sync.on_boot_time('time_boot_ms', boot_ms * NS_PER_MS)
        stamp_ns = self.time_sync.boot_ms_to_ros_ns(boot_ms)
        if stamp_ns is None:
            self._imu_unsynced()
            return None
        acc = None if self.accel is None else vec_frd_to_flu(self.accel.f_frd)
        return ImuSample(stamp_ns, quat_ned_frd_to_enu_flu(q), vec_frd_to_flu(w), acc)

    def _accel(self, boot_ns: int, f) -> AccelSample | None:
        f = tuple(float(v) for v in f)
        if not all(map(math.isfinite, f)) or math.hypot(*f) > MAX_SPECIFIC_FORCE:
            return None
        self.accel = AccelSample(int(boot_ns), np.array(f), self.cos_tilt_now)
        return self.accel

    def _sys_status(self, msg) -> None:
        self.armable = bool(msg.onboard_control_sensors_health & SYS_STATUS_PREARM_CHECK)
        # ArduPilot: errors_count1/2 carry the low/high 16 bits of its internal-error mask
        mask = (int(msg.errors_count1) & 0xFFFF) | ((int(msg.errors_count2) & 0xFFFF) << 16)
        self._internal_errors(mask, 'SYS_STATUS')

    def _internal_errors(self, mask: int, where: str) -> None:
        new = mask & ~self.internal_errors
        if new:
            self.internal_errors |= mask
            self._events.append(('error', f'{internal_errors_text(mask)} ({where})'))

    def _statustext(self, msg) -> None:
        text = msg.text if isinstance(msg.text, str) else msg.text.decode('ascii', 'replace')
        text = text.rstrip('\x00').strip()
        m = re.search(r'internal errors?\s+0x([0-9a-f]+)', text, re.IGNORECASE)
        if m:
            self._internal_errors(int(m.group(1), 16), f'STATUSTEXT "{text}"')
        self._reason(int(msg.severity), f'autopilot: {text}')

    def _event_msg(self, msg) -> None:
        ev = decode_event(msg)
        if ev is None:
            return
        eid, seq, levels, args = ev
        described = self._px4_events.get(eid)
        args_hex = args.rstrip(b'\x00').hex() or '-'
        text = (f'autopilot event 0x{eid:08x}' + (f' ({described})' if described else '')
                + f' args {args_hex} (seq {seq})')
        # log_levels: low nibble = external level (MAV_SEVERITY-like, 0 emergency .. 7 debug)
        self._reason(levels & 0x0F, text)

    def _reason(self, severity: int, text: str) -> None:
        self.reasons += 1
        self.last_reason = text
        now = self._clock()
        last = self._reason_logged.get(text)
        if last is not None and now - last < REASON_REPEAT_S:
            return
        self._reason_logged[text] = now
        level = 'error' if severity <= 3 else 'warn' if severity == 4 else 'info'
        self._events.append((f'reason-{level}', text))

    def _imu_unsynced(self) -> None:
        """Count an IMU sample dropped for want of the clock offset; warn now and then."""
        self.imu_dropped_unsynced += 1
        now = self._clock()
        if now - self._imu_drop_warned_t < IMU_DROP_WARN_PERIOD_S:
            return
        self._imu_drop_warned_t = now
        n = self.imu_dropped_unsynced - self._imu_drop_reported
        self._imu_drop_reported = self.imu_dropped_unsynced
        ts = self.time_sync
        why = ('no ROS time yet' if self._ros_ns is None or self._ros_ns <= 0
               else f'{ts.init_progress} of {ts.config.init_samples} TIMESYNC samples, '
                    f'{ts.rejected_rtt} rejected for their round trip')
        self._events.append(('warn', f'imu/data: {n} sample(s) dropped, clock not synced with '
                                     f'the autopilot yet ({why}); {self.imu_dropped_unsynced} '
                                     'in all'))


# --- stream requests -----------------------------------------------------------------------------

@dataclass
class _Stream:
    msg_id: int
    rate_hz: float
    done: bool = False
    attempts: int = 0


#: what the bridge reads without asking for a stream: never switched off by ``streams_off``
USED_UNREQUESTED = (MavMsgId.HEARTBEAT, MavMsgId.TIMESYNC, MavMsgId.PARAM_VALUE,
                    MavMsgId.COMMAND_ACK, MavMsgId.STATUSTEXT, MavMsgId.EVENT)


def message_ids(names: Iterable[str]) -> tuple[int, ...]:
    """Return the message ids of MAVLink message names ('ATTITUDE', ...).

    Raises ValueError naming an unknown one.
    """
    ids = []
    for name in names:
        msg_id = getattr(mavlink, f'MAVLINK_MSG_ID_{str(name).strip().upper()}', None)
        if msg_id is None:
            raise ValueError(f'unknown MAVLink message name {name!r}')
        ids.append(int(msg_id))
    return tuple(ids)


def streams_for(autopilot: str, attitude_hz: float, imu_hz: float, thrust_hz: float,
                status_hz: float, heartbeat_hz: float,
                off: tuple = (), extra: tuple = ()) -> list[tuple[int, float]]:
    """Return the (message id, rate) list to ask ``autopilot`` ('px4' | 'ardupilot') for.

    PX4: ATTITUDE_QUATERNION, HIGHRES_IMU, ATTITUDE_TARGET, EXTENDED_SYS_STATE, SYS_STATUS
    (its HEARTBEAT rate is fixed: a request fails). ArduPilot: the same with SCALED_IMU instead
    of HIGHRES_IMU (which it lacks), and HEARTBEAT at ``heartbeat_hz`` (a pilot's mode switch is
    then seen within 1 / heartbeat_hz). Then rate 0 (SET_MESSAGE_INTERVAL -1: stream off) for
    each message id of ``off`` that the bridge does not use (the others are ignored): what
    PX4's onboard link streams by default costs the bridge CPU for every message it parses.
    ``extra``: more (message id, rate) streams wanted (RC_CHANNELS for the pilot's switch).
    """
    common = [(MavMsgId.ATTITUDE_QUATERNION, attitude_hz), (MavMsgId.ATTITUDE_TARGET, thrust_hz),
              (MavMsgId.EXTENDED_SYS_STATE, status_hz), (MavMsgId.SYS_STATUS, status_hz)]
    if autopilot == 'ardupilot':
        wanted = common[:1] + [(MavMsgId.SCALED_IMU, imu_hz)] + common[1:] + [
            (MavMsgId.HEARTBEAT, heartbeat_hz)]
    else:
        wanted = common[:1] + [(MavMsgId.HIGHRES_IMU, imu_hz)] + common[1:]
    wanted += [(int(i), float(r)) for i, r in extra]
    used = {int(i) for i, _ in wanted} | {int(i) for i in USED_UNREQUESTED}
    return wanted + [(int(i), 0.0) for i in dict.fromkeys(off) if int(i) not in used]


class StreamRequests:
    """SET_MESSAGE_INTERVAL for each stream, one in flight at a time, until acknowledged.

    :meth:`step` returns the (id, rate) to request now (or None); :meth:`on_ack` takes the
    COMMAND_ACK of MAV_CMD_SET_MESSAGE_INTERVAL (the ACK names no message: hence one at a time).
    ACCEPTED: done. Another result: refused, not asked again (logged). No answer within
    ``ack_timeout_s``: asked again, at most ``max_attempts`` times. :meth:`reset` starts over;
    :meth:`set_rate` re-targets one stream (the bridge's quiet telemetry).
    """

    def __init__(self, streams: list[tuple[int, float]], ack_timeout_s: float = 0.5,
                 max_attempts: int = 3) -> None:
        self._streams = [_Stream(int(i), float(r)) for i, r in streams]
        self.ack_timeout_s = ack_timeout_s
        self.max_attempts = max_attempts
        self._in_flight: _Stream | None = None
        self._in_flight_rate = math.nan
        self._sent_t = -math.inf
        self.refused: list[int] = []

    @property
    def complete(self) -> bool:
        """Whether every stream was answered (or given up)."""
        return all(s.done for s in self._streams)

    def reset(self) -> None:
        """Ask for every stream again (after a link loss or an autopilot reboot)."""
        for s in self._streams:
            s.done, s.attempts = False, 0
        self._in_flight = None
        self.refused = []

    def set_rate(self, msg_id: int, rate_hz: float) -> bool:
        """Want ``msg_id`` at ``rate_hz`` from now on; return whether a new request is due.

        A changed rate is asked for again (even while its previous request is in flight: that
        ACK then does not complete it); a stream the autopilot refused stays given up.
        """
        s = self._find(msg_id)
        if s is None or s.rate_hz == float(rate_hz) or s.msg_id in self.refused:
            return False
        s.rate_hz, s.done, s.attempts = float(rate_hz), False, 0
        return True

    def rate(self, msg_id: int) -> float | None:
        """Return the rate wanted now for ``msg_id`` (None: not one of the streams)."""
        s = self._find(msg_id)
        return None if s is None else s.rate_hz

    def _find(self, msg_id: int) -> _Stream | None:
        return next((x for x in self._streams if x.msg_id == int(msg_id)), None)

    def step(self, now: float) -> tuple[int, float] | None:
        """Return the next request to send now, or None."""
        s = self._in_flight
        if s is not None and now - self._sent_t < self.ack_timeout_s:
            return None
        if s is not None and s.attempts >= self.max_attempts:
            s.done = True                     # no answer at all: give up on it
        self._in_flight = next((x for x in self._streams if not x.done), None)
        if self._in_flight is None:
            return None
        self._in_flight.attempts += 1
        self._sent_t = now
        self._in_flight_rate = self._in_flight.rate_hz
        return self._in_flight.msg_id, self._in_flight.rate_hz

    def on_ack(self, result: int) -> str:
        """Take the ACK of the request in flight; return a warning text if it was refused."""
        s, self._in_flight = self._in_flight, None
        if s is None:
            return ''
        self._sent_t = -math.inf
        if s.rate_hz != self._in_flight_rate:      # re-targeted meanwhile: ask the new rate
            return ''
        s.done = True
        if int(result) == 0 or s.rate_hz == 0.0:   # off: refused = no such stream there
            return ''
        self.refused.append(s.msg_id)
        return (f'the autopilot refused message {s.msg_id} at {s.rate_hz:g} Hz '
                f'(SET_MESSAGE_INTERVAL result {int(result)}): not asked again')


class QuietTelemetry:
    """The high-rate streams slowed while the vehicle rests: disarmed, nothing engaging.

    On the pad with the cameras off, nothing of the graph uses the 100 Hz attitude and IMU
    (no mode flies, no frame is evaluated), yet each sample wakes the bridge's reader thread:
    ~150 wake-ups a second, most of the idle graph's CPU (docs/performance.md). While the
    bridge reports :meth:`update` ``wanted`` (its ``at_rest``: standby, IDLE, disarmed, no arm
    request, no frame evaluated) for ``delay_s`` of the steady clock, every stream of ``full``
    is asked for at ``min(full rate, quiet_rate_hz)``; as soon as it is not wanted (an arm
    request, a supervisor mode, a frame status, the vehicle armed by its pilot, a link loss),
    at its full rate again: the rates change before anything engages, never while the vehicle
    flies. ``quiet_rate_hz`` 0: off (full rates always, as MAVROS streams them).
    """

    def __init__(self, full: dict[int, float], quiet_rate_hz: float, delay_s: float) -> None:
        self.full = {int(i): float(r) for i, r in full.items()}
        self.quiet_rate_hz = float(quiet_rate_hz)
        self.delay_s = float(delay_s)
        self.active = False
        self._wanted_since: float | None = None

    def update(self, wanted: bool, now: float) -> dict[int, float] | None:
        """Return the rates to ask for if the state changes now, else None."""
        if not wanted or self.quiet_rate_hz <= 0.0:
            self._wanted_since = None
            return self._switch(False)
        if self._wanted_since is None:
            self._wanted_since = now
        return self._switch(now - self._wanted_since >= self.delay_s)

    def reset(self) -> dict[int, float]:
        """Full rates from now on (link back, autopilot reboot); return them."""
        self._wanted_since, self.active = None, False
        return self.rates()

    def rates(self) -> dict[int, float]:
        """Return the rates of the current state."""
        if not self.active:
            return dict(self.full)
        return {i: min(r, self.quiet_rate_hz) for i, r in self.full.items()}

    def _switch(self, active: bool) -> dict[int, float] | None:
        if active == self.active:
            return None
        self.active = active
        return self.rates()
