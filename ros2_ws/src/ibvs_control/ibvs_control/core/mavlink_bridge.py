"""The MAVLink bridge without ROS: setpoint shaping, IMU decoding, clock sync, sequencing.

:class:`MavlinkBridge` owns a :class:`~ibvs_control.core.mavlink_link.MavlinkLink` and an
:class:`~ibvs_control.core.mavlink_sequencer.EngageSequencer`. The node feeds it the force and
heading setpoints and the supervisor mode, and calls :meth:`MavlinkBridge.poll` (receive),
:meth:`MavlinkBridge.stream` (>= 50 Hz, repeat the latest setpoint) and
:meth:`MavlinkBridge.heartbeat` (1 Hz) from timers.

Setpoint (SET_ATTITUDE_TARGET, docs/mavlink.md)
    q = attitude of body FRD in the autopilot's local NED (= {I}) with R_d e3 = F / |F| and
    the desired yaw (attitude.attitude_from_force); thrust = |F| / (m g) * hover_thrust in
    [0, 1]; type_mask = 7 (body rates ignored); time_boot_ms = the latest force's stamp mapped
    to the autopilot's boot time at each send (fallback targets too; 0 before any force or
    while the clocks are not synced). A NEW setpoint is sent at once (the sim's lockstep pacing
    waits for it), the stream timer repeats the latest one.
Clock sync (:mod:`ibvs_control.core.time_sync`, docs/mavlink.md)
    :meth:`MavlinkBridge.poll` gets the ROS time; the bridge sends TIMESYNC requests, takes the
    answers into :class:`~ibvs_control.core.time_sync.TimeSync` and answers the autopilot's
    own requests (tc1 = our ROS time). imu/data stamps = time_boot_ms + offset, on the ROS
    clock; while the offset is unknown no IMU sample is published (a wrong stamp would be a
    silent wrong output): it is dropped, counted and reported by a throttled warning.
Heading / force pairing (:class:`HeadingPairing`)
    The heading and the force of one camera frame share its stamp but come on two topics, in
    either order. A force is flown with the heading of the SAME stamp: if that heading has not
    arrived yet, and headings are expected (the previous force had its heading), the force is
    held until it arrives or for at most ``heading_wait_s`` (then flown with the latest
    heading). A heading arriving after its force was sent never changes what was sent.
Mode-dependent content (supervisor mode -> what is sent)
    The mode is the supervisor's for the stamp of the latest force (``ibvs/supervisor_status``,
    :meth:`MavlinkBridge.content_mode`), else the latest ``ibvs/mode``, which also drives the
    engage sequencer. IDLE, WINDOW, CROSSING, LANDING: the controller's F and heading.
    SHUTDOWN: level at the current yaw, thrust ramped linearly from its value at the switch to
    0 over ``shutdown_ramp_s``. FAILSAFE: level at the current yaw, thrust =
    ``failsafe_thrust_ratio`` x hover thrust (a slow descent; the autopilot's land detector or
    an operator ends it).
Bad input
    A non-finite or out-of-range force or heading is never sent: the last valid setpoint is
    kept for at most ``hold_last_s``, then a level hover at the current yaw replaces it.
"""
from __future__ import annotations

from collections import deque, OrderedDict
from dataclasses import dataclass, field
from enum import Enum
import time
from typing import Callable

import numpy as np

from ibvs_control.core.attitude import attitude_from_force, shutdown_thrust_scale
from ibvs_control.core.frames import (
    euler_zyx_from_rot, GRAVITY, quat_from_rot, quat_ned_frd_to_enu_flu, R_IB_from_rot_map_base,
    rot_from_quat, rot_z, vec_frd_to_flu)
from ibvs_control.core.mavlink_link import LinkConfig, MavAutopilot, MavlinkLink, MavMsgId
from ibvs_control.core.mavlink_sequencer import (
    Autopilot, EngageSequencer, SequencerConfig, SequencerInputs)
from ibvs_control.core.modes import Mode
from ibvs_control.core.time_sync import TimeSync, TimeSyncConfig, TimeSyncStatus

ATTITUDE_TARGET_IGNORE_BODY_RATES = 7   # type_mask bits 0-2: roll, pitch, yaw rate ignored
NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000
HOVER_PARAM = {Autopilot.PX4: 'MPC_THR_HOVER', Autopilot.ARDUPILOT: 'MOT_THST_HOVER'}
GUID_OPTIONS_PARAM = 'GUID_OPTIONS'
HOVER_THRUST_RANGE = (0.05, 0.95)       # a hover-thrust parameter outside this is refused
QUAT_NORM_TOLERANCE = 0.1               # |q| in [0.9, 1.1], else the sample is dropped
MS_PER_S = 1000.0
STREAM_GAP_S = 0.5                      # a longer pause in sending restarts the stream count
HEADING_BUFFER_LEN = 8                  # headings kept by stamp, and sent stamps remembered
AUTOPILOT_OF_HEARTBEAT = {MavAutopilot.PX4: Autopilot.PX4,
                          MavAutopilot.ARDUPILOTMEGA: Autopilot.ARDUPILOT}
