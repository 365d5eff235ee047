"""The simulated autopilot: PX4 in offboard mode as a companion computer sees it over MAVLink.

ROS-free core. The sim node composes :class:`Autopilot` with its plant: at every physics step it
calls :meth:`Autopilot.poll` with the ground-truth state (answers commands, sends telemetry) and
:meth:`Autopilot.attitude_reference` to get the inner-loop reference (attitude + normalised
collective thrust) that its attitude controller tracks.

Frames and units (SPEC.md section 1): {I} is the autopilot's local NED frame (z down, gravity
``+g e3``), the body frame is FRD, quaternions are Hamilton ``(w, x, y, z)`` of ``R_IB`` (FRD in
NED) as MAVLink sends them. SI units; MAVLink time stamps are *sim* time since boot (the sim
clock starts at 0). Normalised thrust is ``T / T_max`` with ``T_max = m g / hover_thrust``.

Behaviour (details, and how it differs from real PX4, in docs/sim_autopilot.md):

- modes (PX4 custom_mode layout, main mode in bits 16-23, sub mode in bits 24-31): POSCTL
  (position hold on ground truth, the start mode, armed and airborne), OFFBOARD (the companion's
  SET_ATTITUDE_TARGET is the reference), AUTO_LOITER (hold), AUTO_LAND (descent; also the
  offboard-loss failsafe);
- COMMAND_LONG: ARM_DISARM, DO_SET_MODE, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE, acknowledged
  with PX4's results (a refused mode switch or arming change is TEMPORARILY_REJECTED, as
  PX4's commander answers);
- telemetry ATTITUDE_QUATERNION and HIGHRES_IMU (50 Hz by default, paced in sim time, noisy),
  ATTITUDE_TARGET (the reference's thrust, 50 Hz), EXTENDED_SYS_STATE (landed state) and
  SYS_STATUS (pre-arm check passed) at 5 Hz, HEARTBEAT at 1 Hz wall time;
- TIMESYNC answered as PX4 does: a request (tc1 = 0) gets tc1 = the boot time in ns (= the sim
  time it is polled at, the clock of time_boot_ms), ts1 echoed; not at time 0 (tc1 = 0 would
  read as a request);
- optional MAVLink 2 signing; malformed, unknown, foreign or unsigned input is counted and
  ignored.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import enum
import logging
import math
import os
import struct
import time
from typing import Callable

import numpy as np

from ibvs_common.core.frames import (GRAVITY, euler_zyx_from_rot, quat_from_rot, quat_multiply,
                                     rot_from_euler_zyx, rot_z)

# MAVLink 2 must be chosen before pymavlink.mavutil is imported (it picks the wire version then).
os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

MAVLINK_DIALECT = 'common'
mavutil.set_dialect(MAVLINK_DIALECT)  # re-select: an earlier import may have chosen MAVLink 1
mavlink = mavutil.mavlink

_log = logging.getLogger(__name__)
SETPOINT_LOG_LEN = 256        # new setpoints kept for latency readers (5 s at 50 Hz)

# --- MAVLink ids and flags (from pymavlink where it has them) ----------------------------------
MAV_COMP_ID_AUTOPILOT1 = mavlink.MAV_COMP_ID_AUTOPILOT1
MAV_TYPE_QUADROTOR = mavlink.MAV_TYPE_QUADROTOR
MAV_AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MAV_MODE_FLAG_SAFETY_ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
MAV_STATE_STANDBY = mavlink.MAV_STATE_STANDBY
MAV_STATE_ACTIVE = mavlink.MAV_STATE_ACTIVE
MAV_STATE_CRITICAL = mavlink.MAV_STATE_CRITICAL

MAV_CMD_COMPONENT_ARM_DISARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
MAV_CMD_DO_SET_MODE = mavlink.MAV_CMD_DO_SET_MODE
MAV_CMD_SET_MESSAGE_INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_CMD_REQUEST_MESSAGE = mavlink.MAV_CMD_REQUEST_MESSAGE

MAV_RESULT_ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
MAV_RESULT_TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
MAV_RESULT_DENIED = mavlink.MAV_RESULT_DENIED
MAV_RESULT_UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
MAV_RESULT_FAILED = mavlink.MAV_RESULT_FAILED

MAV_PARAM_TYPE_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
MAV_PARAM_TYPE_INT32 = mavlink.MAV_PARAM_TYPE_INT32
# COM_OBL_RC_ACT of what the sim does on an offboard loss: AUTO_LAND at once (PX4's 4, Land mode)
OFFBOARD_LOSS_ACTION_LAND = 4
MAV_SEVERITY_INFO = mavlink.MAV_SEVERITY_INFO
MAV_SEVERITY_WARNING = mavlink.MAV_SEVERITY_WARNING
MAV_SEVERITY_CRITICAL = mavlink.MAV_SEVERITY_CRITICAL

MSG_ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
MSG_ID_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
MSG_ID_HIGHRES_IMU = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
MSG_ID_ATTITUDE_TARGET = mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET
MSG_ID_EXTENDED_SYS_STATE = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
MSG_ID_SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
MAV_LANDED_STATE_ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
MAV_LANDED_STATE_IN_AIR = mavlink.MAV_LANDED_STATE_IN_AIR
MAV_VTOL_STATE_UNDEFINED = mavlink.MAV_VTOL_STATE_UNDEFINED
MAV_SYS_STATUS_PREARM_CHECK = mavlink.MAV_SYS_STATUS_PREARM_CHECK

TYPEMASK_BODY_RATES_IGNORE = (mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE
                              | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
                              | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE)
TYPEMASK_THROTTLE_IGNORE = mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
TYPEMASK_ATTITUDE_IGNORE = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE

HIGHRES_IMU_FIELDS_ACC_GYRO = (mavlink.HIGHRES_IMU_UPDATED_XACC | mavlink.HIGHRES_IMU_UPDATED_YACC
                               | mavlink.HIGHRES_IMU_UPDATED_ZACC
                               | mavlink.HIGHRES_IMU_UPDATED_XGYRO
                               | mavlink.HIGHRES_IMU_UPDATED_YGYRO
                               | mavlink.HIGHRES_IMU_UPDATED_ZGYRO)

BROADCAST_ID = 0                 # target_system / target_component 0: everyone
PX4_FORCE_DISARM_MAGIC = 21196   # COMPONENT_ARM_DISARM param2 that forces a disarm in the air
ARM_ACTION_DISARM = 0
ARM_ACTION_ARM = 1
SET_INTERVAL_DISABLE = -1        # SET_MESSAGE_INTERVAL param2: stop the stream
SET_INTERVAL_DEFAULT = 0         # SET_MESSAGE_INTERVAL param2: back to the default rate
UINT8_MASK = 0xFF                # PX4 casts the float params of DO_SET_MODE to uint8_t
PX4_MAIN_MODE_BIT = 16           # custom_mode bits 16-23: main mode
PX4_SUB_MODE_BIT = 24            # custom_mode bits 24-31: sub mode
US_PER_S = 1_000_000
MS_PER_S = 1000
NS_PER_S = 1_000_000_000
PARAM_ID_LEN = 16                # PARAM_VALUE.param_id, chars
STATUSTEXT_LEN = 50              # STATUSTEXT.text, chars
MIN_LIFT_FRACTION = 0.1          # hold / land never command less than 0.1 g of lift


class Px4MainMode(enum.IntEnum):
    """PX4's main modes (src/modules/commander/px4_custom_mode.h)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE_LEGACY = 8
    SIMPLE = 9
    TERMINATION = 10


