"""Setpoints of the MAVLink bridge: force / heading pairing and SET_ATTITUDE_TARGET shaping.

ROS-free, no I/O: :class:`HeadingPairing` flies each force with the heading of its own stamp;
:class:`SetpointShaper` turns a force into an attitude and a thrust, with the content of the
supervisor's mode (hold, level hover, the SHUTDOWN ramp of :class:`ShutdownRamp`, the level
hold while the land mode is asked for). Details: docs/mavlink.md, "Setpoint".
"""
from __future__ import annotations

from collections import deque, OrderedDict
from dataclasses import dataclass
from enum import Enum

import numpy as np

from ibvs_control.core.attitude import attitude_from_force, shutdown_thrust_scale
from ibvs_control.mavlink.safety import silence_s
from ibvs_common.core.frames import (
    euler_zyx_from_rot, GRAVITY, quat_from_rot, R_IB_from_rot_map_base, rot_from_quat, rot_z)
from ibvs_common.core.modes import Mode

ATTITUDE_TARGET_IGNORE_BODY_RATES = 7   # type_mask bits 0-2: roll, pitch, yaw rate ignored
QUAT_NORM_TOLERANCE = 0.1               # heading |q| in [0.9, 1.1], else refused
HEADING_BUFFER_LEN = 8                  # headings kept by stamp, and sent stamps remembered
RAMP_STALL_S = 1.0          # s (wall) without newer setpoint stamps before the ramp uses the wall


class SetpointSource(Enum):
    """Where the content of the setpoint being streamed comes from."""

    NONE = 'none'                   # nothing sent yet
    IBVS = 'ibvs'                   # the force controller's F and heading
    HOLD_LAST = 'hold_last'         # bad or missing input: the last valid IBVS setpoint, held
    LEVEL_HOVER = 'level_hover'     # not engaged, no valid input for hold_last_s
    LEVEL_HOLD = 'level_hold'       # until the autopilot's land mode shows
    SHUTDOWN_RAMP = 'shutdown_ramp'  # supervisor SHUTDOWN: thrust ramp to 0