IMU_DROP_WARN_PERIOD_S = 2.0            # s (monotonic) between "IMU dropped" warnings


class SetpointSource(Enum):
    """Where the content of the setpoint being streamed comes from."""

    NONE = 'none'                   # nothing sent yet
    IBVS = 'ibvs'                   # the force controller's F and heading
    HOLD_LAST = 'hold_last'         # bad input: the last valid IBVS setpoint, held
    LEVEL_HOVER = 'level_hover'     # no valid input for hold_last_s
    FAILSAFE = 'failsafe'           # supervisor FAILSAFE: level, slow descent
    SHUTDOWN_RAMP = 'shutdown_ramp'  # supervisor SHUTDOWN: thrust ramp to 0


@dataclass(frozen=True)
class BridgeConfig:
    """Everything the bridge core needs (node parameters + vehicle.yaml)."""

    link: LinkConfig
    mass: float                              # kg (vehicle.yaml)
    max_thrust_factor: float                 # max thrust / (m g) (vehicle.yaml)
    configured_hover_thrust: float           # normalised (vehicle.yaml or parameter)
    autopilot: str = 'auto'                  # 'auto' (from HEARTBEAT) | 'px4' | 'ardupilot'
    hover_thrust_source: str = 'autopilot'   # 'autopilot' (parameter read) | 'config'
    param_timeout_s: float = 3.0             # parameter reads unanswered: fallback/refuse
    param_retry_s: float = 0.5
    attitude_rate_hz: float = 100.0          # ATTITUDE_QUATERNION requested rate
    imu_rate_hz: float = 100.0               # HIGHRES_IMU requested rate
    interval_retry_s: float = 2.0            # re-request a message not received for this long
    time_sync: TimeSyncConfig = field(default_factory=TimeSyncConfig)   # TIMESYNC estimator
    hold_last_s: float = 0.5                 # keep the last valid setpoint this long (s,
    #                                          monotonic) when input is bad or stops
    max_force_factor: float = 3.0            # |F| above factor * m g is out of range
    max_tilt_rad: float = 0.6                # tilt limit of the thrust direction
    failsafe_thrust_ratio: float = 0.9       # FAILSAFE thrust = ratio * hover thrust
    shutdown_ramp_s: float = 2.0             # SHUTDOWN: thrust ramp time to 0
    heading_wait_s: float = 0.02             # s (monotonic): a force waits this long at most
    #                                          for the heading of its stamp (0: never waits)
    sequencer: SequencerConfig = field(default_factory=SequencerConfig)

    def __post_init__(self):
        if self.autopilot not in ('auto', 'px4', 'ardupilot'):
            raise ValueError(f"autopilot must be 'auto', 'px4' or 'ardupilot', not "
                             f'{self.autopilot!r}')
        if self.hover_thrust_source not in ('autopilot', 'config'):
            raise ValueError("hover_thrust_source must be 'autopilot' or 'config'")
        lo, hi = HOVER_THRUST_RANGE
        if not lo <= self.configured_hover_thrust <= hi:
            raise ValueError(f'configured hover thrust {self.configured_hover_thrust} outside '
                             f'[{lo}, {hi}]')
        positive = ('mass', 'max_thrust_factor', 'param_timeout_s', 'param_retry_s',
                    'attitude_rate_hz', 'imu_rate_hz', 'interval_retry_s', 'hold_last_s',
                    'max_force_factor', 'max_tilt_rad', 'shutdown_ramp_s')
        for name in positive:
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        if not 0.0 < self.failsafe_thrust_ratio <= 1.0:
            raise ValueError('failsafe_thrust_ratio must be in (0, 1]')
        if not (np.isfinite(self.heading_wait_s) and self.heading_wait_s >= 0.0):
            raise ValueError(f'heading_wait_s must be finite and >= 0, got '
                             f'{self.heading_wait_s}')


@dataclass(frozen=True)
class AttitudeTarget:
    """Content of one SET_ATTITUDE_TARGET."""

    time_boot_ms: int
    q_wxyz: np.ndarray              # body FRD in local NED, unit, (w, x, y, z)
    thrust: float                   # normalised [0, 1]
    source: SetpointSource
    type_mask: int = ATTITUDE_TARGET_IGNORE_BODY_RATES


@dataclass(frozen=True)
class ImuSample:
    """One imu/data message in ROS conventions (ENU/FLU as MAVROS converts them)."""

    stamp_ns: int                   # ROS time
    q_wxyz: np.ndarray              # base_link (FLU) in map (ENU), (w, x, y, z)
    angular_velocity_flu: np.ndarray  # rad/s
    linear_acceleration_flu: np.ndarray | None  # m/s^2 (specific force), None: no HIGHRES_IMU


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
    hover_thrust: float | None
    hover_thrust_source: str
    setpoint_source: str
    setpoint_rate_hz: float
    rejected_setpoints: int
    counters: dict
    time_sync: TimeSyncStatus
    imu_dropped_unsynced: int       # ATTITUDE_QUATERNION dropped while the clock was unsynced