class Px4AutoSubMode(enum.IntEnum):
    """PX4's AUTO sub modes (src/modules/commander/px4_custom_mode.h)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


class FlightMode(enum.Enum):
    """The PX4 modes this autopilot flies; value = (main mode, sub mode)."""

    POSCTL = (Px4MainMode.POSCTL, 0)
    OFFBOARD = (Px4MainMode.OFFBOARD, 0)
    AUTO_LOITER = (Px4MainMode.AUTO, Px4AutoSubMode.LOITER)
    AUTO_LAND = (Px4MainMode.AUTO, Px4AutoSubMode.LAND)

    @property
    def main_mode(self) -> int:
        """PX4 main mode number."""
        return int(self.value[0])

    @property
    def sub_mode(self) -> int:
        """PX4 sub mode number (0 = none)."""
        return int(self.value[1])

    @property
    def custom_mode(self) -> int:
        """HEARTBEAT.custom_mode in PX4's layout (main << 16 | sub << 24)."""
        return (self.main_mode << PX4_MAIN_MODE_BIT) | (self.sub_mode << PX4_SUB_MODE_BIT)


class ReferenceSource(str, enum.Enum):
    """Where the inner-loop reference comes from."""

    OFFBOARD = 'offboard'
    HOLD = 'hold'
    FAILSAFE = 'failsafe'
    DISARMED = 'disarmed'


# --- Data in and out ---------------------------------------------------------------------------


NOISE_GRID_S = 0.01      # s, sim-time step of the attitude error process


class NoiseStream(enum.IntEnum):
    """Independent noise streams of the telemetry (part of each sample's RNG key)."""

    ATTITUDE = 1
    ATTITUDE_RATES = 2
    HIGHRES_IMU = 3


@dataclass
class AutopilotConfig:
    """Settings of the simulated autopilot (SI units; rates in Hz; angles in rad).

    ``hover_thrust`` is PX4's MPC_THR_HOVER: the normalised thrust that holds the vehicle
    (0.5 = vehicle.yaml hover_thrust, maximum thrust 2 m g). ``signing_key_file`` holds a 32-byte
    MAVLink 2 signing key (raw 32 bytes, or 64 hex characters); None disables signing.
    Time-outs ``*_s`` are in sim time unless named ``*_wall_s``.
    """

    url: str = 'udpin:127.0.0.1:14560'
    hover_thrust: float = 0.5
    system_id: int = 1
    component_id: int = MAV_COMP_ID_AUTOPILOT1
    offboard_timeout_s: float = 0.5         # PX4 COM_OF_LOSS_T; sim time
    offboard_timeout_wall_s: float = 2.0    # wall-clock bound on the same loss (lockstep stall)
    offboard_stream_min_s: float = 0.5      # setpoints needed this long before OFFBOARD
    signing_key_file: str | None = None
    noise_seed: int = 0
    mass: float = 1.676                     # kg (the references are mass-normalised)
    start_armed: bool = True                # armed in POSCTL, airborne at the initial condition
    heartbeat_period_wall_s: float = 1.0
    telemetry_default_hz: float = 50.0
    thrust_telemetry_hz: float = 50.0       # ATTITUDE_TARGET default (= the bridge's request)
    status_telemetry_hz: float = 5.0        # EXTENDED_SYS_STATE, SYS_STATUS (as PX4 SITL)
    telemetry_max_hz: float = 250.0
    gyro_noise_std: float = 0.005           # rad/s, white, per axis
    accel_noise_std: float = 0.05           # m/s^2, white, per axis
    attitude_noise_std: float = math.radians(0.2)  # rad, stationary std per axis
    # An attitude estimator's error wanders slowly (first-order Gauss-Markov), it is not white
    # from one sample to the next: white 0.2 deg per sample would read as ~0.25 rad/s of
    # spurious rotation between two camera frames 20 ms apart.
    attitude_noise_tau_s: float = 5.0              # s, correlation time of that error
    hold_kp_xy: float = 2.0                 # 1/s^2
    hold_kd_xy: float = 2.5                 # 1/s
    hold_kp_z: float = 3.0                  # 1/s^2
    hold_kd_z: float = 3.0                  # 1/s
    max_tilt: float = math.radians(35.0)    # rad, hold / land attitude limit
    land_descent_rate: float = 0.4          # m/s, AUTO_LAND and failsafe (PX4 MPC_LAND_SPEED)
    land_speed_gain: float = 2.0            # 1/s, descent-rate loop
    floor_z: float = 0.0                    # m, {I} z of the landing plane
    landed_height: float = 0.15             # m, body origin above the floor counted as landed
    landed_speed: float = 0.3               # m/s, |v_z| below which landed
    auto_disarm_landed_s: float = 2.0       # PX4 COM_DISARM_LAND, in AUTO_LAND
    quat_norm_tol: float = 1e-2             # |‖q‖ - 1| accepted in SET_ATTITUDE_TARGET
    max_messages_per_poll: int = 2000
    log_period_wall_s: float = 5.0          # rate limit of repeated warnings


