"""The sim autopilot's output: HEARTBEAT on the wall clock, telemetry streams paced in sim time.

Streams (message id -> default rate): ATTITUDE_QUATERNION and HIGHRES_IMU at
``telemetry_default_hz`` (noisy, see :mod:`~ibvs_sim.core.autopilot.noise`), ATTITUDE_TARGET at
``thrust_telemetry_hz`` (the inner-loop reference now), EXTENDED_SYS_STATE (landed state) and
SYS_STATUS (pre-arm health bit) at ``status_telemetry_hz``; RC_CHANNELS (the pilot's radio,
``config.radio``: none without one, as PX4 without RC) only once asked. A stream falls due
every interval of sim time; when polled slower than that it re-phases instead of bursting.
SET_MESSAGE_INTERVAL changes a stream's interval (the same interval again keeps its phase);
REQUEST_MESSAGE sends one at once. HEARTBEAT every ``heartbeat_period_wall_s`` of wall clock,
at once to a new peer. Messages are stamped with sim time (``time_boot_ms = round(1000 t)``,
``time_usec``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ibvs_sim.core.autopilot.config import (AttitudeReference, AutopilotConfig,
                                            AutopilotCounters, finite, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_sim.core.autopilot.modes import FlightModeMachine
from ibvs_sim.core.autopilot.noise import SensorNoise
from ibvs_sim.core.autopilot.protocol import (
    HIGHRES_IMU_FIELDS_ACC_GYRO, MAV_AUTOPILOT_PX4, MAV_LANDED_STATE_IN_AIR,
    MAV_LANDED_STATE_ON_GROUND, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_RESULT_ACCEPTED, MAV_RESULT_DENIED, MAV_RESULT_FAILED, MAV_STATE_ACTIVE,
    MAV_STATE_CRITICAL, MAV_STATE_STANDBY, MAV_SYS_STATUS_PREARM_CHECK, MAV_TYPE_QUADROTOR,
    MAV_VTOL_STATE_UNDEFINED, MS_PER_S, MSG_ID_ATTITUDE_QUATERNION, MSG_ID_ATTITUDE_TARGET,
    MSG_ID_EXTENDED_SYS_STATE, MSG_ID_HEARTBEAT, MSG_ID_HIGHRES_IMU, MSG_ID_RC_CHANNELS,
    MSG_ID_SYS_STATUS,
    SET_INTERVAL_DEFAULT, SET_INTERVAL_DISABLE, TYPEMASK_BODY_RATES_IGNORE, US_PER_S)

RC_CHANNELS_DEFAULT_HZ = 5.0     # RC_CHANNELS at SET_MESSAGE_INTERVAL 0 (the default rate)


@dataclass
class TelemetryStream:
    """A telemetry stream paced in sim time (intervals and times in s)."""

    default_interval_s: float
    interval_s: float | None        # None = disabled
    next_due_t: float | None = None


class Telemetry:
    """HEARTBEAT and the telemetry streams of the autopilot, sent on ``link``."""

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 warn: RateLimitedLog, link: AutopilotLink, noise: SensorNoise,
                 modes: FlightModeMachine,
                 reference: Callable[[VehicleStateView], AttitudeReference],
                 wall_clock: Callable[[], float]) -> None:
        """Set every stream to its default rate.

        ``modes`` is read for the heartbeat and the landed state, ``reference`` gives the
        inner-loop reference ATTITUDE_TARGET reports, ``wall_clock`` (monotonic s) paces the
        heartbeat.
        """
        self.config = config
        self.counters = counters
        self._warn = warn
        self._link = link
        self._noise = noise
        self._modes = modes
        self._reference = reference
        self._wall = wall_clock
        intervals = {MSG_ID_ATTITUDE_QUATERNION: 1.0 / config.telemetry_default_hz,
                     MSG_ID_HIGHRES_IMU: 1.0 / config.telemetry_default_hz,
                     MSG_ID_ATTITUDE_TARGET: 1.0 / config.thrust_telemetry_hz,
                     MSG_ID_EXTENDED_SYS_STATE: 1.0 / config.status_telemetry_hz,
                     MSG_ID_SYS_STATUS: 1.0 / config.status_telemetry_hz}
        self.streams = {i: TelemetryStream(v, v) for i, v in intervals.items()}
        # RC_CHANNELS: off until asked (PX4's onboard link), then at the asked rate
        self.streams[MSG_ID_RC_CHANNELS] = TelemetryStream(1.0 / RC_CHANNELS_DEFAULT_HZ, None)
        self._last_heartbeat_wall: float | None = None
        # time_boot_ms of the newest valid ATTITUDE_QUATERNION sent: the bridge's newest
        # imu/data stamp (lockstep: the sim holds images until the graph has it)
        self.last_attitude_ms: int | None = None

    # --- requests -------------------------------------------------------------------------------

    def set_interval(self, msg_id: int, interval_us: int) -> int:
        """Apply SET_MESSAGE_INTERVAL: -1 off, 0 default, > 0 interval (µs); return a MAV_RESULT.

        FAILED for a message that is not a stream (as PX4), DENIED for another negative value;
        faster than telemetry_max_hz is clamped (and counted).
        """
        stream = self.streams.get(msg_id)
        if stream is None:
            return MAV_RESULT_FAILED  # as PX4 does for a stream it does not have
        if interval_us == SET_INTERVAL_DISABLE:
            interval = None
        elif interval_us == SET_INTERVAL_DEFAULT:
            interval = stream.default_interval_s
        elif interval_us > 0:
            min_interval = 1.0 / self.config.telemetry_max_hz
            interval = interval_us / US_PER_S
            if interval < min_interval:
                self.counters.interval_clamped += 1
                interval = min_interval
        else:
            return MAV_RESULT_DENIED
        # The same interval again (the bridge asks after every link-up) keeps the stream's
        # phase: in lockstep the request lands at a load-dependent frame, which must not matter.
        if stream.interval_s is None or interval is None \
                or abs(interval - stream.interval_s) > 1e-9:
            stream.interval_s = interval
            stream.next_due_t = None
        return MAV_RESULT_ACCEPTED

    def send_once(self, msg_id: int, state: VehicleStateView) -> bool:
        """Send HEARTBEAT or a stream's message now (REQUEST_MESSAGE); False for other ids."""
        if msg_id == MSG_ID_HEARTBEAT:
            self.send_heartbeat()
        elif msg_id == MSG_ID_ATTITUDE_QUATERNION:
            self._send_attitude_quaternion(state)
        elif msg_id in self._senders():
            self._senders()[msg_id](state)
        else:
            return False
        return True

    # --- pacing ---------------------------------------------------------------------------------

    def greet_new_peer(self) -> None:
        """Send the next heartbeat at the next :meth:`send_heartbeat_if_due`."""
        self._last_heartbeat_wall = None

    def send_heartbeat_if_due(self) -> None:
        """Send HEARTBEAT once per heartbeat_period_wall_s of wall clock (once a peer is known)."""
        now = self._wall()
        if (self._last_heartbeat_wall is None
                or now - self._last_heartbeat_wall >= self.config.heartbeat_period_wall_s):
            self._last_heartbeat_wall = now
            if self._link.peer_known():
                self.send_heartbeat()

    def next_due_t(self) -> float | None:
        """Sim time at which the next stream is due (None: none has been sent yet or on)."""
        due = [s.next_due_t for s in self.streams.values()
               if s.interval_s is not None and s.next_due_t is not None]
        return min(due) if due else None

    def send_due(self, state: VehicleStateView) -> None:
        """Send the streams due at sim time ``state.t`` (once a peer is known)."""
        t = float(state.t)
        eps = 1e-9  # s, float slack so a 1 ms physics step hits a 20 ms period exactly
        senders = self._senders()
        for msg_id, stream in self.streams.items():
            if stream.interval_s is None:
                continue
            if stream.next_due_t is None:
                stream.next_due_t = t
            if t + eps < stream.next_due_t:
                continue
            stream.next_due_t += stream.interval_s
            if stream.next_due_t <= t:                   # fell behind: no burst, re-phase
                stream.next_due_t = t + stream.interval_s
            if self._link.peer_known():
                senders[msg_id](state)

    # --- messages -------------------------------------------------------------------------------

    def send_heartbeat(self) -> None:
        """Send HEARTBEAT: PX4 quadrotor, armed flag, custom_mode, status (failsafe: CRITICAL)."""
        modes = self._modes
        base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if modes.armed:
            base_mode |= MAV_MODE_FLAG_SAFETY_ARMED
        if modes.failsafe_active:
            status = MAV_STATE_CRITICAL
        else:
            status = MAV_STATE_ACTIVE if modes.armed else MAV_STATE_STANDBY
        self._link.mav.heartbeat_send(MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode,
                                      modes.mode.custom_mode, status)
        self.counters.heartbeats_sent += 1

    def _senders(self) -> dict:
        return {MSG_ID_ATTITUDE_QUATERNION: self._send_attitude_quaternion,
                MSG_ID_HIGHRES_IMU: self._send_highres_imu,
                MSG_ID_ATTITUDE_TARGET: self._send_attitude_target,
                MSG_ID_EXTENDED_SYS_STATE: self._send_extended_sys_state,
                MSG_ID_SYS_STATUS: self._send_sys_status,
                MSG_ID_RC_CHANNELS: self._send_rc_channels}

    def _send_rc_channels(self, state: VehicleStateView) -> None:
        """RC_CHANNELS: the pilot's radio at sim time (nothing without one: no RC)."""
        radio = self.config.radio
        if radio is None:
            return
        mav = self._link.mav
        mav.send(radio.message(mav, int(round(state.t * US_PER_S)), state.t))
        self.counters.rc_channels_sent += 1

    def _send_attitude_target(self, state: VehicleStateView) -> None:
        """ATTITUDE_TARGET: the inner-loop reference (attitude, thrust) now, as PX4 reports it.

        PX4 reports |thrust_body| of its attitude setpoint in any mode: the thrust applied.
        """
        ref = self._reference(state)
        q = [float(x) for x in ref.q_IB_wxyz]
        self._link.mav.attitude_target_send(int(round(state.t * MS_PER_S)),
                                            TYPEMASK_BODY_RATES_IGNORE, q, 0.0, 0.0, 0.0,
                                            float(ref.thrust_norm))
        self.counters.attitude_target_sent += 1

    def _send_extended_sys_state(self, state: VehicleStateView) -> None:
        """EXTENDED_SYS_STATE: landed state from the (ground-truth) land detector."""
        landed = finite(state.xi_I, state.v_I) and self._modes.landed(state)
        self._link.mav.extended_sys_state_send(
            MAV_VTOL_STATE_UNDEFINED,
            MAV_LANDED_STATE_ON_GROUND if landed else MAV_LANDED_STATE_IN_AIR)
        self.counters.extended_sys_state_sent += 1

    def _send_sys_status(self, state: VehicleStateView) -> None:
        """SYS_STATUS: only the pre-arm health bit (set: the sim has no pre-arm checks)."""
        zero = 0
        self._link.mav.sys_status_send(zero, zero, MAV_SYS_STATUS_PREARM_CHECK, zero, zero,
                                       -1, -1, zero, zero, zero, zero, zero, zero)
        self.counters.sys_status_sent += 1

    def _imu_fault(self, t: float) -> str:
        """Return the IMU fault injected at ``t`` ('off', 'nan', ''), counted."""
        fault = self.config.imu_fault_at(t)
        self.counters.imu_faulted += bool(fault)
        return fault

    def _send_attitude_quaternion(self, state: VehicleStateView) -> None:
        fault = self._imu_fault(state.t)
        if fault == 'off':
            return
        if fault == 'nan':
            nan = float('nan')
            self._link.mav.attitude_quaternion_send(int(round(state.t * MS_PER_S)),
                                                    *([nan] * 7))
            return
        if not finite(state.R_IB, state.Omega_B):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite attitude at t=%.3f: not sent', state.t)
            return
        q = self._noise.noisy_attitude(state.R_IB, state.t)
        w = self._noise.noisy_rates(state.Omega_B, state.t)
        time_boot_ms = int(round(state.t * MS_PER_S))
        self._link.mav.attitude_quaternion_send(time_boot_ms, *map(float, q), *map(float, w))
        self.counters.attitude_quaternion_sent += 1
        self.last_attitude_ms = time_boot_ms

    def _send_highres_imu(self, state: VehicleStateView) -> None:
        fault = self._imu_fault(state.t)
        if fault == 'off':
            return
        if fault == 'nan':
            nan, zero = float('nan'), 0.0
            self._link.mav.highres_imu_send(int(round(state.t * US_PER_S)), *([nan] * 6),
                                            zero, zero, zero, zero, zero, zero, zero,
                                            HIGHRES_IMU_FIELDS_ACC_GYRO)
            return
        if not finite(state.accel_B_specific, state.Omega_B):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite IMU at t=%.3f: not sent', state.t)
            return
        acc, gyro = self._noise.noisy_imu(state.accel_B_specific, state.Omega_B, state.t)
        zero = 0.0
        self._link.mav.highres_imu_send(int(round(state.t * US_PER_S)), *map(float, acc),
                                        *map(float, gyro), zero, zero, zero, zero, zero, zero,
                                        zero, HIGHRES_IMU_FIELDS_ACC_GYRO)
        self.counters.highres_imu_sent += 1