def yaw_from_heading_quat(q_wxyz_enu_flu: np.ndarray) -> float:
    """NED yaw (rad) of a heading quaternion (base_link in map, w x y z).

    Raises ValueError if the quaternion is non-finite or not unit within 10 %.
    """
    q = np.asarray(q_wxyz_enu_flu, dtype=float)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(n - 1.0) > QUAT_NORM_TOLERANCE:
        raise ValueError(f'heading quaternion {q!r} is not a unit quaternion')
    return euler_zyx_from_rot(R_IB_from_rot_map_base(rot_from_quat(q)))[2]


class HoverThrust:
    """Hover thrust: the autopilot's parameter if it answers, else the configured value."""

    def __init__(self, configured: float, use_autopilot: bool) -> None:
        self.configured = configured
        self.use_autopilot = use_autopilot
        self.value: float | None = None if use_autopilot else configured
        self.source = 'pending' if use_autopilot else 'config'
        self.error = ''

    def on_param(self, name: str, value: float) -> None:
        """Take the autopilot's answer if it is in range (else keep the configured one)."""
        lo, hi = HOVER_THRUST_RANGE
        if not (np.isfinite(value) and lo <= value <= hi):
            self.error = f'{name} = {value} outside [{lo}, {hi}]: using the configured ' \
                         f'{self.configured}'
            self.value, self.source = self.configured, 'config (autopilot value refused)'
            return
        self.value, self.source = float(value), f'autopilot {name}'

    def on_timeout(self) -> None:
        """No answer: fall back to the configured value."""
        if self.value is None:
            self.value, self.source = self.configured, 'config (autopilot did not answer)'


class SetpointShaper:
    """Turns (mode, latest valid force/heading, attitude) into the attitude target to send."""

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        self.rejected = 0
        self.last_error = ''
        self._valid: tuple[float, np.ndarray, float] | None = None  # (t_rx, F, NED yaw)
        self._last_refused = False
        self._ramp: ShutdownRamp | None = None
        self._last_thrust: float | None = None

    def check_force(self, F_I: np.ndarray) -> str:
        """Return '' for a usable force (N, {I}), else the reason it is refused."""
        F = np.asarray(F_I, dtype=float)
        if F.shape != (3,) or not np.all(np.isfinite(F)):
            return f'non-finite force {F!r}'
        limit = self.config.max_force_factor * self.config.mass * GRAVITY
        if np.linalg.norm(F) > limit:
            return f'|F| = {np.linalg.norm(F):.1f} N above {limit:.1f} N'
        if F[2] <= 0.0:
            return f'F = {F} has no downward (thrust-up) component'
        return ''

    def on_force(self, t: float, F_I: np.ndarray, yaw: float) -> str:
        """Store a force received at monotonic time t with the NED yaw it is flown with.

        Returns '' or the refusal reason (a refused force keeps the last valid one).
        """
        reason = self.check_force(F_I)
        self._last_refused = bool(reason)
        if reason:
            self.rejected += 1
            self.last_error = reason
            return reason
        self._valid = (t, np.asarray(F_I, dtype=float).copy(), float(yaw))
        return ''

    def ramp_done(self, t: float) -> bool:
        """Whether the SHUTDOWN ramp has reached zero thrust (t: monotonic s)."""
        return (self._ramp is not None and shutdown_thrust_scale(
            self._ramp.elapsed(t), self.config.shutdown_ramp_s) <= 0.0)

    def target(self, t: float, mode: Mode, yaw_now: float, hover: float,
               time_boot_ms: int, t_vehicle: float) -> AttitudeTarget:
        """Return the attitude target for supervisor ``mode`` at monotonic time t.

        ``yaw_now``: current NED yaw (level setpoints keep it); ``hover``: hover thrust;
        ``time_boot_ms``: what the target carries; ``t_vehicle``: the latest force's stamp (s,
        ROS clock: sim time in the sim), the clock of the shutdown ramp.
        """
        level_q = quat_from_rot(rot_z(yaw_now))
        if mode == Mode.SHUTDOWN:
            if self._ramp is None:
                start = self._last_thrust if self._last_thrust is not None else hover
                self._ramp = ShutdownRamp(start, t_vehicle, t)
            self._ramp.advance(t_vehicle, t)
            scale = shutdown_thrust_scale(self._ramp.elapsed(t), self.config.shutdown_ramp_s)
            return self._out(time_boot_ms, level_q, self._ramp.start_thrust * scale,
                             SetpointSource.SHUTDOWN_RAMP)
        self._ramp = None
        if mode == Mode.FAILSAFE:
            return self._out(time_boot_ms, level_q, self.config.failsafe_thrust_ratio * hover,
                             SetpointSource.FAILSAFE)
        if self._valid is not None and t - self._valid[0] <= self.config.hold_last_s:
            _, F, yaw = self._valid
            sp = attitude_from_force(F, yaw, self.config.mass, hover,
                                     self.config.max_thrust_factor, self.config.max_tilt_rad)
            return self._out(time_boot_ms, sp.q_IB_wxyz, sp.thrust_norm,
                             SetpointSource.HOLD_LAST if self._last_refused
                             else SetpointSource.IBVS)
        return self._out(time_boot_ms, level_q, hover, SetpointSource.LEVEL_HOVER)

    def _out(self, time_boot_ms: int, q: np.ndarray, thrust: float,
             source: SetpointSource) -> AttitudeTarget:
        thrust = float(np.clip(thrust, 0.0, 1.0))
        self._last_thrust = thrust
        return AttitudeTarget(int(time_boot_ms), np.asarray(q, dtype=float), thrust, source)