@dataclass
class VehicleStateView:
    """Ground truth the sim hands to the autopilot.

    t: sim time since boot (s). xi_I, v_I: position and velocity of the body origin in {I}
    (NED, m, m/s). R_IB: attitude (FRD -> NED). Omega_B: angular velocity in FRD (rad/s).
    accel_B_specific: specific force in FRD (m/s^2; (0, 0, -g) in hover), what an
    accelerometer measures.
    """

    t: float
    xi_I: np.ndarray
    v_I: np.ndarray
    R_IB: np.ndarray
    Omega_B: np.ndarray
    accel_B_specific: np.ndarray


@dataclass
class AttitudeReference:
    """Inner-loop reference: attitude of FRD in NED (w, x, y, z) and normalised thrust 0..1."""

    q_IB_wxyz: np.ndarray
    thrust_norm: float
    source: str  # ReferenceSource value: 'offboard' | 'hold' | 'failsafe' | 'disarmed'


@dataclass
class AutopilotCounters:
    """Event counters, for tests and diagnostics."""

    messages_received: int = 0      # decoded MAVLink messages (any type)
    malformed: int = 0              # bad bytes, CRC errors, truncated datagrams
    unknown_messages: int = 0       # ids outside the dialect, or types the sim does not handle
    foreign_target: int = 0         # addressed to another system/component
    signing_rejected: int = 0       # unsigned or wrongly signed while signing is on
    socket_errors: int = 0
    commands: int = 0
    commands_unsupported: int = 0
    commands_rejected: int = 0      # TEMPORARILY_REJECTED / DENIED / FAILED answers
    setpoints_received: int = 0     # well-formed SET_ATTITUDE_TARGET
    setpoints_invalid: int = 0      # NaN, non-unit quaternion, thrust outside [0, 1]
    setpoints_applied: int = 0      # received while armed and in OFFBOARD
    setpoints_rates_ignored: int = 0  # body rates not flagged ignored (the sim does not use them)
    param_requests: int = 0
    param_unknown: int = 0
    timesync_answered: int = 0      # TIMESYNC requests answered
    timesync_unanswered: int = 0    # requests read at boot time 0 (not answered)
    interval_clamped: int = 0       # SET_MESSAGE_INTERVAL faster than telemetry_max_hz
    failsafe_events: int = 0
    heartbeats_sent: int = 0
    attitude_quaternion_sent: int = 0
    highres_imu_sent: int = 0
    attitude_target_sent: int = 0
    extended_sys_state_sent: int = 0
    sys_status_sent: int = 0
    state_invalid: int = 0          # non-finite ground truth handed in by the sim


@dataclass
class _Stream:
    """A telemetry stream paced in sim time."""

    default_interval_s: float
    interval_s: float | None        # None = disabled
    next_due_t: float | None = None


@dataclass
class _Setpoint:
    """Latest well-formed SET_ATTITUDE_TARGET fields (held across ignored fields)."""

    q_wxyz: np.ndarray | None = None
    thrust: float | None = None


@dataclass
class _RateLimitedLog:
    """Log a message per key at most once per period (wall clock), with a suppressed count."""

    period_s: float
    clock: Callable[[], float]
    _last: dict = field(default_factory=dict)
    _suppressed: dict = field(default_factory=dict)

    def warning(self, key: str, msg: str, *args) -> None:
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        suffix = f' ({n} similar suppressed)' if n else ''
        _log.warning(msg + suffix, *args)


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


def _finite(*values) -> bool:
    return all(np.all(np.isfinite(np.asarray(v, dtype=float))) for v in values)


