"""The MAVLink bridge without ROS: a thin composition of its parts (docs/mavlink.md).

- :mod:`~ibvs_control.mavlink.link`: connection, signing, heartbeats, link supervision;
- :mod:`~ibvs_control.mavlink.time_sync`: clock offset by TIMESYNC (and its message exchange);
- :mod:`~ibvs_control.mavlink.telemetry`: autopilot messages -> imu/data samples, specific
  force, applied thrust, landed state, armability, the autopilot's reasons; stream requests;
- :mod:`~ibvs_control.mavlink.setpoints`: force / heading pairing and SET_ATTITUDE_TARGET;
- :mod:`~ibvs_control.mavlink.hover`: hover thrust seed and online estimate;
- :mod:`~ibvs_control.mavlink.params`: the autopilot parameters read and what they imply;
- :mod:`~ibvs_control.mavlink.safety`: the safety policy's table and detectors;
- :mod:`~ibvs_control.mavlink.sequencer`: engage / arm / hand-back state machine (one
  strategy per autopilot).

The node feeds :class:`MavlinkBridge` the force and heading setpoints, the supervisor's mode
and arm requests, and calls :meth:`MavlinkBridge.poll` (receive: when input is pending, from
its reader thread, and at the stream rate), :meth:`MavlinkBridge.stream` (repeat the latest
setpoint when none left for 1 / stream_rate_hz)
and :meth:`MavlinkBridge.heartbeat` (1 Hz), with the ROS time (system time on a vehicle, sim
time in the sim): the clock of the stamps, of the clock sync and of the safety's hold.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
import struct
import time
from typing import Callable

import numpy as np

from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.hover import HoverThrustEstimator, HoverThrustSeed
from ibvs_control.mavlink.link import MavAutopilot, MavlinkLink, MavMsgId
from ibvs_control.mavlink.params import AutopilotParams, Changed
from ibvs_control.mavlink.safety import SafetyMonitor
from ibvs_control.mavlink.sequencer import (
    Autopilot, engage_sequencer, EngageSequencer, EngageState, SequencerInputs)
from ibvs_control.mavlink.setpoints import (
    AttitudeTarget, HeadingPairing, RateMeter, SetpointShaper, SetpointSource, ShaperConfig,
    yaw_from_heading_quat)
from ibvs_control.mavlink.telemetry import (
    AccelSample, ImuSample, LandedState, QuietTelemetry, StreamRequests, streams_for,
    Telemetry)
from ibvs_common.core.modes import Mode
from ibvs_common.core.stamps import NS_PER_S
from ibvs_control.mavlink.time_sync import (
    TimeSync, TimesyncExchange, TimeSyncStatus)

__all__ = ['BridgeConfig', 'BridgeStatus', 'ImuSample', 'MavlinkBridge', 'SetpointSource']

NS_PER_MS = 1_000_000
MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 6, 9
STREAM_GAP_S = 0.5                      # a longer pause in sending restarts the stream count
STREAM_EPS_S = 1e-3                     # s, slack of the repeat period (timer jitter)
AUTOPILOT_OF_HEARTBEAT = {MavAutopilot.PX4: Autopilot.PX4,
                          MavAutopilot.ARDUPILOTMEGA: Autopilot.ARDUPILOT}
STATUS_MODES_KEPT = 32      # supervisor modes by stamp kept to pair with forces (0.64 s)
PENDING_ACCEL_KEPT = 500    # IMU samples kept until the hover-thrust seed is known
MAV_CMD_SET_MESSAGE_INTERVAL = 511
# the streams that arrive at 50-100 Hz and need no supervision step of their own (poll)
HIGH_RATE_TYPES = frozenset(('ATTITUDE_QUATERNION', 'HIGHRES_IMU', 'SCALED_IMU',
                             'ATTITUDE_TARGET'))


@dataclass(frozen=True)
class BridgeStatus:
    """Snapshot for /diagnostics."""

    link_up: bool
    heartbeat_age_s: float
    autopilot: str
    armed: bool
    custom_mode: int
    engage_state: str
    engage_reason: str
    supervisor_mode: str
    streaming: bool
    arm_requested: bool
    hover_thrust: float | None           # what the setpoints use now
    hover_thrust_seed: float | None
    hover_thrust_source: str
    hover_estimate_std: float | None
    setpoint_source: str
    setpoint_rate_hz: float
    rejected_setpoints: int
    landed_state: int | None
    armable: bool | None
    autopilot_internal_errors: int
    last_autopilot_reason: str
    dead_bridge_failsafe: bool | None       # the autopilot lands if we stop; None: unknown
    counters: dict
    time_sync: TimeSyncStatus
    imu_dropped_unsynced: int
    link_error: str = ''                    # the connection's last error ('' if none)
    stale_setpoints: int = 0                # of rejected_setpoints: images too old
    telemetry_slowed: bool = False          # the high-rate streams at their rate at rest


def param_value(value: float, param_type: int, bytewise: bool) -> float:
    """Return the value of a PARAM_VALUE's ``param_value`` field of type ``param_type``.

    PX4 copies an integer parameter's bytes into the float field (MAVLink's bytewise parameter
    encoding, its MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); ArduPilot casts the integer
    to a float (C-cast encoding). ``bytewise``: the autopilot's encoding is bytewise.
    """
    if not bytewise or param_type == MAV_PARAM_TYPE_REAL32:
        return value
    fmt = '<i' if param_type == MAV_PARAM_TYPE_INT32 else '<I'    # PX4: INT32 only
    return float(struct.unpack(fmt, struct.pack('<f', value))[0])


class MavlinkBridge:
    """ROS-free bridge: call on_* for inputs, poll/stream/heartbeat from timers."""

    def __init__(self, config: BridgeConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self.link = MavlinkLink(config.link, clock)
        self.time_sync = TimeSync(config.time_sync)
        self.timesync = TimesyncExchange(self.time_sync, self.link.send_timesync)
        self.telemetry = Telemetry(self.time_sync, clock, config.px4_events)
        self.streams: StreamRequests | None = None
        self.quiet_telemetry: QuietTelemetry | None = None      # with the streams
        self.shaper = SetpointShaper(ShaperConfig(
            config.mass, config.max_thrust_factor, config.max_force_factor,
            config.max_tilt_rad, config.hold_last_s, config.shutdown_ramp_s,
            config.max_force_age_s))
        self.pairing = HeadingPairing()
        self.seed = HoverThrustSeed(config.configured_hover_thrust,
                                    config.hover_thrust_source == 'autopilot')
        self.estimator = HoverThrustEstimator(config.estimator)
        self._pending_accel: deque = deque(maxlen=PENDING_ACCEL_KEPT)
        self._start_estimator()                  # the configured seed is known at once
        self.safety = SafetyMonitor(replace(
            config.safety, hold_last_s=config.hold_last_s,
            disarm_force_after_s=config.sequencer.disarm_force_after_s))
        self.autopilot: Autopilot | None = (None if config.autopilot == 'auto'
                                            else Autopilot(config.autopilot))
        self.sequencer: EngageSequencer | None = None
        self.supervisor_mode = Mode.IDLE
        self.idle_reports = 0
        self.params = AutopilotParams(self.seed, config.link.source_system,
                                      config.param_retry_s, config.param_timeout_s)
        self.params.autopilot = self.autopilot
        self.rate = RateMeter()
        self.setpoint_source = SetpointSource.NONE
        # False: build the targets but send none (the node holds the stream until the IMU's
        # consumers are matched, so that a lockstep sim starts only when they hear every sample)
        self.stream_enabled = True
        self._arm_pending = bool(config.arm_on_start)
        self._current: AttitudeTarget | None = None
        self._ros_ns: int | None = None              # latest ROS time given (ns)
        self._setpoint_stamp_ns: int | None = None   # latest stamp of a force sent (ROS ns)
        self._status_modes: dict[int, Mode] = {}     # stamp ns -> supervisor mode of that frame
        self._stream_start: float | None = None
        self._last_status_t: float | None = None     # steady time of the last frame status
        self._last_send_t: float | None = None
        self._last_tick_t: float | None = None
        self._was_up = False
        self._sync_reboots = 0
        self._reported_missing = 0
        self._events: list[tuple[str, str]] = []
        self._maybe_build_sequencer()

    # --- inputs from ROS ---------------------------------------------------------------
    def on_supervisor_mode(self, mode: int) -> None:
        """ibvs/mode; unknown values are refused (logged) and the mode is kept."""
        try:
            new = Mode(int(mode))
        except ValueError:
            self._event('error', f'unknown supervisor mode {mode}: kept {self.supervisor_mode}')
            return
        if new == Mode.IDLE:
            self.idle_reports += 1
        if new == self.supervisor_mode:
            return
        self._event('info', f'supervisor mode {self.supervisor_mode.name} -> {new.name}')
        self.supervisor_mode = new
        # The full telemetry rates, then the engagement commands, leave now, not at the next
        # poll (before the next setpoint).
        now = self._clock()
        self._request_streams(now)
        self._run_sequencer(now)

    def on_supervisor_status(self, stamp_ns: int, mode: int | None) -> str:
        """Note the supervisor's mode for the frame of ``stamp_ns`` (ibvs/supervisor_status).

        The force of that stamp is then flown with the content of that mode (see
        :meth:`content_mode`). Returns '' or why the value is refused.
        """
        try:
            m = Mode(int(mode))
        except (TypeError, ValueError):
            return f'unknown supervisor mode {mode!r}'
        self._status_modes[int(stamp_ns)] = m
        while len(self._status_modes) > STATUS_MODES_KEPT:
            del self._status_modes[min(self._status_modes)]
        self._last_status_t = self._clock()
        if self.quiet_telemetry is not None and self.quiet_telemetry.active:
            self._request_streams(self._last_status_t)   # frames again: full rates now
        return ''

    def content_mode(self) -> Mode:
        """Return the mode whose content (F, shutdown ramp) the target carries.

        The supervisor's mode reported for the stamp of the latest force, so that e.g. the
        shutdown ramp starts on the SHUTDOWN frame itself, not on whichever setpoint follows the
        ``ibvs/mode`` message (lockstep runs then repeat to the end). Without that status, or
        once the forces stopped for ``hold_last_s`` (controller silent: the latest mode must
        still act), the latest ``ibvs/mode``.
        """
        if self._setpoint_stamp_ns is not None and not self.safety.inputs_lost(self._vehicle_s()):
            mode = self._status_modes.get(self._setpoint_stamp_ns)
            if mode is not None:
                return mode
        return self.supervisor_mode

    def on_heading(self, stamp_ns: int, q_wxyz_enu_flu: np.ndarray,
                   ros_ns: int | None = None) -> str:
        """ibvs/heading_setpoint of stamp_ns (base_link in map); '' or the refusal reason."""
        self._set_ros(ros_ns)
        try:
            yaw: float | None = yaw_from_heading_quat(q_wxyz_enu_flu)
            reason = ''
        except ValueError as exc:
            self.shaper.rejected += 1
            yaw, reason = None, str(exc)
        self.pairing.on_heading(stamp_ns, yaw)
        return reason

    def on_force(self, stamp_ns: int, F_I: np.ndarray, ros_ns: int | None = None) -> str:
        """ibvs/force_setpoint (already in {I}): sent at once with the heading of its stamp.

        Returns '' or why the force was refused (then the held/fallback setpoint is sent at
        once, with the new stamp, so that a lockstep sim keeps advancing).
        """
        self._set_ros(ros_ns)
        p = self.pairing.on_force(stamp_ns, F_I)
        yaw = self.telemetry.yaw_now if p.yaw is None else p.yaw
        reason = self.shaper.on_force(self._vehicle_s() or 0.0, p.F_I, yaw,
                                      self.hover_for_stamp(p.stamp_ns), p.stamp_ns / NS_PER_S)
        if not reason:
            self.safety.on_force(self._vehicle_s())
        if self._setpoint_stamp_ns is None or p.stamp_ns > self._setpoint_stamp_ns:
            self._setpoint_stamp_ns = p.stamp_ns
        self._send_current(new=True)
        return reason

    def request_arm(self) -> tuple[bool, str]:
        """ibvs/arm: allow the bridge to arm the vehicle when it engages."""
        hb = self.link.heartbeat
        if hb is not None and hb.armed:
            return True, 'the vehicle is already armed'
        if self.sequencer is None:
            self._arm_pending = True
            return True, ('arm request noted: no autopilot yet; the bridge arms the vehicle once '
                          'it is in the offboard mode and armable')
        answer = self.sequencer.request_arm()
        self._request_streams(self._clock())       # full telemetry rates before arming
        return answer

    def pop_heading_warning(self) -> str:
        """Text about forces flown without their heading since the last call, or ''."""
        n = self.pairing.missing - self._reported_missing
        if n <= 0:
            return ''
        self._reported_missing = self.pairing.missing
        return (f'{n} force setpoint(s) without the heading of their stamp: flown at once with '
                f'the latest heading ({self.pairing.missing} in all, {self.pairing.late} late '
                'headings)')

    # --- timers ------------------------------------------------------------------------
    def heartbeat(self) -> None:
        """1 Hz: our HEARTBEAT."""
        self.link.send_heartbeat()

    @property
    def quiet(self) -> bool:
        """Whether nothing is to be engaged or flown: the periodic step may slow down.

        Standby (PX4: the keepalive stream of the level hover), the supervisor IDLE, the
        clocks synced and the stream released. Anything that engages (a supervisor mode, an
        arm request) acts at once, not at the next step.
        """
        seq = self.sequencer
        return (seq is not None and seq.state == EngageState.STANDBY
                and self.supervisor_mode == Mode.IDLE and self.stream_enabled
                and self.time_sync.synced)

    def tick_due(self) -> bool:
        """Whether the node's periodic step (poll, supervision, repeat) runs now.

        Always, except while :attr:`quiet`: then at most at ``idle_tick_rate_hz`` (steady
        clock), which is also the keepalive stream's rate then (PX4 wants > 2 Hz before
        OFFBOARD). At ``stream_rate_hz`` (30 Hz) this step took ~1 % of a core in an idle
        graph (docs/performance.md, "Idle CPU").
        """
        now = self._clock()
        c = self.config
        # half a timer period of slack: the step is called at stream_rate_hz, with jitter
        if self.quiet and self._last_tick_t is not None \
                and now - self._last_tick_t < 1.0 / c.idle_tick_rate_hz - 0.5 / c.stream_rate_hz:
            return False
        self._last_tick_t = now
        return True

    def stream(self, ros_ns: int | None = None) -> None:
        """Repeat the latest setpoint if none left for 1 / stream_rate_hz (call it often)."""
        self._set_ros(ros_ns)
        period = 1.0 / self.config.stream_rate_hz
        if self._last_send_t is not None \
                and self._clock() - self._last_send_t < period - STREAM_EPS_S:
            return
        self._send_current(new=False)

    def poll(self, ros_ns: int | None = None, supervise: bool = True,
             ros_clock: Callable[[], int | None] | None = None) -> list[ImuSample]:
        """Receive everything pending, run the sequencer, return new IMU samples.

        ``ros_ns``: ROS time now (ns; the node's clock). It is the receipt time of the TIMESYNC
        answers read here, the tc1 of our answers to the autopilot's requests and the ts1 of
        our requests; None or 0 (no ``/clock`` yet): no clock sync. ``ros_clock`` (instead of
        ``ros_ns``): the node's clock, read only once a message or the supervision needs the
        time, just before it; the high-rate telemetry alone needs none (its stamps are mapped
        from the autopilot's boot time), so a reader-thread wake-up that brings only that
        (most of ~150 a second) skips the ROS clock read, ~30 us of a cold wake-up
        (docs/performance.md "Idle CPU"). ``supervise=False`` (the reader thread, at every
        datagram): the supervision after the messages (link state, sequencer, clock-sync,
        parameter and stream requests) runs only if a message other than the high-rate
        telemetry (``HIGH_RATE_TYPES``: ~270 a second) came in; the caller's periodic poll
        (the node's stream tick) supervises in any case.
        """
        now = self._clock()
        clock_read = ros_clock is None
        if clock_read:
            self._set_ros(ros_ns, force=True)
        samples = []
        messages = self.link.poll()
        for msg in messages:
            if not clock_read and msg.get_type() not in HIGH_RATE_TYPES:
                self._set_ros(ros_clock(), force=True)
                clock_read = True
            sample = self._handle(msg)
            if sample is not None:
                samples.append(sample)
        if not supervise and all(m.get_type() in HIGH_RATE_TYPES for m in messages):
            return samples
        if not clock_read:
            self._set_ros(ros_clock(), force=True)
        self._maybe_build_sequencer()
        self._on_link_state()
        if self.link.link_up:
            self.timesync.request(self._ros_ns, now)
            self._service_requests(now)
        self._run_sequencer(now)
        return samples

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) log events since the last call.

        Levels: 'info', 'warn', 'error'; 'reason-info' / 'reason-warn' / 'reason-error' are the
        autopilot's own words (STATUSTEXT, EVENT), each text once per 5 s.
        """
        events, self._events = self._events, []
        events += self.link.pop_events()
        events += self.telemetry.pop_events()
        if self.sequencer is not None:
            events += [('info', f'engage: {e}') for e in self.sequencer.pop_events()]
        return events

    def status(self) -> BridgeStatus:
        """Diagnostics snapshot."""
        now = self._clock()
        hb = self.link.heartbeat
        seq = self.sequencer
        c = self.link.counters
        tel = self.telemetry
        return BridgeStatus(
            link_up=self.link.link_up, heartbeat_age_s=self.link.heartbeat_age(),
            autopilot=self.autopilot.value if self.autopilot else 'unknown',
            armed=bool(hb and hb.armed), custom_mode=hb.custom_mode if hb else 0,
            engage_state=seq.state.value if seq else 'no_link',
            engage_reason=seq.last_reason if seq else '',
            supervisor_mode=self.supervisor_mode.name, streaming=self._may_stream(),
            arm_requested=bool(seq.arm_requested if seq else self._arm_pending),
            hover_thrust=self.hover_now(), hover_thrust_seed=self.seed.value,
            hover_thrust_source=self.seed.source + (
                ' + online estimate' if self.config.estimator.enabled else ''),
            hover_estimate_std=self.estimator.std,
            setpoint_source=self.setpoint_source.value, setpoint_rate_hz=self.rate.rate(now),
            rejected_setpoints=self.shaper.rejected, landed_state=tel.landed_state,
            armable=tel.armable, autopilot_internal_errors=tel.internal_errors,
            last_autopilot_reason=tel.last_reason,
            dead_bridge_failsafe=self.params.dead_bridge_failsafe,
            counters={'received': c.received, 'sent': c.sent, 'bad_data': c.bad_data,
                      'foreign': c.foreign, 'reconnects': c.reconnects, 'reopens': c.reopens,
                      'link_losses': c.link_losses, 'send_errors': c.send_errors,
                      'peers': c.peers, 'headings_missing': self.pairing.missing,
                      'late_headings': self.pairing.late,
                      'timesync_answered': self.timesync.answered,
                      'hover_estimate_samples': self.estimator.accepted,
                      'hover_estimate_rejected': self.estimator.rejected,
                      'autopilot_reasons': tel.reasons,
                      'streams_refused': len(self.streams.refused) if self.streams else 0},
            time_sync=self.time_sync.status(), imu_dropped_unsynced=tel.imu_dropped_unsynced,
            link_error=self.link.last_error, stale_setpoints=self.shaper.stale,
            telemetry_slowed=bool(self.quiet_telemetry and self.quiet_telemetry.active))

    def close(self) -> None:
        """Close the link."""
        self.link.close()

    @property
    def imu_dropped_unsynced(self) -> int:
        """ATTITUDE_QUATERNION dropped while the clock was unsynced."""
        return self.telemetry.imu_dropped_unsynced

    # --- hover thrust ------------------------------------------------------------------
    def hover_now(self) -> float | None:
        """Hover thrust the setpoints use now (estimate, else seed)."""
        v = self.estimator.value_at(None)
        return self.seed.value if v is None else v

    def hover_for_stamp(self, stamp_ns: int | None) -> float:
        """Hover thrust for the setpoint of ``stamp_ns``: the estimate as of its samples.

        In boot time, the samples at least ``margin_s`` older than the stamp (deterministic in
        a lockstep sim); unsynced or unknown: the latest; no seed yet: the configured value.
        """
        boot = None if stamp_ns is None else self.time_sync.ros_ns_to_boot_ms(stamp_ns)
        v = self.estimator.value_at(None if boot is None else boot * NS_PER_MS)
        if v is None:
            v = self.seed.value
        return self.config.configured_hover_thrust if v is None else v

    # --- time --------------------------------------------------------------------------
    def stamp_to_boot_ms(self, stamp_ns: int) -> int | None:
        """ROS stamp -> autopilot time_boot_ms (>= 0; None while the clocks are not synced)."""
        ms = self.time_sync.ros_ns_to_boot_ms(stamp_ns)
        return None if ms is None else max(0, ms)

    def _set_ros(self, ros_ns: int | None, force: bool = False) -> None:
        if ros_ns is not None or force:
            self._ros_ns = None if ros_ns is None else int(ros_ns)

    def _vehicle_s(self) -> float | None:
        """Vehicle time: the ROS clock (s), None while unknown (no /clock yet)."""
        if self._ros_ns is None or self._ros_ns <= 0:
            return None
        return self._ros_ns / NS_PER_S

    # --- internals ---------------------------------------------------------------------
    def _event(self, level: str, text: str) -> None:
        self._events.append((level, text))

    def _maybe_build_sequencer(self) -> None:
        if self.sequencer is not None:
            return
        hb = self.link.heartbeat
        if self.autopilot is None and hb is not None:
            self.autopilot = AUTOPILOT_OF_HEARTBEAT.get(hb.autopilot)
            if self.autopilot is None:
                self._event('error', f'autopilot type {hb.autopilot} unsupported: set the '
                                     "'autopilot' parameter to px4 or ardupilot")
                return
        if self.autopilot is None:
            return
        self.params.autopilot = self.autopilot
        self.sequencer = engage_sequencer(self.autopilot, self.config.sequencer)
        self.sequencer.arm_requested = self._arm_pending
        c = self.config
        self.streams = StreamRequests(streams_for(
            self.autopilot.value, c.attitude_rate_hz, c.imu_rate_hz, c.thrust_rate_hz,
            c.status_rate_hz, c.heartbeat_request_hz, c.streams_off))
        imu = MavMsgId.SCALED_IMU if self.autopilot == Autopilot.ARDUPILOT \
            else MavMsgId.HIGHRES_IMU
        self.quiet_telemetry = QuietTelemetry(
            {MavMsgId.ATTITUDE_QUATERNION: c.attitude_rate_hz, imu: c.imu_rate_hz,
             MavMsgId.ATTITUDE_TARGET: c.thrust_rate_hz},
            c.quiet_telemetry_rate_hz, c.quiet_telemetry_delay_s)

    def _on_link_state(self) -> None:
        """Link back / autopilot reboot: ask for the streams again, forget per-boot state."""
        up = self.link.link_up
        rebooted = self.time_sync.reboots != self._sync_reboots
        self._sync_reboots = self.time_sync.reboots
        if (up and not self._was_up) or rebooted:
            if self.streams is not None:
                for msg_id, rate in self.quiet_telemetry.reset().items():
                    self.streams.set_rate(msg_id, rate)
                self.streams.reset()
            if self._was_up or rebooted:
                self.telemetry.reset()
                self.safety.reset_contact()
        if not up and self._was_up:
            self.safety.reset_contact()
        self._was_up = up

    def _handle(self, msg) -> ImuSample | None:
        kind = msg.get_type()
        if kind == 'TIMESYNC':
            for level, text in self.timesync.on_message(msg.tc1, msg.ts1, self._ros_ns):
                self._event(level, text)
        elif kind == 'PARAM_VALUE':
            self._param(msg.param_id, param_value(float(msg.param_value), int(msg.param_type),
                                                  self.autopilot == Autopilot.PX4))
        elif kind == 'COMMAND_ACK':
            if int(msg.command) == MAV_CMD_SET_MESSAGE_INTERVAL:
                warning = self.streams.on_ack(msg.result) if self.streams else ''
                if warning:
                    self._event('warn', warning)
                return None
            if self.sequencer is not None:
                self.sequencer.on_command_ack(msg.command, msg.result)
            if msg.result != 0:
                self._event('warn', f'command {msg.command} answered with result {msg.result}')
        else:
            imu, accel, _ = self.telemetry.on_message(msg, self._ros_ns)
            if accel is not None:
                self._on_accel(accel)
            return imu
        return None

    def _on_accel(self, a: AccelSample) -> None:
        """Take an IMU specific-force sample: touchdown rule, hover-thrust estimator."""
        hover = self.hover_now() or self.config.configured_hover_thrust
        thr = self.telemetry.thrust
        commanded = self._current.thrust if self._current is not None and self._may_stream() \
            else (thr.thrust if thr is not None else hover)
        f_norm = float(np.linalg.norm(a.f_frd))
        self.safety.on_accel(a.boot_ns, f_norm, commanded, hover)
        if self.estimator.theta is None:
            self._pending_accel.append((a, thr))     # replayed once the seed is known
            return
        self._estimate(a, thr)

    def _estimate(self, a: AccelSample, thr) -> None:
        if thr is None or abs(a.boot_ns - thr.boot_ns) > \
                self.config.estimator.max_pairing_s * NS_PER_S:
            return
        hb = self.link.heartbeat
        airborne = bool(hb and hb.armed) and self.telemetry.landed_state in (
            None, LandedState.UNDEFINED, LandedState.IN_AIR, LandedState.TAKEOFF)
        boost = 1.0
        if self.shaper.tilt_boost_by_autopilot and a.cos_tilt > 0.5:
            boost = 1.0 / a.cos_tilt
        self.estimator.update(a.boot_ns, float(a.f_frd[2]), float(np.linalg.norm(a.f_frd)),
                              thr.thrust, boost, airborne)

    def _param(self, raw_name, value: float) -> None:
        self._apply(self.params.on_param(raw_name, value))

    def _apply(self, changed: Changed) -> None:
        """Apply what the autopilot's parameters changed; pass their events on."""
        for level, text in self.params.pop_events():
            self._event(level, text)
        if Changed.SEED in changed:
            self._start_estimator()
        if Changed.TILT_BOOST in changed:
            self.shaper.tilt_boost_by_autopilot = self.params.tilt_boosted_by_autopilot

    def _start_estimator(self) -> None:
        if self.estimator.theta is not None or self.seed.value is None:
            return
        self.estimator.start(self.seed.value)
        pending, self._pending_accel = list(self._pending_accel), deque(
            maxlen=PENDING_ACCEL_KEPT)
        for a, thr in pending:
            self._estimate(a, thr)

    def _service_requests(self, now: float) -> None:
        """Parameter reads (retried while unanswered) and stream requests (one at a time)."""
        reads, changed = self.params.due(now)
        for name in reads:
            self.link.request_param(name)
        self._apply(changed)
        self._request_streams(now)

    @property
    def at_rest(self) -> bool:
        """Whether the telemetry may slow down: standby, supervisor IDLE, disarmed, no frames.

        No arm request either, and no frame evaluated (``ibvs/supervisor_status``) for
        ``quiet_telemetry_delay_s``: with the cameras on, the window detection of IDLE (the
        start's check, the preflight's) derotates with the attitude at each image stamp, which
        a 10 Hz stream cannot give within the nodes' extrapolation bound. Whether our setpoint
        stream is held or the clocks are synced does not matter.
        """
        hb = self.link.heartbeat
        seq = self.sequencer
        frames = self._last_status_t is not None and \
            self._clock() - self._last_status_t < self.config.quiet_telemetry_delay_s
        return (seq is not None and seq.state == EngageState.STANDBY
                and self.supervisor_mode == Mode.IDLE and hb is not None and not hb.armed
                and not seq.arm_requested and not frames)

    def _request_streams(self, now: float) -> None:
        """Send the next stream request (one at a time), at the rates :attr:`at_rest` asks."""
        if self.streams is None or not self.link.link_up:
            return
        rates = self.quiet_telemetry.update(self.at_rest, now)
        if rates is not None:
            changed = [i for i, r in rates.items() if self.streams.set_rate(i, r)]
            if changed:
                self._event('info', 'telemetry streams ' + (
                    f'slowed to {self.config.quiet_telemetry_rate_hz:g} Hz at rest (disarmed, '
                    'nothing engaging)' if self.quiet_telemetry.active
                    else 'back to their full rates') + f': messages {changed}')
        req = self.streams.step(now)
        if req is not None:
            self.link.set_message_interval(*req)

    def _may_stream(self) -> bool:
        return (self.link.link_up and self.stream_enabled and self.sequencer is not None
                and self.sequencer.streaming)

    def _run_sequencer(self, now: float) -> None:
        if self.sequencer is None:
            return
        hb = self.link.heartbeat
        vehicle = self._vehicle_s()
        timed_out = self.params.timed_out(now)
        was = self.sequencer.state
        inp = SequencerInputs(
            t=now, link_up=self.link.link_up, supervisor_mode=self.supervisor_mode,
            idle_reports=self.idle_reports, armed=bool(hb and hb.armed),
            custom_mode=hb.custom_mode if hb else 0, streaming_s=self._streaming_s(now),
            hover_thrust_ready=self.seed.value is not None,
            guid_options=self.params.guid_options,
            params_timed_out=timed_out, ramp_done=self.shaper.ramp_done(now),
            armable=self.telemetry.armable, landed=self.telemetry.landed,
            inputs_lost=self.safety.inputs_lost(vehicle), touchdown=self.safety.touchdown,
            airborne_at_low_thrust=self.safety.airborne_at_low_thrust)
        for req in self.sequencer.step(inp):
            self._event('info', f'command {req.command.name} {req.params}: {req.reason}')
            self.link.send_command_long(req.command, req.params)
        if self.sequencer.state != was:
            if self.sequencer.state == EngageState.SET_MODE:
                self.safety.start_count(vehicle)     # engaging without any force: counts
            if not self.sequencer.streaming:
                self._stream_start = None

    def _streaming_s(self, now: float) -> float:
        if self._stream_start is None:
            return 0.0
        return now - self._stream_start

    def _send_current(self, new: bool) -> None:
        """Build the target for the current state and mode; send it if the policy streams."""
        now = self._clock()
        seq = self.sequencer
        # Every target carries the stamp of the latest controller output (0 before any), never
        # the autopilot's current time: a fallback (level hover before the first force, hold,
        # shutdown ramp) is not an answer to a newer camera frame, so the sim's lockstep keeps
        # waiting for the controller instead of running ahead of the graph. Mapped at each
        # send: a repeat sent once the clocks are synced carries the mapped value (0 before).
        stamp = self._setpoint_stamp_ns
        ms = (self.stamp_to_boot_ms(stamp) if stamp is not None else None) or 0
        t_stamp = 0.0 if stamp is None else stamp / NS_PER_S
        hover = self.hover_now() or self.config.configured_hover_thrust
        target = self.shaper.target(
            self._vehicle_s(), self.content_mode(), self.telemetry.yaw_now, hover, ms, t_stamp,
            now, engaged=bool(seq and seq.state == EngageState.ENGAGED),
            level_hold=bool(seq and seq.level_hold))
        if target.source == SetpointSource.HOLD_LAST and new:
            self._event('error', f'force setpoint refused ({self.shaper.last_error}): '
                                 'holding the last valid one')
        if target.source != self.setpoint_source:
            self._event('info' if target.source == SetpointSource.IBVS else 'warn',
                        f'setpoint source {self.setpoint_source.value} -> '
                        f'{target.source.value}')
            self.setpoint_source = target.source
        self._current = target
        if not self._may_stream():
            self._stream_start = None
            return
        if self.link.send_attitude_target(target.time_boot_ms, target.q_wxyz, target.thrust,
                                          target.type_mask):
            self.rate.tick(now)
            if self._stream_start is None or (self._last_send_t is not None
                                              and now - self._last_send_t > STREAM_GAP_S):
                self._stream_start = now
            self._last_send_t = now
