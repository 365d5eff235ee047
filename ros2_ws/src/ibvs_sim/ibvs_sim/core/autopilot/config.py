"""Settings, data in and out, and counters of the sim autopilot; helpers all its parts share.

Frames and units (docs/spec.md section 1): {I} is the autopilot's local NED frame, the body
frame is FRD, quaternions are Hamilton ``(w, x, y, z)`` of ``R_IB``. SI units.
``VehicleStateView.t`` is sim time since boot (s); the wall clock (``time.monotonic`` or an
injected one, s) only paces the heartbeat, the offboard-loss bound ``offboard_timeout_wall_s``
and the log rate limit.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import logging
import math
from typing import Callable

import numpy as np

from ibvs_sim.core.autopilot.protocol import MAV_COMP_ID_AUTOPILOT1
from ibvs_sim.core.radio import PilotSwitchRadio

# One logger for every part of the autopilot: 'ibvs_sim.core.autopilot', as before the split.
LOG = logging.getLogger(__package__)

MAX_ESTIMATE_OFFSET_RAD = 0.2     # rad (11.5 deg): larger is not an estimator error to fly on


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
    offboard_timeout_s: float = 1.0         # PX4 COM_OF_LOSS_T (v1.16 default); sim time
    radio: PilotSwitchRadio | None = None    # the pilot's RC input (RC_CHANNELS); None: no RC
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
    timesync_request_hz: float = 10.0       # own TIMESYNC requests, sim time (PX4: ~10 Hz)
    # rad/s, white, per body axis (FRD x, y, z) of each ATTITUDE_QUATERNION and HIGHRES_IMU
    # rate sample (the sim node's gyro_noise_std_radps; PX4 SIH's imu/data against its truth
    # in flight: 0.083, 0.040, 0.017)
    gyro_noise_std: tuple = (0.005, 0.005, 0.005)
    # m/s^2, white, per body axis (FRD x, y, z) of each HIGHRES_IMU sample (the sim node's
    # accel_noise_std_mps2; PX4 SIH's as the bridge receives it: 0.28, 0.95, 0.80)
    accel_noise_std: tuple = (0.05, 0.05, 0.05)
    # The estimate's error wanders (first-order Gauss-Markov per axis), it is not white from one
    # sample to the next: white noise per sample would read as spurious rotation between two
    # camera frames 20 ms apart. Fitted to PX4 v1.16 SIH's EKF2 on motion capture during a
    # mission (docs/sim_autopilot.md "Attitude-estimate error: fitted to PX4 SIH"): std roll /
    # pitch / yaw 1.02 / 0.43 / 0.51 deg (RMS over the axes 0.70), autocorrelation 1/e at
    # 1.75-2.5 s.
    attitude_noise_std: float = 0.0122      # rad (0.7 deg), stationary std per axis
    attitude_noise_tau_s: float = 2.0       # s (sim), correlation time of that error
    # A static error of the estimate (roll, pitch; rad, body rotation vector (x, y, 0)): an
    # accelerometer bias b tilts an estimate that levels on it by b / g (PX4 SIH: 1.5-1.8 deg
    # in one axis). Reported and flown, as the noise above (noise.py).
    attitude_estimate_offset_rad: tuple = (0.0, 0.0)
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
    # fault injection (tests only), [start, end) in sim s, start == end: never. Off: no
    # ATTITUDE_QUATERNION / HIGHRES_IMU (an attitude estimator that stopped); NaN: they carry
    # NaN (a broken estimator or sensor driver)
    imu_off_s: tuple = (0.0, 0.0)
    imu_nan_s: tuple = (0.0, 0.0)

    def __post_init__(self) -> None:
        offset = tuple(float(a) for a in self.attitude_estimate_offset_rad)
        if len(offset) != 2 or not all(math.isfinite(a) and abs(a) <= MAX_ESTIMATE_OFFSET_RAD
                                       for a in offset):
            raise ValueError('attitude_estimate_offset_rad must be (roll, pitch), each finite '
                             f'and within +-{MAX_ESTIMATE_OFFSET_RAD} rad, got '
                             f'{self.attitude_estimate_offset_rad!r}')
        self.attitude_estimate_offset_rad = offset
        std_max = MAX_ESTIMATE_OFFSET_RAD / 2.0
        std = self.attitude_noise_std
        if not (math.isfinite(std) and 0.0 <= std <= std_max):
            raise ValueError(f'attitude_noise_std must be finite and within [0, {std_max}] rad, '
                             f'got {self.attitude_noise_std!r}')
        if not (math.isfinite(self.attitude_noise_tau_s) and self.attitude_noise_tau_s >= 0.0):
            raise ValueError('attitude_noise_tau_s must be finite and >= 0 (0: white), got '
                             f'{self.attitude_noise_tau_s!r}')

    def imu_fault_at(self, t: float) -> str:
        """Return 'off', 'nan' or '' (no IMU fault) at sim time ``t`` (s)."""
        for name, (start, end) in (('off', self.imu_off_s), ('nan', self.imu_nan_s)):
            if start <= t < end:
                return name
        return ''


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
    timesync_requests_sent: int = 0   # our own requests (TimesyncRequester)
    timesync_answers_received: int = 0  # answers to them (ts1 one of ours, tc1 > 0)
    timesync_answers_foreign: int = 0   # answers to no request of ours, or tc1 <= 0
    interval_clamped: int = 0       # SET_MESSAGE_INTERVAL faster than telemetry_max_hz
    failsafe_events: int = 0
    heartbeats_sent: int = 0
    attitude_quaternion_sent: int = 0
    highres_imu_sent: int = 0
    attitude_target_sent: int = 0
    imu_faulted: int = 0            # IMU messages withheld or sent as NaN (fault injection)
    extended_sys_state_sent: int = 0
    sys_status_sent: int = 0
    rc_channels_sent: int = 0
    state_invalid: int = 0          # non-finite ground truth handed in by the sim


@dataclass
class RateLimitedLog:
    """Log a message per key at most once per period (wall clock), with a suppressed count."""

    period_s: float
    clock: Callable[[], float]
    _last: dict = field(default_factory=dict)
    _suppressed: dict = field(default_factory=dict)

    def warning(self, key: str, msg: str, *args) -> None:
        """Log ``msg % args`` as a warning unless ``key`` was logged less than period_s ago."""
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        suffix = f' ({n} similar suppressed)' if n else ''
        LOG.warning(msg + suffix, *args)


def finite(*values) -> bool:
    """Tell whether every element of every value (scalars or arrays) is finite."""
    return all(np.all(np.isfinite(np.asarray(v, dtype=float))) for v in values)