@dataclass(frozen=True)
class PairedForce:
    """A force to send now, with the heading it is flown with."""

    stamp_ns: int                   # the force's stamp (ROS time, ns)
    F_I: np.ndarray                 # N, {I}
    t_rx: float                     # monotonic s when the force was received
    yaw: float | None               # NED yaw to fly; None: no heading yet (the current yaw)
    paired: bool                    # True: the heading of the same stamp


class HeadingPairing:
    """Pairs each force with the heading of the same stamp (ROS-free, no I/O).

    The controller publishes, per camera frame of stamp S, the heading S and then the force S
    on two topics, which the node may take in either order. Rules:

    - headings are kept by exact stamp (int ns; the last ``buffer_len``);
    - a force S whose heading S is there is sent at once with it;
    - otherwise, if headings are *expected* (a heading was seen and the previous force had its
      heading S', before or after it was sent), a valid force is held until its heading
      arrives (then sent at once with it), or until ``wait_s`` has passed (:meth:`expire`), or
      until a heading newer than S arrives (the topic is ordered: heading S will not come),
      or until a newer force arrives; it is then sent with the latest heading and counted in
      ``missing``;
    - any other force (none expected, or refused: it is not flown anyway) is sent at once with
      the latest heading (None before any heading);
    - a heading whose force was already sent is counted in ``late`` and only becomes the
      latest heading for later forces: what was sent for its stamp never changes.

    Each method returns the forces to send now, in order.
    """

    def __init__(self, wait_s: float, buffer_len: int = HEADING_BUFFER_LEN) -> None:
        self.wait_s = wait_s
        self.latest_yaw: float | None = None    # latest valid heading received (NED yaw)
        self.late = 0                           # headings that came after their force
        self.missing = 0                        # held forces sent without their heading
        self._headings: OrderedDict[int, float | None] = OrderedDict()  # None: refused
        self._sent: deque = deque(maxlen=buffer_len)    # stamps of forces already sent
        self._buffer_len = buffer_len
        self._held: PairedForce | None = None
        self._any_heading = False
        self._last_force_stamp: int | None = None
        self._last_force_had_heading = False

    @property
    def holding(self) -> bool:
        """Whether a force is waiting for its heading."""
        return self._held is not None

    def expected(self) -> bool:
        """Whether the next force is expected to come with a heading of its stamp."""
        if not self._any_heading:
            return False
        return self._last_force_stamp is None or self._last_force_had_heading

    def on_heading(self, stamp_ns: int, yaw: float | None) -> list[PairedForce]:
        """Heading of stamp_ns (NED yaw, or None if it was refused as invalid)."""
        stamp_ns = int(stamp_ns)
        out = []
        if self._held is not None and stamp_ns > self._held.stamp_ns:
            out.append(self._release_unpaired())
        self._any_heading = True
        if stamp_ns == self._last_force_stamp:
            self._last_force_had_heading = True
        if self._held is not None and stamp_ns == self._held.stamp_ns:
            held, self._held = self._held, None
            out.append(PairedForce(held.stamp_ns, held.F_I, held.t_rx,
                                   self.latest_yaw if yaw is None else yaw, yaw is not None))
            self._sent.append(stamp_ns)
        elif stamp_ns in self._sent:
            self.late += 1
        else:
            self._headings[stamp_ns] = yaw
            self._headings.move_to_end(stamp_ns)
            while len(self._headings) > self._buffer_len:
                self._headings.popitem(last=False)
        if yaw is not None:
            self.latest_yaw = float(yaw)
        return out

    def on_force(self, stamp_ns: int, F_I: np.ndarray, t: float,
                 may_wait: bool = True) -> list[PairedForce]:
        """Force of stamp_ns received at monotonic time t (``may_wait`` False: refused)."""
        stamp_ns = int(stamp_ns)
        out = [self._release_unpaired()] if self._held is not None else []
        expected = self.expected()
        self._last_force_stamp = stamp_ns
        self._last_force_had_heading = stamp_ns in self._headings
        F = np.asarray(F_I, dtype=float).copy()
        if self._last_force_had_heading:
            yaw = self._headings.pop(stamp_ns)
            out.append(PairedForce(stamp_ns, F, t, self.latest_yaw if yaw is None else yaw,
                                   yaw is not None))
        elif expected and may_wait and self.wait_s > 0.0:
            self._held = PairedForce(stamp_ns, F, t, None, False)
            return out
        else:
            out.append(PairedForce(stamp_ns, F, t, self.latest_yaw, False))
        self._sent.append(stamp_ns)
        return out

    def expire(self, t: float) -> list[PairedForce]:
        """Release a held force whose wait has passed at monotonic time t."""
        if self._held is not None and t - self._held.t_rx >= self.wait_s:
            return [self._release_unpaired()]
        return []

    def _release_unpaired(self) -> PairedForce:
        held, self._held = self._held, None
        self.missing += 1
        self._sent.append(held.stamp_ns)
        return PairedForce(held.stamp_ns, held.F_I, held.t_rx, self.latest_yaw, False)