class Autopilot:
    """PX4-like autopilot on a MAVLink 2 UDP endpoint (see the module docstring)."""

    def __init__(self, config: AutopilotConfig,
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        """Open the endpoint (``config.url``) and start armed in POSCTL (or disarmed).

        ``wall_clock`` (s, monotonic) paces the heartbeat and bounds the offboard loss; tests may
        inject a fake one.
        """
        self.config = config
        self._wall = wall_clock
        self._rng = np.random.default_rng(config.noise_seed)
        # attitude error process on a fixed sim-time grid (see _noisy_attitude)
        self._att_err = self._rng_at(NoiseStream.ATTITUDE, 0).normal(
            0.0, config.attitude_noise_std, 3)                   # rad, body axes
        self._att_k = 0
        self._warn = _RateLimitedLog(config.log_period_wall_s, wall_clock)
        self.counters = AutopilotCounters()
        self.armed: bool = bool(config.start_armed)
        self.mode: FlightMode = FlightMode.POSCTL
        self.last_setpoint_time_boot_ms: int | None = None
        # (time_boot_ms, wall s) of every valid SET_ATTITUDE_TARGET whose time_boot_ms is new,
        # for latency measurements (the sim's sim/stats, benchmarks); the reader pops them
        self.new_setpoints: deque = deque(maxlen=SETPOINT_LOG_LEN)
        self._failsafe_active = False
        self._params = {'MPC_THR_HOVER': float(config.hover_thrust),
                        'COM_OF_LOSS_T': float(config.offboard_timeout_s),
                        'COM_OBL_RC_ACT': OFFBOARD_LOSS_ACTION_LAND}      # INT32, as PX4's
        intervals = {MSG_ID_ATTITUDE_QUATERNION: 1.0 / config.telemetry_default_hz,
                     MSG_ID_HIGHRES_IMU: 1.0 / config.telemetry_default_hz,
                     MSG_ID_ATTITUDE_TARGET: 1.0 / config.thrust_telemetry_hz,
                     MSG_ID_EXTENDED_SYS_STATE: 1.0 / config.status_telemetry_hz,
                     MSG_ID_SYS_STATUS: 1.0 / config.status_telemetry_hz}
        self._streams = {i: _Stream(v, v) for i, v in intervals.items()}
        self._setpoint = _Setpoint()
        self._sp_last_t: float | None = None      # sim time of the latest well-formed setpoint
        self._sp_last_wall: float | None = None
        self._sp_stream_start_t: float | None = None
        self._hold_xi: np.ndarray | None = None    # hold position {I}, m
        self._hold_yaw: float | None = None        # rad
        self._landed_since_t: float | None = None
        self._last_heartbeat_wall: float | None = None
        self._known_peers = 0
        self._last_t = 0.0
        self._conn = mavutil.mavlink_connection(config.url, source_system=config.system_id,
                                                source_component=config.component_id,
                                                dialect=MAVLINK_DIALECT)
        if config.signing_key_file:
            key = load_signing_key(config.signing_key_file)
            self._conn.setup_signing(key, sign_outgoing=True,
                                     allow_unsigned_callback=lambda _mav, _msg_id: False,
                                     link_id=0)
        _log.info('sim autopilot on %s (sys %d comp %d), %s, %s, signing %s', config.url,
                  config.system_id, config.component_id,
                  'armed' if self.armed else 'disarmed', self.mode.name,
                  'on' if config.signing_key_file else 'off')

    # --- public API ---------------------------------------------------------------------------

    def fileno(self) -> int:
        """File descriptor of the MAVLink socket (to wait on it with select)."""
        return self._conn.port.fileno()

    @property
    def failsafe(self) -> bool:
        """True while the offboard-loss failsafe flies the vehicle (reported as AUTO_LAND)."""
        return self._failsafe_active

    def poll(self, state: VehicleStateView, receive: bool = True,
             telemetry: bool = True) -> None:
        """Do one autopilot cycle at sim time ``state.t``; never blocks.

        Reads every pending datagram and answers it (unless ``receive`` is False: the
        lockstep sim reads only between frames), checks the offboard stream (failsafe),
        auto-disarms after a landing, sends due telemetry (sim-time rates; not with
        ``telemetry`` False: the sim before its first frame) and the heartbeat (wall clock).
        """
        self._last_t = float(state.t)
        self._ensure_hold_target(state)
        if receive:
            self._receive(state)
        self._check_offboard_loss(state)
        self._check_auto_disarm(state)
        self._send_heartbeat_if_due()
        if telemetry:
            self._send_telemetry_if_due(state)

    def attitude_reference(self, state: VehicleStateView) -> AttitudeReference:
        """Return the inner-loop reference for the current mode (does not change the mode)."""
        self._ensure_hold_target(state)
        if not _finite(state.xi_I, state.v_I, state.R_IB):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite ground truth at t=%.3f: level, hover', state.t)
            return AttitudeReference(np.array([1.0, 0.0, 0.0, 0.0]),
                                     self.config.hover_thrust if self.armed else 0.0,
                                     ReferenceSource.FAILSAFE.value
                                     if self.armed else ReferenceSource.DISARMED.value)
        if not self.armed:
            return AttitudeReference(self._level_quat(state), 0.0, ReferenceSource.DISARMED.value)
        if self.mode is FlightMode.OFFBOARD:
            q = self._setpoint.q_wxyz if self._setpoint.q_wxyz is not None \
                else self._level_quat(state)
            thrust = self._setpoint.thrust if self._setpoint.thrust is not None \
                else self.config.hover_thrust
            return AttitudeReference(np.array(q, dtype=float), float(thrust),
                                     ReferenceSource.OFFBOARD.value)
        if self.mode is FlightMode.AUTO_LAND:
            return self._land_reference(state)
        return self._hold_reference(state)

    def close(self) -> None:
        """Close the UDP endpoint."""
        try:
            self._conn.close()
        except OSError:
            pass

    # --- references ---------------------------------------------------------------------------

    def _ensure_hold_target(self, state: VehicleStateView) -> None:
        if self._hold_xi is None and _finite(state.xi_I, state.R_IB):
            self._set_hold_target(state)

    def _set_hold_target(self, state: VehicleStateView) -> None:
        self._hold_xi = np.array(state.xi_I, dtype=float)
        self._hold_yaw = euler_zyx_from_rot(state.R_IB)[2]

    def _level_quat(self, state: VehicleStateView) -> np.ndarray:
        """Level attitude keeping the current yaw."""
        yaw = euler_zyx_from_rot(state.R_IB)[2]
        return quat_from_rot(rot_from_euler_zyx(0.0, 0.0, yaw))

    def _thrust_attitude(self, acc_cmd_I: np.ndarray, yaw: float) -> tuple[np.ndarray, float]:
        """Attitude (w, x, y, z) and normalised thrust realising acceleration ``acc_cmd_I``.

        NED dynamics ``dv/dt = g e3 - (T/m) R e3``: the body z axis must point along
        ``g e3 - a`` and ``T/m = ‖g e3 - a‖``. The horizontal part is limited to ``max_tilt``.
        """
        acc = np.array(acc_cmd_I, dtype=float)
        lift = GRAVITY - acc[2]                        # up-acceleration the thrust must provide
        lift = max(lift, MIN_LIFT_FRACTION * GRAVITY)
        horiz = acc[:2]
        horiz_max = lift * math.tan(self.config.max_tilt)
        n = float(np.linalg.norm(horiz))
        if n > horiz_max:
            horiz = horiz * (horiz_max / n)
        b3_I = np.array([-horiz[0], -horiz[1], lift])  # g e3 - a, body z (down) in {I}
        thrust_acc = float(np.linalg.norm(b3_I))
        # Express b3 in the yaw-aligned frame, then read roll/pitch of R = Rz(yaw) Ry Rx.
        b = rot_z(yaw).T @ (b3_I / thrust_acc)
        pitch = math.atan2(b[0], b[2])
        roll = math.atan2(-b[1], math.hypot(b[0], b[2]))
        q = quat_from_rot(rot_from_euler_zyx(roll, pitch, yaw))
        thrust = self.config.hover_thrust * thrust_acc / GRAVITY
        return q, float(np.clip(thrust, 0.0, 1.0))

    def _hold_reference(self, state: VehicleStateView) -> AttitudeReference:
        """POSCTL / AUTO_LOITER: PD on ground-truth position towards the hold point, hold yaw."""
        c = self.config
        err = self._hold_xi - np.asarray(state.xi_I, dtype=float)
        v = np.asarray(state.v_I, dtype=float)
        kp = np.array([c.hold_kp_xy, c.hold_kp_xy, c.hold_kp_z])
        kd = np.array([c.hold_kd_xy, c.hold_kd_xy, c.hold_kd_z])
        q, thrust = self._thrust_attitude(kp * err - kd * v, self._hold_yaw)
        return AttitudeReference(q, thrust, ReferenceSource.HOLD.value)

    def _land_reference(self, state: VehicleStateView) -> AttitudeReference:
        """AUTO_LAND / failsafe: level, current yaw, descent-rate loop on ground truth."""
        c = self.config
        v_down = float(np.asarray(state.v_I, dtype=float)[2])
        acc_down = c.land_speed_gain * (c.land_descent_rate - v_down)
        thrust = c.hover_thrust * (GRAVITY - acc_down) / GRAVITY
        return AttitudeReference(self._level_quat(state), float(np.clip(thrust, 0.0, 1.0)),
                                 ReferenceSource.FAILSAFE.value)

    # --- state machine ------------------------------------------------------------------------

    def _landed(self, state: VehicleStateView) -> bool:
        c = self.config
        height = c.floor_z - float(state.xi_I[2])
        return height <= c.landed_height and abs(float(state.v_I[2])) <= c.landed_speed

    def _stream_healthy(self) -> bool:
        """Setpoints arrive (within the time-outs) and have done so for offboard_stream_min_s."""
        if self._sp_last_t is None or self._sp_stream_start_t is None:
            return False
        c = self.config
        t = self._last_t
        return (t - self._sp_last_t <= c.offboard_timeout_s
                and self._wall() - self._sp_last_wall <= c.offboard_timeout_wall_s
                and t - self._sp_stream_start_t >= c.offboard_stream_min_s)

    def _set_mode(self, mode: FlightMode, state: VehicleStateView, failsafe: bool = False) -> None:
        if mode in (FlightMode.POSCTL, FlightMode.AUTO_LOITER) and mode is not self.mode:
            self._set_hold_target(state)
        if mode is not self.mode:
            _log.info('mode %s -> %s%s', self.mode.name, mode.name,
                      ' (failsafe)' if failsafe else '')
        self.mode = mode
        self._failsafe_active = failsafe
        self._landed_since_t = None

    def _check_offboard_loss(self, state: VehicleStateView) -> None:
        if not (self.armed and self.mode is FlightMode.OFFBOARD):
            return
        c = self.config
        lost_sim = self._sp_last_t is None or state.t - self._sp_last_t > c.offboard_timeout_s
        lost_wall = (self._sp_last_wall is None
                     or self._wall() - self._sp_last_wall > c.offboard_timeout_wall_s)
        if lost_sim or lost_wall:
            self.counters.failsafe_events += 1
            _log.warning('offboard setpoints lost (%s): failsafe AUTO_LAND',
                         'sim time' if lost_sim else 'wall clock')
            self._set_mode(FlightMode.AUTO_LAND, state, failsafe=True)
            self._statustext(MAV_SEVERITY_CRITICAL, 'Failsafe: offboard lost, landing')

    def _check_auto_disarm(self, state: VehicleStateView) -> None:
        if not (self.armed and self.mode is FlightMode.AUTO_LAND):
            self._landed_since_t = None
            return
        if not _finite(state.xi_I, state.v_I) or not self._landed(state):
            self._landed_since_t = None
            return
        if self._landed_since_t is None:
            self._landed_since_t = state.t
        elif state.t - self._landed_since_t >= self.config.auto_disarm_landed_s:
            _log.info('landed for %.1f s in AUTO_LAND: disarming', state.t - self._landed_since_t)
            self.armed = False
            self._landed_since_t = None

    # --- receiving ----------------------------------------------------------------------------

    def _receive(self, state: VehicleStateView) -> None:
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
                self._last_heartbeat_wall = None        # greet a new peer at once
            rejected_before = mav.signing.reject_count
            try:
                msgs = mav.parse_buffer(data) or []
            except Exception as exc:  # pymavlink raises assorted errors on hostile input
                self.counters.malformed += 1
                self._warn.warning('parse', 'MAVLink parser error: %s', exc)
                msgs = []
            if mav.buf_len() > 0:
                # A datagram carries whole messages: a leftover is a truncated one. Drop it so
                # it cannot swallow the next datagram.
                self.counters.malformed += 1
                mav.buf = bytearray()
                mav.buf_index = 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
            self.counters.signing_rejected += mav.signing.reject_count - rejected_before
            for msg in msgs:
                try:
                    self._dispatch(msg, state)
                except Exception as exc:  # never let one message take the autopilot down
                    self.counters.malformed += 1
                    self._warn.warning('dispatch', 'error handling %s: %r', msg.get_type(), exc)

    def _dispatch(self, msg, state: VehicleStateView) -> None:
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
        handler = {'COMMAND_LONG': self._on_command_long,
                   'SET_ATTITUDE_TARGET': self._on_set_attitude_target,
                   'PARAM_REQUEST_READ': self._on_param_request_read,
                   'PARAM_REQUEST_LIST': self._on_param_request_list,
                   'TIMESYNC': self._on_timesync}.get(mtype)
        if handler is None:
            self.counters.unknown_messages += 1
            self._warn.warning('unhandled', 'MAVLink %s not handled by the sim autopilot', mtype)
            return
        handler(msg, state)

    def _for_us(self, target_system: int, target_component: int) -> bool:
        ok = (target_system in (BROADCAST_ID, self.config.system_id)
              and target_component in (BROADCAST_ID, self.config.component_id))
        if not ok:
            self.counters.foreign_target += 1
            self._warn.warning('foreign', 'ignored a message for %d/%d', target_system,
                               target_component)
        return ok

    # --- commands -----------------------------------------------------------------------------

    def _on_command_long(self, msg, state: VehicleStateView) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self.counters.commands += 1
        handlers = {MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
                    MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
                    MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
                    MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message}
        handler = handlers.get(msg.command)
        if handler is None:
            self.counters.commands_unsupported += 1
            result = MAV_RESULT_UNSUPPORTED
        else:
            result = handler(msg, state)
        if result != MAV_RESULT_ACCEPTED:
            self.counters.commands_rejected += 1
        self._conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(),
                                        msg.get_srcComponent())

    def _cmd_arm_disarm(self, msg, state: VehicleStateView) -> int:
        if not _finite(msg.param1, msg.param2):
            return MAV_RESULT_DENIED
        action = int(round(msg.param1))
        if action == ARM_ACTION_ARM:
            if self.armed:
                return MAV_RESULT_ACCEPTED
            if self.mode is FlightMode.OFFBOARD and not self._stream_healthy():
                self._statustext(MAV_SEVERITY_CRITICAL, 'Arming denied: no offboard signal')
                return MAV_RESULT_TEMPORARILY_REJECTED
            self.armed = True
            if self.mode in (FlightMode.POSCTL, FlightMode.AUTO_LOITER):
                self._set_hold_target(state)
            _log.info('armed (%s)', self.mode.name)
            return MAV_RESULT_ACCEPTED
        if action == ARM_ACTION_DISARM:
            if not self.armed:
                return MAV_RESULT_ACCEPTED
            forced = int(round(msg.param2)) == PX4_FORCE_DISARM_MAGIC
            if not forced and not self._landed(state):
                self._statustext(MAV_SEVERITY_CRITICAL, 'Disarming denied: not landed')
                return MAV_RESULT_TEMPORARILY_REJECTED
            self.armed = False
            _log.info('disarmed%s', ' (forced, in the air)' if not self._landed(state) else '')
            return MAV_RESULT_ACCEPTED
        return MAV_RESULT_DENIED

    def _cmd_set_mode(self, msg, state: VehicleStateView) -> int:
        if not _finite(msg.param1, msg.param2, msg.param3):
            return MAV_RESULT_DENIED
        base_mode = int(msg.param1) & UINT8_MASK
        if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MAV_RESULT_UNSUPPORTED  # base-mode-only switches are not modelled
        # PX4 casts the float params to uint8_t: on x86 SITL a packed 6 << 16 reads as 0.
        main = int(msg.param2) & UINT8_MASK
        sub = int(msg.param3) & UINT8_MASK
        if main == Px4MainMode.OFFBOARD:
            if self.mode is FlightMode.OFFBOARD or self._stream_healthy():
                self._set_mode(FlightMode.OFFBOARD, state)
                return MAV_RESULT_ACCEPTED
            self._statustext(MAV_SEVERITY_CRITICAL,
                             'Switching to Offboard is currently not available')
            return MAV_RESULT_TEMPORARILY_REJECTED
        if main == Px4MainMode.POSCTL:
            self._set_mode(FlightMode.POSCTL, state)
            return MAV_RESULT_ACCEPTED
        if main == Px4MainMode.AUTO and sub == Px4AutoSubMode.LOITER:
            self._set_mode(FlightMode.AUTO_LOITER, state)
            return MAV_RESULT_ACCEPTED
        if main == Px4MainMode.AUTO and sub == Px4AutoSubMode.LAND:
            self._set_mode(FlightMode.AUTO_LAND, state)
            return MAV_RESULT_ACCEPTED
        if any(main == known for known in Px4MainMode):
            self._statustext(MAV_SEVERITY_WARNING, f'Mode {main}/{sub} not available in the sim')
            return MAV_RESULT_TEMPORARILY_REJECTED
        # Unknown main mode: PX4's commander leaves the mode unchanged and still accepts.
        self._warn.warning('mode', 'DO_SET_MODE with unknown main mode %d (param2=%r): ignored',
                           main, msg.param2)
        return MAV_RESULT_ACCEPTED

    def _cmd_set_message_interval(self, msg, state: VehicleStateView) -> int:
        if not _finite(msg.param1, msg.param2):
            return MAV_RESULT_DENIED
        stream = self._streams.get(int(msg.param1))
        if stream is None:
            return MAV_RESULT_FAILED  # as PX4 does for a stream it does not have
        interval_us = int(msg.param2)
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

    def _cmd_request_message(self, msg, state: VehicleStateView) -> int:
        if not _finite(msg.param1):
            return MAV_RESULT_DENIED
        msg_id = int(msg.param1)
        if msg_id == MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif msg_id == MSG_ID_ATTITUDE_QUATERNION:
            self._send_attitude_quaternion(state)
        elif msg_id in self._senders():
            self._senders()[msg_id](state)
        else:
            return MAV_RESULT_UNSUPPORTED
        return MAV_RESULT_ACCEPTED

    # --- clock sync -----------------------------------------------------------------------------

    def _on_timesync(self, msg, state: VehicleStateView) -> None:
        """Answer a TIMESYNC request as PX4 does: tc1 = boot time now (ns), ts1 echoed.

        The boot time is the sim time of this poll (time_boot_ms is the same clock). In
        lockstep the sim reads MAVLink only between frames, so a request is answered with the
        time of the frame being waited on. An answer (tc1 != 0: we send no requests) is
        ignored. At time 0 no answer: a real autopilot's boot time is never 0, and tc1 = 0
        would read as a request. pymavlink's common TIMESYNC has no target fields: the answer
        goes to the link's peer.
        """
        if int(msg.tc1) != 0:
            return
        t_ns = int(round(float(state.t) * NS_PER_S))
        if t_ns <= 0:
            self.counters.timesync_unanswered += 1
            return
        self._conn.mav.timesync_send(t_ns, int(msg.ts1))
        self.counters.timesync_answered += 1

    # --- setpoints and parameters ---------------------------------------------------------------

    def _on_set_attitude_target(self, msg, state: VehicleStateView) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mask = int(msg.type_mask)
        use_att = not mask & TYPEMASK_ATTITUDE_IGNORE
        use_thrust = not mask & TYPEMASK_THROTTLE_IGNORE
        rates_given = (mask & TYPEMASK_BODY_RATES_IGNORE) != TYPEMASK_BODY_RATES_IGNORE
        q = np.asarray(msg.q, dtype=float)
        problem = None
        if use_att and not _finite(q):
            problem = f'non-finite quaternion {q}'
        elif use_att and abs(float(np.linalg.norm(q)) - 1.0) > self.config.quat_norm_tol:
            problem = f'non-unit quaternion (norm {np.linalg.norm(q):.4f})'
        elif use_thrust and not (_finite(msg.thrust) and 0.0 <= msg.thrust <= 1.0):
            problem = f'thrust {msg.thrust} outside [0, 1]'
        elif rates_given and not _finite(msg.body_roll_rate, msg.body_pitch_rate,
                                         msg.body_yaw_rate):
            problem = 'non-finite body rates'
        if problem is not None:
            self.counters.setpoints_invalid += 1
            self._warn.warning('setpoint', 'SET_ATTITUDE_TARGET ignored: %s', problem)
            return
        self.counters.setpoints_received += 1
        if rates_given:
            self.counters.setpoints_rates_ignored += 1
        if use_att:
            self._setpoint.q_wxyz = q / np.linalg.norm(q)
        if use_thrust:
            self._setpoint.thrust = float(msg.thrust)
        now_wall = self._wall()
        if (self._sp_last_t is None
                or state.t - self._sp_last_t > self.config.offboard_timeout_s
                or now_wall - self._sp_last_wall > self.config.offboard_timeout_wall_s):
            self._sp_stream_start_t = state.t          # a new stream starts
        self._sp_last_t = float(state.t)
        self._sp_last_wall = now_wall
        if int(msg.time_boot_ms) != self.last_setpoint_time_boot_ms:
            self.new_setpoints.append((int(msg.time_boot_ms), now_wall))
        self.last_setpoint_time_boot_ms = int(msg.time_boot_ms)
        if self.armed and self.mode is FlightMode.OFFBOARD:
            self.counters.setpoints_applied += 1

    def _param_names(self) -> list[str]:
        return list(self._params)

    def _send_param(self, name: str) -> None:
        names = self._param_names()
        value, kind = self._params[name], MAV_PARAM_TYPE_REAL32
        if isinstance(value, int):     # PX4's bytewise encoding: the INT32's bytes as a float
            value, kind = struct.unpack('<f', struct.pack('<i', value))[0], MAV_PARAM_TYPE_INT32
        self._conn.mav.param_value_send(name.encode('ascii')[:PARAM_ID_LEN], float(value), kind,
                                        len(names), names.index(name))

    def _on_param_request_read(self, msg, state: VehicleStateView) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self.counters.param_requests += 1
        names = self._param_names()
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
            else:
                self.counters.param_unknown += 1
            return
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(
            'ascii', 'replace')
        name = name.rstrip('\x00')
        if name in self._params:
            self._send_param(name)
        else:
            # PX4's parameter manager sends no PARAM_VALUE, only an info text.
            self.counters.param_unknown += 1
            self._statustext(MAV_SEVERITY_INFO, f'[pm] unknown param: {name}')

    def _on_param_request_list(self, msg, state: VehicleStateView) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self.counters.param_requests += 1
        for name in self._param_names():
            self._send_param(name)

    # --- sending ------------------------------------------------------------------------------

    def _peer_known(self) -> bool:
        """Tell whether sends can go out ('udpin' learns its peer from the first packet)."""
        if getattr(self._conn, 'udp_server', False):
            return bool(self._conn.clients)
        return True

    def _statustext(self, severity: int, text: str) -> None:
        self._conn.mav.statustext_send(severity, text.encode('ascii', 'replace')[:STATUSTEXT_LEN])

    def _send_heartbeat(self) -> None:
        base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base_mode |= MAV_MODE_FLAG_SAFETY_ARMED
        if self._failsafe_active:
            status = MAV_STATE_CRITICAL
        else:
            status = MAV_STATE_ACTIVE if self.armed else MAV_STATE_STANDBY
        self._conn.mav.heartbeat_send(MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode,
                                      self.mode.custom_mode, status)
        self.counters.heartbeats_sent += 1

    def _send_heartbeat_if_due(self) -> None:
        now = self._wall()
        if (self._last_heartbeat_wall is None
                or now - self._last_heartbeat_wall >= self.config.heartbeat_period_wall_s):
            self._last_heartbeat_wall = now
            if self._peer_known():
                self._send_heartbeat()

    def _send_telemetry_if_due(self, state: VehicleStateView) -> None:
        t = float(state.t)
        eps = 1e-9  # s, float slack so a 1 ms physics step hits a 20 ms period exactly
        senders = self._senders()
        for msg_id, stream in self._streams.items():
            if stream.interval_s is None:
                continue
            if stream.next_due_t is None:
                stream.next_due_t = t
            if t + eps < stream.next_due_t:
                continue
            stream.next_due_t += stream.interval_s
            if stream.next_due_t <= t:                   # fell behind: no burst, re-phase
                stream.next_due_t = t + stream.interval_s
            if self._peer_known():
                senders[msg_id](state)

    def _senders(self) -> dict:
        return {MSG_ID_ATTITUDE_QUATERNION: self._send_attitude_quaternion,
                MSG_ID_HIGHRES_IMU: self._send_highres_imu,
                MSG_ID_ATTITUDE_TARGET: self._send_attitude_target,
                MSG_ID_EXTENDED_SYS_STATE: self._send_extended_sys_state,
                MSG_ID_SYS_STATUS: self._send_sys_status}

    def _send_attitude_target(self, state: VehicleStateView) -> None:
        """ATTITUDE_TARGET: the inner-loop reference (attitude, thrust) now, as PX4 reports it.

        PX4 reports |thrust_body| of its attitude setpoint in any mode: the thrust applied.
        """
        ref = self.attitude_reference(state)
        q = [float(x) for x in ref.q_IB_wxyz]
        self._conn.mav.attitude_target_send(int(round(state.t * MS_PER_S)),
                                            TYPEMASK_BODY_RATES_IGNORE, q, 0.0, 0.0, 0.0,
                                            float(ref.thrust_norm))
        self.counters.attitude_target_sent += 1

    def _send_extended_sys_state(self, state: VehicleStateView) -> None:
        """EXTENDED_SYS_STATE: landed state from the (ground-truth) land detector."""
        landed = _finite(state.xi_I, state.v_I) and self._landed(state)
        self._conn.mav.extended_sys_state_send(
            MAV_VTOL_STATE_UNDEFINED,
            MAV_LANDED_STATE_ON_GROUND if landed else MAV_LANDED_STATE_IN_AIR)
        self.counters.extended_sys_state_sent += 1

    def _send_sys_status(self, state: VehicleStateView) -> None:
        """SYS_STATUS: only the pre-arm health bit (set: the sim has no pre-arm checks)."""
        zero = 0
        self._conn.mav.sys_status_send(zero, zero, MAV_SYS_STATUS_PREARM_CHECK, zero, zero,
                                       -1, -1, zero, zero, zero, zero, zero, zero)
        self.counters.sys_status_sent += 1

    def _noisy_attitude(self, R_IB: np.ndarray, t: float) -> np.ndarray:
        """Quaternion (w, x, y, z) of R_IB times a small, slowly varying body rotation.

        The error is a first-order Gauss-Markov process per axis (std attitude_noise_std,
        correlation time attitude_noise_tau_s), advanced to the sim time t.
        """
        cfg = self.config
        a = math.exp(-NOISE_GRID_S / cfg.attitude_noise_tau_s) \
            if cfg.attitude_noise_tau_s > 0 else 0.0
        k = int(t / NOISE_GRID_S)
        while self._att_k < k:            # advance on the grid: same errors whatever the rates
            self._att_k += 1
            self._att_err = a * self._att_err + math.sqrt(1.0 - a * a) * self._rng_at(
                NoiseStream.ATTITUDE, self._att_k).normal(0.0, cfg.attitude_noise_std, 3)
        half = 0.5 * self._att_err
        dq = np.concatenate(([1.0], half))
        q = quat_multiply(quat_from_rot(R_IB), dq / np.linalg.norm(dq))
        return q if q[0] >= 0.0 else -q

    def _rng_at(self, stream: 'NoiseStream', index: int) -> np.random.Generator:
        """Return the generator of one noise sample, keyed by (seed, stream, sim-time index).

        Noise then depends on the sim time only, not on how many messages were sent before
        (which depends on wall-clock timing of rate requests): two lockstep runs see the same
        noise.
        """
        return np.random.default_rng((self.config.noise_seed, int(stream), int(index)))

    def _send_attitude_quaternion(self, state: VehicleStateView) -> None:
        if not _finite(state.R_IB, state.Omega_B):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite attitude at t=%.3f: not sent', state.t)
            return
        q = self._noisy_attitude(state.R_IB, state.t)
        w = np.asarray(state.Omega_B, dtype=float) + self._rng_at(
            NoiseStream.ATTITUDE_RATES, int(round(state.t * US_PER_S))).normal(
            0.0, self.config.gyro_noise_std, 3)
        self._conn.mav.attitude_quaternion_send(int(round(state.t * MS_PER_S)), *map(float, q),
                                                *map(float, w))
        self.counters.attitude_quaternion_sent += 1

    def _send_highres_imu(self, state: VehicleStateView) -> None:
        if not _finite(state.accel_B_specific, state.Omega_B):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite IMU at t=%.3f: not sent', state.t)
            return
        c = self.config
        rng = self._rng_at(NoiseStream.HIGHRES_IMU, int(round(state.t * US_PER_S)))
        acc = np.asarray(state.accel_B_specific, dtype=float) + rng.normal(
            0.0, c.accel_noise_std, 3)
        gyro = np.asarray(state.Omega_B, dtype=float) + rng.normal(0.0, c.gyro_noise_std, 3)
        zero = 0.0
        self._conn.mav.highres_imu_send(int(round(state.t * US_PER_S)), *map(float, acc),
                                        *map(float, gyro), zero, zero, zero, zero, zero, zero,
                                        zero, HIGHRES_IMU_FIELDS_ACC_GYRO)
        self.counters.highres_imu_sent += 1


__all__ = ['Autopilot', 'AutopilotConfig', 'AutopilotCounters', 'AttitudeReference',
           'FlightMode', 'Px4AutoSubMode', 'Px4MainMode', 'ReferenceSource', 'VehicleStateView',
           'load_signing_key']