@dataclass(frozen=True)
class ShaperConfig:
    """Vehicle and shaping settings (vehicle.yaml + node parameters)."""

    mass: float                     # kg
    max_thrust_factor: float        # max thrust / (m g)
    max_force_factor: float = 3.0   # |F| above factor * m g is out of range
    max_tilt_rad: float = 0.6       # tilt limit of the thrust direction
    hold_last_s: float = 0.25       # s of vehicle time a valid setpoint is kept
    shutdown_ramp_s: float = 2.0    # SHUTDOWN: thrust ramp time to 0 (vehicle time)
    max_force_age_s: float = 0.25   # s (ROS clock), a force of an older image is refused; 0 off

    def __post_init__(self):
        for name in ('mass', 'max_thrust_factor', 'max_force_factor', 'max_tilt_rad',
                     'hold_last_s', 'shutdown_ramp_s'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        if not (np.isfinite(self.max_force_age_s) and self.max_force_age_s >= 0.0):
            raise ValueError(f'max_force_age_s must be finite and >= 0, got '
                             f'{self.max_force_age_s}')


@dataclass(frozen=True)
class AttitudeTarget:
    """Content of one SET_ATTITUDE_TARGET."""

    time_boot_ms: int
    q_wxyz: np.ndarray              # body FRD in local NED, unit, (w, x, y, z)
    thrust: float                   # normalised [0, 1]
    source: SetpointSource
    type_mask: int = ATTITUDE_TARGET_IGNORE_BODY_RATES


def yaw_from_heading_quat(q_wxyz_enu_flu: np.ndarray) -> float:
    """NED yaw (rad) of a heading quaternion (base_link in map, w x y z).

    Raises ValueError if the quaternion is non-finite or not unit within 10 %.
    """
    q = np.asarray(q_wxyz_enu_flu, dtype=float)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(n - 1.0) > QUAT_NORM_TOLERANCE:
        raise ValueError(f'heading quaternion {q!r} is not a unit quaternion')
    return euler_zyx_from_rot(R_IB_from_rot_map_base(rot_from_quat(q)))[2]


@dataclass(frozen=True)
class PairedForce:
    """A force to fly now, with the heading it is flown with."""

    stamp_ns: int                   # the force's stamp (ROS time, ns)
    F_I: np.ndarray                 # N, {I}
    yaw: float | None               # NED yaw to fly; None: no heading yet (the current yaw)
    paired: bool                    # True: the heading of the same stamp


class HeadingPairing:
    """Pairs each force with the heading of the same stamp, without waiting (see module doc)."""

    def __init__(self, buffer_len: int = HEADING_BUFFER_LEN) -> None:
        self.latest_yaw: float | None = None    # latest valid heading received (NED yaw)
        self.late = 0                           # headings that came after their force
        self.missing = 0                        # forces flown without their stamp's heading
        self._headings: OrderedDict[int, float | None] = OrderedDict()  # None: refused
        self._sent: deque = deque(maxlen=buffer_len)    # stamps of forces already flown
        self._buffer_len = buffer_len

    def on_heading(self, stamp_ns: int, yaw: float | None) -> None:
        """Heading of stamp_ns (NED yaw, or None if it was refused as invalid)."""
        stamp_ns = int(stamp_ns)
        if stamp_ns in self._sent:
            self.late += 1
        else:
            self._headings[stamp_ns] = yaw
            self._headings.move_to_end(stamp_ns)
            while len(self._headings) > self._buffer_len:
                self._headings.popitem(last=False)
        if yaw is not None:
            self.latest_yaw = float(yaw)

    def on_force(self, stamp_ns: int, F_I: np.ndarray) -> PairedForce:
        """Force of stamp_ns: the heading of the same stamp if it came, else the latest."""
        stamp_ns = int(stamp_ns)
        F = np.asarray(F_I, dtype=float).copy()
        self._sent.append(stamp_ns)
        if stamp_ns in self._headings:
            yaw = self._headings.pop(stamp_ns)
            if yaw is not None:
                return PairedForce(stamp_ns, F, yaw, True)
        self.missing += 1
        return PairedForce(stamp_ns, F, self.latest_yaw, False)


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


@dataclass(frozen=True)
class _Valid:
    t: float                         # vehicle time of receipt (s)
    q: np.ndarray
    thrust: float


class SetpointShaper:
    """Turns (mode, latest valid force/heading, attitude) into the attitude target to send."""

    def __init__(self, config: ShaperConfig) -> None:
        self.config = config
        self.tilt_boost_by_autopilot = False    # True: send F_z (ArduPilot ATC_ANGLE_BOOST=1)
        self.rejected = 0
        self.stale = 0                          # of them: forces of images too old (age)
        self.last_error = ''
        self._valid: _Valid | None = None
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

    def force_target(self, F_I: np.ndarray, yaw: float, hover: float) -> tuple[np.ndarray, float]:
        """(q, thrust) of a usable force flown with NED ``yaw`` at hover thrust ``hover``."""
        c = self.config
        sp = attitude_from_force(F_I, yaw, c.mass, hover, c.max_thrust_factor, c.max_tilt_rad)
        thrust = sp.thrust_norm
        if self.tilt_boost_by_autopilot:
            thrust *= float(sp.R_IB_des[2, 2])     # cos(tilt): the vertical component
        return sp.q_IB_wxyz, float(np.clip(thrust, 0.0, 1.0))

    def check_age(self, t: float, stamp_t: float | None) -> str:
        """Return '' for a force answering an image of ``stamp_t`` received at ``t``, else why.

        Both on the ROS clock (s): system time onboard, sim time in the sim, where lockstep
        stops the clock while the graph computes (an age of 0). A force computed from an image
        older than ``max_force_age_s`` is refused: a graph that falls behind (an overloaded
        onboard computer queues its frames) must not fly old images. With the default equal
        to ``hold_last_s``, such a force is older than anything the hold itself would fly.
        """
        limit = self.config.max_force_age_s
        if limit <= 0.0 or stamp_t is None or stamp_t <= 0.0 or t - stamp_t <= limit:
            return ''
        return (f'force of an image {1e3 * (t - stamp_t):.0f} ms old (max_force_age_s '
                f'{1e3 * limit:.0f} ms): the graph falls behind')

    def on_force(self, t: float, F_I: np.ndarray, yaw: float, hover: float,
                 stamp_t: float | None = None) -> str:
        """Store a force received at vehicle time t (s) with its yaw; compute its content once.

        ``stamp_t``: the stamp (s, ROS clock) of the image the force answers (None: unknown,
        no age check). Returns '' or the refusal reason (a refused force keeps the last valid
        one).
        """
        stale = self.check_age(t, stamp_t)
        reason = stale or self.check_force(F_I)
        self._last_refused = bool(reason)
        if reason:
            self.rejected += 1
            self.stale += bool(stale)
            self.last_error = reason
            return reason
        q, thrust = self.force_target(F_I, yaw, hover)
        self._valid = _Valid(float(t), q, thrust)
        return ''

    def ramp_done(self, t_wall: float) -> bool:
        """Whether the SHUTDOWN ramp has reached zero thrust (t_wall: monotonic s)."""
        return (self._ramp is not None and shutdown_thrust_scale(
            self._ramp.elapsed(t_wall), self.config.shutdown_ramp_s) <= 0.0)

    def target(self, now: float | None, mode: Mode, yaw_now: float, hover: float,
               time_boot_ms: int, t_stamp: float, t_wall: float, engaged: bool = False,
               level_hold: bool = False) -> AttitudeTarget:
        """Return the attitude target for supervisor ``mode``.

        ``now``: vehicle time (ROS clock, s; None: unknown, the last valid force is kept);
        ``yaw_now``: current NED yaw (level setpoints keep it); ``hover``: hover thrust;
        ``time_boot_ms``: what the target carries; ``t_stamp``: the latest force's stamp (s,
        the shutdown ramp's clock); ``t_wall``: monotonic s (ramp stall); ``engaged``: the
        IBVS setpoints fly the vehicle (a stale force is then held, never replaced by a hover:
        the safety policy acts); ``level_hold``: the autopilot's land mode is being asked for.
        """
        level_q = quat_from_rot(rot_z(yaw_now))
        if mode == Mode.SHUTDOWN and not level_hold:
            if self._ramp is None:      # never above hover: held level, more would climb
                start = hover if self._last_thrust is None else min(self._last_thrust, hover)
                self._ramp = ShutdownRamp(start, t_stamp, t_wall)
            self._ramp.advance(t_stamp, t_wall)
            scale = shutdown_thrust_scale(self._ramp.elapsed(t_wall), self.config.shutdown_ramp_s)
            return self._out(time_boot_ms, level_q, self._ramp.start_thrust * scale,
                             SetpointSource.SHUTDOWN_RAMP)
        if mode != Mode.SHUTDOWN:
            self._ramp = None
        if level_hold or mode == Mode.FAILSAFE:
            return self._out(time_boot_ms, level_q, hover, SetpointSource.LEVEL_HOLD)
        v = self._valid
        hold = self.config.hold_last_s       # a clock stepped back by more: not fresh either
        fresh = v is not None and (now is None or silence_s(now, v.t, hold) <= hold)
        if v is not None and (fresh or engaged):
            stale = self._last_refused or not fresh
            return self._out(time_boot_ms, v.q, v.thrust,
                             SetpointSource.HOLD_LAST if stale else SetpointSource.IBVS)
        return self._out(time_boot_ms, level_q, hover, SetpointSource.LEVEL_HOVER)

    def _out(self, time_boot_ms: int, q: np.ndarray, thrust: float,
             source: SetpointSource) -> AttitudeTarget:
        thrust = float(np.clip(thrust, 0.0, 1.0))
        self._last_thrust = thrust
        return AttitudeTarget(int(time_boot_ms), np.asarray(q, dtype=float), thrust, source)


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