RAMP_STALL_S = 1.0          # s (wall) without newer setpoint stamps before the ramp uses the wall


@dataclass
class ShutdownRamp:
    """Elapsed time of the mode-4 thrust ramp, in the VEHICLE's time.

    The ramp runs on the stamps of the forces (the ROS clock: sim time in the sim, where
    lockstep makes it run slower than the wall clock; the same instants the setpoints'
    time_boot_ms carry, without depending on the clock sync), so the descent profile is the
    same whatever the pacing. If the setpoint stamps stop advancing (the controller went
    silent), it goes on with the wall clock after RAMP_STALL_S, so thrust never hangs.
    """

    start_thrust: float
    t_vehicle: float                 # s, last vehicle time seen
    t_wall: float                    # s, monotonic time when it was seen
    progress: float = 0.0            # s of vehicle time elapsed up to t_vehicle

    def advance(self, t_vehicle: float, t_wall: float) -> None:
        """Account for a setpoint at vehicle time t_vehicle, sent at wall time t_wall."""
        if t_vehicle > self.t_vehicle:
            self.progress += self._stalled(t_wall) + (t_vehicle - self.t_vehicle)
            self.t_vehicle, self.t_wall = t_vehicle, t_wall

    def _stalled(self, t_wall: float) -> float:
        return max(0.0, t_wall - self.t_wall - RAMP_STALL_S)

    def elapsed(self, t_wall: float) -> float:
        """Return how long the ramp has run (s): vehicle time, plus wall time past a stall."""
        return self.progress + self._stalled(t_wall)


class RateMeter:
    """Events per second over a sliding window (for the setpoint rate diagnostic)."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self._t: deque = deque()

    def tick(self, t: float) -> None:
        """Record one event at time t."""
        self._t.append(t)
        self._trim(t)

    def rate(self, t: float) -> float:
        """Events per second in the last window."""
        self._trim(t)
        return len(self._t) / self.window_s

    def _trim(self, t: float) -> None:
        while self._t and self._t[0] < t - self.window_s:
            self._t.popleft()


STATUS_MODES_KEPT = 32      # supervisor modes by stamp kept to pair with forces (0.64 s)


class MavlinkBridge:
    """ROS-free bridge: call on_* for inputs, poll/stream/heartbeat from timers."""

    def __init__(self, config: BridgeConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self.link = MavlinkLink(config.link, clock)
        self.shaper = SetpointShaper(config)
        self.pairing = HeadingPairing(config.heading_wait_s)
        self._reported_missing = 0
        self.hover = HoverThrust(config.configured_hover_thrust,
                                 config.hover_thrust_source == 'autopilot')
        self.autopilot: Autopilot | None = (None if config.autopilot == 'auto'
                                            else Autopilot(config.autopilot))
        self.sequencer: EngageSequencer | None = None
        self.supervisor_mode = Mode.IDLE
        self.guid_options: int | None = None
        self.rate = RateMeter()
        self.setpoint_source = SetpointSource.NONE
        # False: build the targets but send none (the node holds the stream until the IMU's
        # consumers are matched, so that a lockstep sim starts only when they hear every sample)
        self.stream_enabled = True
        self._current: AttitudeTarget | None = None
        self.time_sync = TimeSync(config.time_sync)
        self._ros_ns: int | None = None           # ROS time of the current poll (ns)
        self._setpoint_stamp_ns: int | None = None   # latest stamp of a force sent (ROS ns)
        self.imu_dropped_unsynced = 0
        self._imu_drop_reported = 0
        self._imu_drop_warned_t = -np.inf
        self.timesync_answered = 0                # the autopilot's requests we answered
        self._force_stamp_ns: int | None = None   # stamp of the latest force sent
        self._force_sent_t = -np.inf              # when (monotonic s)
        self._status_modes: dict[int, Mode] = {}  # stamp ns -> supervisor mode of that frame
        self._stream_start: float | None = None
        self._last_stream_t: float | None = None
        self._params_since: float | None = None
        self._last_param_request = -np.inf
        self._last_seen: dict[int, float] = {}
        self._last_interval_request: dict[int, float] = {}
        self._yaw_now = 0.0
        self._lin_acc_frd: np.ndarray | None = None
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
        if new == self.supervisor_mode:
            return
        self._event('info', f'supervisor mode {self.supervisor_mode.name} -> {new.name}')
        self.supervisor_mode = new
        # Engagement commands leave now, not at the next poll (before the next setpoint).
        self._run_sequencer(self._clock())

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
        return ''

    def content_mode(self, now: float) -> Mode:
        """Return the mode whose content (F, shutdown ramp, failsafe) the target carries.

        The supervisor's mode reported for the stamp of the latest force, so that e.g. the
        shutdown ramp starts on the SHUTDOWN frame itself, not on whichever setpoint follows the
        ``ibvs/mode`` message (lockstep runs then repeat to the end). Without that status, or
        once the forces stopped for ``hold_last_s`` (controller silent: the latest mode must
        still act, e.g. FAILSAFE), the latest ``ibvs/mode``.
        """
        if self._force_stamp_ns is not None \
                and now - self._force_sent_t <= self.config.hold_last_s:
            mode = self._status_modes.get(self._force_stamp_ns)
            if mode is not None:
                return mode
        return self.supervisor_mode

    def on_heading(self, stamp_ns: int, q_wxyz_enu_flu: np.ndarray) -> str:
        """ibvs/heading_setpoint of stamp_ns (base_link in map).

        Sends the force of the same stamp if it is waiting for this heading. Returns '' or the
        refusal reason (a refused heading is never flown; its force takes the latest one).
        """
        try:
            yaw: float | None = yaw_from_heading_quat(q_wxyz_enu_flu)
            reason = ''
        except ValueError as exc:
            self.shaper.rejected += 1
            yaw, reason = None, str(exc)
        self._send_forces(self.pairing.on_heading(stamp_ns, yaw))
        return reason

    def on_force(self, stamp_ns: int, F_I: np.ndarray) -> str:
        """ibvs/force_setpoint (already in {I}): send the new setpoint as soon as it is paired.

        Sent at once if the heading of the same stamp is there or none is expected, else when
        that heading arrives or ``heading_wait_s`` has passed (:class:`HeadingPairing`).
        Returns '' or why the force was refused (then the held/fallback setpoint is sent at
        once, with the new stamp, so that a lockstep sim keeps advancing).
        """
        reason = self.shaper.check_force(F_I)
        self._send_forces(self.pairing.on_force(stamp_ns, F_I, self._clock(),
                                                may_wait=not reason))
        return reason

    def release_expired(self) -> None:
        """Send a force that waited ``heading_wait_s`` in vain for its heading (timers)."""
        self._send_forces(self.pairing.expire(self._clock()))

    def pop_heading_warning(self) -> str:
        """Text about forces sent without their heading since the last call, or ''."""
        n = self.pairing.missing - self._reported_missing
        if n <= 0:
            return ''
        self._reported_missing = self.pairing.missing
        return (f'{n} force setpoint(s) sent without the heading of their stamp (waited '
                f'{self.config.heading_wait_s * MS_PER_S:.0f} ms): flown with the latest '
                f'heading ({self.pairing.missing} in all, {self.pairing.late} late headings)')

    # --- timers ------------------------------------------------------------------------
    def heartbeat(self) -> None:
        """1 Hz: our HEARTBEAT."""
        self.link.send_heartbeat()

    def stream(self) -> None:
        """>= 50 Hz: repeat the latest setpoint (recomputed for fallbacks and ramps).

        A force whose heading wait has expired is sent first.
        """
        self.release_expired()
        self._send_current(new=False)

    def poll(self, ros_ns: int | None = None) -> list[ImuSample]:
        """Receive everything pending, run the sequencer, return new IMU samples.

        ``ros_ns``: ROS time now (ns; the node's clock: system time on a vehicle, sim time in
        the sim). It is the receipt time of the TIMESYNC answers read here, the tc1 of our
        answers to the autopilot's requests and the ts1 of our requests; None or 0 (no
        ``/clock`` yet): no clock sync. Also sends a force whose heading wait has expired
        (:meth:`release_expired`).
        """
        self.release_expired()
        now = self._clock()
        self._ros_ns = None if ros_ns is None else int(ros_ns)
        samples = []
        for msg in self.link.poll():
            sample = self._handle(msg, now)
            if sample is not None:
                samples.append(sample)
        self._maybe_build_sequencer()
        self._request_timesync(now)
        self._service_requests(now)
        self._run_sequencer(now)
        return samples

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) log events since the last call: 'info', 'warn', 'error'."""
        events, self._events = self._events, []
        if self.sequencer is not None:
            events += [('info', f'engage: {e}') for e in self.sequencer.pop_events()]
        return events

    def status(self) -> BridgeStatus:
        """Diagnostics snapshot."""
        now = self._clock()
        hb = self.link.heartbeat
        seq = self.sequencer
        c = self.link.counters
        return BridgeStatus(
            link_up=self.link.link_up, heartbeat_age_s=self.link.heartbeat_age(),
            autopilot=self.autopilot.value if self.autopilot else 'unknown',
            armed=bool(hb and hb.armed), custom_mode=hb.custom_mode if hb else 0,
            engage_state=seq.state.value if seq else 'no_link',
            engage_reason=seq.last_reason if seq else '',
            supervisor_mode=self.supervisor_mode.name,
            hover_thrust=self.hover.value, hover_thrust_source=self.hover.source,
            setpoint_source=self.setpoint_source.value, setpoint_rate_hz=self.rate.rate(now),
            rejected_setpoints=self.shaper.rejected,
            counters={'received': c.received, 'sent': c.sent, 'bad_data': c.bad_data,
                      'foreign': c.foreign, 'reconnects': c.reconnects,
                      'link_losses': c.link_losses, 'send_errors': c.send_errors,
                      'heading_timeouts': self.pairing.missing,
                      'late_headings': self.pairing.late,
                      'timesync_answered': self.timesync_answered},
            time_sync=self.time_sync.status(), imu_dropped_unsynced=self.imu_dropped_unsynced)

    def close(self) -> None:
        """Close the link."""
        self.link.close()

    # --- time mapping ------------------------------------------------------------------
    def stamp_to_boot_ms(self, stamp_ns: int) -> int | None:
        """ROS stamp -> autopilot time_boot_ms (>= 0; None while the clocks are not synced)."""
        ms = self.time_sync.ros_ns_to_boot_ms(stamp_ns)
        return None if ms is None else max(0, ms)

    def _request_timesync(self, now: float) -> None:
        """Send a TIMESYNC request when the estimator wants one (link up, ROS time > 0)."""
        if not self.link.link_up:
            return
        ts1 = self.time_sync.next_request(self._ros_ns, now)
        if ts1 is not None:
            self.link.send_timesync(0, ts1)

    def _on_timesync(self, msg) -> None:
        """Answer the autopilot's request (tc1 == 0), or take the answer to one of ours."""
        tc1, ts1 = int(msg.tc1), int(msg.ts1)
        ros = self._ros_ns
        if ros is None or ros <= 0:
            return      # no ROS time yet: an answer tc1 = 0 would read as a request
        if tc1 == 0:
            if self.link.send_timesync(ros, ts1):
                self.timesync_answered += 1
        elif tc1 > 0:
            for level, text in self.time_sync.on_reply(tc1, ts1, ros):
                self._event(level, text)

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
        cfg = self.config.sequencer
        self.sequencer = EngageSequencer(SequencerConfig(
            self.autopilot, cfg.prestream_s, cfg.command_retry_s, cfg.max_attempts,
            cfg.disarm_force_after_s))

    def _handle(self, msg, now: float) -> ImuSample | None:
        kind = msg.get_type()
        if kind == 'ATTITUDE_QUATERNION':
            self._last_seen[MavMsgId.ATTITUDE_QUATERNION] = now
            return self._attitude(msg)
        if kind == 'HIGHRES_IMU':
            self._last_seen[MavMsgId.HIGHRES_IMU] = now
            acc = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float)
            if np.all(np.isfinite(acc)):
                self._lin_acc_frd = acc
        elif kind == 'TIMESYNC':
            self._on_timesync(msg)
        elif kind == 'PARAM_VALUE':
            self._param(msg.param_id, float(msg.param_value))
        elif kind == 'COMMAND_ACK':
            if self.sequencer is not None:
                self.sequencer.on_command_ack(msg.command, msg.result)
            if msg.result != 0:
                self._event('warn', f'command {msg.command} answered with result {msg.result}')
        return None

    def _attitude(self, msg) -> ImuSample | None:
        q = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=float)
        w = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if (not np.all(np.isfinite(q)) or not np.all(np.isfinite(w))
                or abs(np.linalg.norm(q) - 1.0) > QUAT_NORM_TOLERANCE):
            self._event('error', f'ATTITUDE_QUATERNION out of range (q={q}, rates={w}): '
                                 'dropped')
            return None
        self._yaw_now = euler_zyx_from_rot(rot_from_quat(q))[2]
        boot_ms = int(msg.time_boot_ms)
        for level, text in self.time_sync.on_boot_time('time_boot_ms', boot_ms * NS_PER_MS):
            self._event(level, text)
        stamp_ns = self.time_sync.boot_ms_to_ros_ns(boot_ms)
        if stamp_ns is None:
            self._imu_unsynced()
            return None
        acc = None if self._lin_acc_frd is None else vec_frd_to_flu(self._lin_acc_frd)
        return ImuSample(stamp_ns, quat_ned_frd_to_enu_flu(q), vec_frd_to_flu(w), acc)

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
        self._event('warn', f'imu/data: {n} sample(s) dropped, clock not synced with the '
                            f'autopilot yet ({why}); {self.imu_dropped_unsynced} in all')

    def _param(self, raw_name, value: float) -> None:
        name = raw_name.decode('ascii', 'replace') if isinstance(raw_name, bytes) else raw_name
        name = name.rstrip('\x00')
        if self.autopilot is not None and name == HOVER_PARAM[self.autopilot] \
                and self.hover.use_autopilot:
            self.hover.on_param(name, value)
            if self.hover.error:
                self._event('error', self.hover.error)
            else:
                self._event('info', f'hover thrust {value:.3f} from {name}')
        elif name == GUID_OPTIONS_PARAM:
            if np.isfinite(value):
                self.guid_options = int(value)

    def _params_missing(self) -> list[str]:
        missing = []
        if self.autopilot is None:
            return missing
        if self.hover.value is None:
            missing.append(HOVER_PARAM[self.autopilot])
        if self.autopilot == Autopilot.ARDUPILOT and self.guid_options is None:
            missing.append(GUID_OPTIONS_PARAM)
        return missing

    def _service_requests(self, now: float) -> None:
        """Parameter reads and message-interval requests, retried while unanswered."""
        if not self.link.link_up:
            self._params_since = None
            return
        if self._params_since is None:
            self._params_since = now
        missing = self._params_missing()
        if missing and now - self._last_param_request >= self.config.param_retry_s:
            self._last_param_request = now
            for name in missing:
                self.link.request_param(name)
        if missing and now - self._params_since >= self.config.param_timeout_s:
            self.hover.on_timeout()
        rates = {MavMsgId.ATTITUDE_QUATERNION: self.config.attitude_rate_hz,
                 MavMsgId.HIGHRES_IMU: self.config.imu_rate_hz}
        for msg_id, rate in rates.items():
            seen = self._last_seen.get(msg_id, -np.inf)
            asked = self._last_interval_request.get(msg_id, -np.inf)
            retry = self.config.interval_retry_s
            if now - seen > retry and now - asked > retry:
                self._last_interval_request[msg_id] = now
                self.link.set_message_interval(msg_id, rate)

    def _run_sequencer(self, now: float) -> None:
        if self.sequencer is None:
            return
        hb = self.link.heartbeat
        timed_out = (self._params_since is not None
                     and now - self._params_since >= self.config.param_timeout_s)
        inp = SequencerInputs(
            t=now, link_up=self.link.link_up, supervisor_mode=self.supervisor_mode,
            armed=bool(hb and hb.armed), custom_mode=hb.custom_mode if hb else 0,
            streaming_s=self._streaming_s(now), hover_thrust_ready=self.hover.value is not None,
            guid_options=self.guid_options, params_timed_out=timed_out,
            ramp_done=self.shaper.ramp_done(now))
        for req in self.sequencer.step(inp):
            self._event('info', f'command {req.command.name} {req.params}: {req.reason}')
            self.link.send_command_long(req.command, req.params)

    def _streaming_s(self, now: float) -> float:
        if self._stream_start is None:
            return 0.0
        return now - self._stream_start

    def _send_forces(self, forces: list[PairedForce]) -> None:
        """Store and send each paired force at once, in order."""
        for p in forces:
            # Before any heading: the current yaw, frozen so that repeats equal what was sent.
            self.shaper.on_force(p.t_rx, p.F_I, self._yaw_now if p.yaw is None else p.yaw)
            if self._setpoint_stamp_ns is None or p.stamp_ns > self._setpoint_stamp_ns:
                self._setpoint_stamp_ns = p.stamp_ns
            self._force_stamp_ns, self._force_sent_t = p.stamp_ns, self._clock()
            self._send_current(new=True)

    def _send_current(self, new: bool) -> None:
        """Build the target for the current mode and send it (if the link can)."""
        now = self._clock()
        hover = self.hover.value if self.hover.value is not None \
            else self.config.configured_hover_thrust
        # Every target carries the stamp of the latest controller output (0 before any), never
        # the autopilot's current time: a fallback (level hover before the first force, hold,
        # shutdown ramp) is not an answer to a newer camera frame, so the sim's lockstep keeps
        # waiting for the controller instead of running ahead of the graph. Mapped at each
        # send: a repeat sent once the clocks are synced carries the mapped value (0 before).
        stamp = self._setpoint_stamp_ns
        ms = (self.stamp_to_boot_ms(stamp) if stamp is not None else None) or 0
        t_vehicle = 0.0 if stamp is None else stamp / NS_PER_S
        target = self.shaper.target(now, self.content_mode(now), self._yaw_now, hover, ms,
                                    t_vehicle)
        if target.source == SetpointSource.HOLD_LAST and new:
            self._event('error', f'force setpoint refused ({self.shaper.last_error}): '
                                 'holding the last valid one')
        if target.source != self.setpoint_source:
            self._event('info' if target.source == SetpointSource.IBVS else 'warn',
                        f'setpoint source {self.setpoint_source.value} -> '
                        f'{target.source.value}')
            self.setpoint_source = target.source
        self._current = target
        if not self.link.link_up or not self.stream_enabled:
            self._stream_start = None
            return
        if self.link.send_attitude_target(target.time_boot_ms, target.q_wxyz, target.thrust,
                                          target.type_mask):
            self.rate.tick(now)
            if self._stream_start is None or (self._last_stream_t is not None
                                              and now - self._last_stream_t > STREAM_GAP_S):
                self._stream_start = now
            self._last_stream_t = now
