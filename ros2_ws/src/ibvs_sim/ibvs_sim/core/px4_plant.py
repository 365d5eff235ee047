"""PX4 SIH as the plant (ROS-free): SIH parameters, ground truth -> {I}, frame pacing, contacts.

The pure parts of the ``px4-sih`` mode, where PX4 SITL with its SIH simulator is the plant and
the autopilot and the ``px4_sim`` node only renders the cameras: :func:`sih_parameters` (the
Pelican of vehicle.yaml for SIH), :func:`geodetic_to_ned` and :class:`NedToI` (PX4's frames to
{I}), :func:`hil_state_sample`, :class:`PositionFilter`, :class:`FrameClock`,
:class:`ContactWatch`, :class:`StateLink` (the ground-truth link) and :class:`MocapRelay`
(motion capture for PX4's estimator). How and why: docs/px4_sih.md.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass
import math
import os
import threading
import time
from typing import Any, Sequence

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import euler_zyx_from_rot, exp_so3, GRAVITY, rot_from_quat
from ibvs_sim.core.contacts import FLOOR, min_clearance
from ibvs_sim.core.dynamics import N_ROTORS, PlantParams, State
from ibvs_sim.core.events import EventType, SimEvent
from ibvs_sim.core.world import WorldConfig

EARTH_RADIUS_M = 6371000.0          # PX4's CONSTANTS_RADIUS_OF_EARTH (map_projection)
HIL_STATE_QUATERNION_ID = 115
MAV_CMD_SET_MESSAGE_INTERVAL = 511
#: PX4 v1.16 EKF2 on motion capture (:class:`MocapRelay`) instead of SIH's GPS, barometer and
#: magnetometer: GNSS off, vision horizontal + vertical position and yaw (EKF2_EV_CTRL bits
#: 0, 1, 3), vision as the height reference, no magnetometer heading. Measured in a 20 s
#: hold (docs/px4_sih.md): truth std 0.35 / 0.54 / 0.35 m (N / E / D) on SIH's sensors,
#: 0.15 / 0.35 / 0.09 m on mocap; heading estimate off by 0.034 rad, 0.006 rad.
MOCAP_EKF2_PARAMETERS = {'EKF2_GPS_CTRL': 0, 'EKF2_EV_CTRL': 11, 'EKF2_HGT_REF': 3,
                         'EKF2_MAG_TYPE': 5}
# PX4 SIH's default home (SIH_LOC_LAT0 / LON0 / H0, PX4 v1.16 parameters.json)
SIH_DEFAULT_HOME = (47.397742, 8.545594, 489.4)


class Px4PlantError(ValueError):
    """A configuration or a message that this mode cannot use."""


def sih_parameters(vehicle: VehicleConfig, plant: PlantParams | None = None) -> dict:
    """Return the PX4 parameters (name -> value, SI as PX4 documents them) of the Pelican.

    From vehicle.yaml: ``mass`` (SIH_MASS, kg); ``sim_plant.inertia_diag`` (SIH_IXX/IYY/IZZ,
    kg m^2, body FRD principal axes, no cross terms); ``sim_plant.rotor_thrust_max``
    (SIH_T_MAX, N per rotor: 4 x 8.22 N = 2 m g, vehicle.yaml's max_thrust_factor);
    the yaw torque limit SIH_Q_MAX = rotor_moment_constant x rotor_thrust_max (N m);
    SIH_L_ROLL = SIH_L_PITCH = arm_length sin 45 deg (X frame: half the distance between the
    left and right rotors, PX4's definition); SIH_T_TAU = the slower of the rotor time
    constants (spinning down; SIH has one); SIH_KDV = rotor_drag_coefficient (N s/m; SIH
    applies it to the whole velocity, the sim to the body-horizontal part only); and
    MPC_THR_HOVER = m g / (4 SIH_T_MAX), the hover thrust the bridge and PX4's estimator start
    from (vehicle.yaml's hover_thrust when consistent).
    """
    p = plant or PlantParams.from_vehicle(vehicle)
    t_max = float(p.rotor_thrust_max)
    if not (t_max > 0.0 and p.mass > 0.0 and np.all(p.inertia_diag > 0.0)):
        raise Px4PlantError(f'vehicle.yaml: mass, inertia and rotor_thrust_max must be > 0, '
                            f'got {p.mass}, {p.inertia_diag.tolist()}, {t_max}')
    arm = float(p.arm_length) * math.sin(math.pi / 4.0)
    hover = p.mass * GRAVITY / (N_ROTORS * t_max)
    if not 0.0 < hover < 1.0:
        raise Px4PlantError(f'the rotors cannot lift the vehicle: hover thrust {hover:.3f}')
    return {'SIH_MASS': float(p.mass),
            'SIH_IXX': float(p.inertia_diag[0]), 'SIH_IYY': float(p.inertia_diag[1]),
            'SIH_IZZ': float(p.inertia_diag[2]),
            'SIH_T_MAX': t_max, 'SIH_Q_MAX': float(p.moment_constant) * t_max,
            'SIH_L_ROLL': arm, 'SIH_L_PITCH': arm,
            'SIH_T_TAU': float(max(p.tau_up, p.tau_down)),
            'SIH_KDV': float(p.drag_coefficient),
            'MPC_THR_HOVER': round(hover, 4)}


def px4_home(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    """Return the home SIH really starts at from its SIH_LOC_LAT0 / LON0 / H0 values.

    PX4 stores parameters as float32: 47.397742 deg becomes 47.39774323 (13.6 cm north),
    8.545594 becomes 8.54559422 (1.6 cm east). Measured: PX4 SIH at rest reported 0.133 m
    north, 0.015 m east of the double-precision home.
    """
    return tuple(float(np.float32(x)) for x in (lat_deg, lon_deg, alt_m))


def geodetic_to_ned(lat_deg: float, lon_deg: float, alt_m: float,
                    home: tuple[float, float, float]) -> np.ndarray:
    """Return the NED position (m) of a geodetic point about ``home`` = (lat, lon deg, alt m).

    North / east: PX4's azimuthal equidistant projection (``map_projection_project``) on a
    sphere of EARTH_RADIUS_M; down: home altitude minus altitude.
    """
    lat0, lon0 = math.radians(home[0]), math.radians(home[1])
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    cos_d_lon = math.cos(lon - lon0)
    arg = math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * cos_d_lon
    c = math.acos(max(-1.0, min(1.0, arg)))
    k = c / math.sin(c) if abs(c) > 0.0 else 1.0
    north = k * (math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * cos_d_lon)
    east = k * math.cos(lat) * math.sin(lon - lon0)
    return np.array([north * EARTH_RADIUS_M, east * EARTH_RADIUS_M, float(home[2]) - alt_m])


@dataclass(frozen=True)
class NedToI:
    """PX4 local NED (origin at home on the ground) <-> paper frame {I}: a translation.

    ``origin_I`` is where PX4's NED origin lies in {I} (m): the take-off point's body origin
    at rest, i.e. (x0, y0, floor_z - rest_height_m).
    """

    origin_I: tuple

    @classmethod
    def from_start(cls, start_I: Sequence[float] | np.ndarray, floor_z: float,
                   rest_height_m: float) -> 'NedToI':
        """Take off below the scenario's start: its (x, y), on the floor (z = floor - rest)."""
        x, y = float(start_I[0]), float(start_I[1])
        if not all(math.isfinite(v) for v in (x, y, floor_z, rest_height_m)) \
                or rest_height_m < 0.0:
            raise Px4PlantError(f'bad start {start_I} / floor {floor_z} / rest height '
                                f'{rest_height_m}')
        return cls((x, y, float(floor_z) - float(rest_height_m)))

    def to_I(self, p_ned: np.ndarray) -> np.ndarray:
        """Return the {I} position (m) of a local NED position (m)."""
        return np.asarray(p_ned, dtype=float) + np.asarray(self.origin_I)

    def to_ned(self, xi_I: Sequence[float] | np.ndarray) -> np.ndarray:
        """Return the local NED position (m) of an {I} position (m)."""
        return np.asarray(xi_I, dtype=float) - np.asarray(self.origin_I)

    def takeoff_altitude(self, start_I: Sequence[float] | np.ndarray) -> float:
        """Return the height (m) above home of the start position ``start_I`` ({I})."""
        return float(-self.to_ned(start_I)[2])


@dataclass
class TruthSample:
    """PX4's ground truth in {I}: body origin, velocity, attitude, body FRD rates."""

    t_boot_s: float               # s, PX4 boot clock (time_usec; PX4 v1.16 SIH sends 0)
    xi_I: np.ndarray              # m
    v_I: np.ndarray               # m/s
    R_IB: np.ndarray              # body FRD -> {I}
    Omega_B: np.ndarray           # rad/s, body FRD
    p_ned_raw: np.ndarray         # m, quantised fix in local NED (before the filter)

    def state(self) -> State:
        """Return the sample as a plant State of the sim (rotor thrusts unknown: zeros)."""
        return State(self.xi_I.copy(), self.v_I.copy(), self.R_IB.copy(), self.Omega_B.copy())

    def extrapolated(self, dt_s: float) -> 'TruthSample':
        """Return the sample moved ``dt_s`` ahead (constant velocity and body rates)."""
        dt = float(dt_s)
        return TruthSample(self.t_boot_s + dt, self.xi_I + self.v_I * dt, self.v_I.copy(),
                           self.R_IB @ exp_so3(self.Omega_B * dt), self.Omega_B.copy(),
                           self.p_ned_raw.copy())


def _unit_quaternion(msg: Any) -> np.ndarray:
    """HIL_STATE_QUATERNION's attitude (w, x, y, z); Px4PlantError unless a unit quaternion."""
    q = np.asarray(msg.attitude_quaternion, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 0.01:
        raise Px4PlantError(f'HIL_STATE_QUATERNION attitude {q.tolist()} is not a unit '
                            'quaternion')
    return q


def hil_state_sample(msg: Any, home: tuple[float, float, float], frame: NedToI,
                     p_ned: np.ndarray | None = None) -> TruthSample:
    """Convert a HIL_STATE_QUATERNION (pymavlink message or same fields) to {I}.

    ``p_ned``: a filtered local NED position to use instead of the message's quantised fix.
    Raises Px4PlantError for a non-finite or non-unit attitude (bad input is not rendered).
    """
    q = _unit_quaternion(msg)
    raw = geodetic_to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3, home)
    v = np.array([msg.vx, msg.vy, msg.vz], dtype=float) * 0.01
    w = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
    p = raw if p_ned is None else np.asarray(p_ned, dtype=float)
    if not (np.all(np.isfinite(raw)) and np.all(np.isfinite(v)) and np.all(np.isfinite(w))
            and np.all(np.isfinite(p))):
        raise Px4PlantError('HIL_STATE_QUATERNION has a non-finite field')
    return TruthSample(msg.time_usec * 1e-6, frame.to_I(p), v, rot_from_quat(q), w, raw)


class PositionFilter:
    """Smooth a quantised position fix with the (finer) velocity: complementary filter.

    ``update(t_s, fix, v)``: predict with v over the time since the last update (s, the
    receipt clock: PX4 v1.16 SIH sends time_usec = 0), then move a fraction dt / tau_s of
    the way to the fix. Steady error for a constant velocity: zero; quantisation noise:
    reduced by about sqrt(dt / (2 tau)). A gap longer than ``reset_after_s`` or a step
    larger than ``reset_jump_m`` restarts at the fix. Only the ``filtered`` axes are smoothed
    (default north and east: the altitude comes in mm, and a filtered one lags the ground
    contact: measured, a 0.6 m/s touchdown reported as 0.0 because the filtered height
    reached the floor after SIH had stopped the body); the others are the fix.
    """

    def __init__(self, tau_s: float, reset_after_s: float = 0.5, reset_jump_m: float = 0.5,
                 filtered: tuple = (True, True, False)) -> None:
        if not tau_s >= 0.0:
            raise Px4PlantError(f'position filter tau must be >= 0 s, got {tau_s}')
        self.filtered = np.asarray(filtered, dtype=bool)
        self.tau_s = float(tau_s)
        self.reset_after_s = float(reset_after_s)
        self.reset_jump_m = float(reset_jump_m)
        self.p: np.ndarray | None = None
        self._t: float | None = None

    def update(self, t_s: float, fix: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return the filtered position after a fix (m) and a velocity (m/s) at ``t_s``."""
        fix = np.asarray(fix, dtype=float)
        dt = None if self._t is None else float(t_s) - self._t
        if self.p is None or dt is None or not 0.0 <= dt <= self.reset_after_s \
                or self.tau_s == 0.0:
            self.p = fix.copy()
        else:
            pred = self.p + np.asarray(v, dtype=float) * dt
            self.p = pred + min(1.0, dt / self.tau_s) * (fix - pred)
            if np.linalg.norm(self.p - fix) > self.reset_jump_m:
                self.p = fix.copy()
        self.p = np.where(self.filtered, self.p, fix)
        self._t = float(t_s)
        return self.p.copy()


class FrameClock:
    """The cameras' frame grid on the system clock (ns): due, rendered or dropped.

    ``due(now_ns)`` returns the frame time to render now, or None. A frame is due once
    ``now_ns`` reaches it; when ``now_ns`` is already a whole period past a frame, that frame
    is dropped (``dropped``) and the grid moves on: late frames are never bunched.
    """

    def __init__(self, rate_hz: float, start_ns: int) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise Px4PlantError(f'camera rate must be > 0 Hz, got {rate_hz}')
        self.period_ns = int(round(1e9 / rate_hz))
        self.next_ns = int(start_ns)
        self.dropped = 0
        self.due_count = 0

    def due(self, now_ns: int) -> int | None:
        """Return the frame time (ns) to render now, or None when none is due."""
        if now_ns < self.next_ns:
            return None
        late = (now_ns - self.next_ns) // self.period_ns      # whole periods late
        self.dropped += int(late)
        self.due_count += int(late) + 1
        frame_ns = self.next_ns + late * self.period_ns
        self.next_ns = frame_ns + self.period_ns
        return frame_ns


class ContactWatch:
    """Touchdown / collision events ({I}) from ground-truth samples.

    The vehicle starts on the floor, so nothing is reported before it has been airborne
    (floor clearance above ``airborne_m``). Touchdown: the first floor contact after that; its
    speed is the larger vertical speed of the contact sample and the one before (SIH stops the
    body at the ground within one of its steps). Collision: wall, window frame or back wall,
    before touchdown. One event of each kind at most.
    """

    def __init__(self, world: WorldConfig, envelope_radius: float, envelope_height: float,
                 airborne_m: float = 0.3) -> None:
        self.world = world
        self.radius, self.height = float(envelope_radius), float(envelope_height)
        self.airborne_m = float(airborne_m)
        self.airborne = False
        self.touched_down = False
        self.collided = False
        self._vz_before = 0.0

    def check(self, t_s: float, xi_I: np.ndarray, v_I: np.ndarray) -> SimEvent | None:
        """Return the event of this sample (time ``t_s`` on the caller's clock), if any."""
        xi, v = np.asarray(xi_I, dtype=float), np.asarray(v_I, dtype=float)
        clearance, surface = min_clearance(xi, self.world, self.radius, self.height)
        floor_clear = self.world.floor_z - (xi[2] + self.height / 2.0)
        vz_before, self._vz_before = self._vz_before, float(v[2])
        if not self.airborne:
            self.airborne = floor_clear > self.airborne_m
            return None
        if self.touched_down or clearance > 0.0:
            return None
        if surface == FLOOR:
            self.touched_down = True
            return SimEvent(EventType.TOUCHDOWN, t_s, surface, xi.copy(),
                            max(float(v[2]), vz_before))
        if self.collided:
            return None
        self.collided = True
        return SimEvent(EventType.COLLISION, t_s, surface, xi.copy(), float(np.linalg.norm(v)))


def px4_sitl_candidates(cwd: str | None = None, here: str | None = None) -> list[str]:
    """Return where ``px4-sitl`` (with its ``px4-sih`` script) is looked for, in order.

    ``$IBVS_PX4_SITL_DIR``; ``../shared/px4-sitl`` from the working directory (``make run``
    runs at the repository's top); the same next to the repository of this source file.
    """
    out = []
    env = os.environ.get('IBVS_PX4_SITL_DIR')
    if env:
        out.append(env)
    cwd = cwd or os.getcwd()
    out.append(os.path.join(os.path.dirname(os.path.abspath(cwd)), 'shared', 'px4-sitl'))
    here = here or os.path.abspath(__file__)
    parts = here.split(os.sep)
    if 'ros2_ws' in parts:
        repo = os.sep.join(parts[:parts.index('ros2_ws')])
        out.append(os.path.join(os.path.dirname(repo), 'shared', 'px4-sitl'))
    return list(dict.fromkeys(os.path.normpath(p) for p in out))


def find_px4_sitl(cwd: str | None = None, here: str | None = None) -> str:
    """Return the px4-sitl folder; raise FileNotFoundError naming where it was looked for."""
    cands = px4_sitl_candidates(cwd, here)
    for c in cands:
        if os.path.isfile(os.path.join(c, 'px4-sih')):
            return c
    raise FileNotFoundError(
        'PX4 SITL not found (looked for px4-sih in ' + ', '.join(cands) + '): the px4-sih mode '
        'needs PX4 v1.16 SITL with SIH as ../shared/px4-sitl next to the repository, or '
        'IBVS_PX4_SITL_DIR pointing at it; it is not part of the repository')


RATE_SLACK = 0.9      # a sample this fraction of the relay's period after the last one is sent
#                       (samples come at SIH's period with jitter: 100 Hz -> 50 Hz, not 33)


class MocapRelay:
    """The ground truth back to PX4 as motion capture: VISION_POSITION_ESTIMATE, EKF origin.

    :meth:`on_sample` takes each HIL_STATE_QUATERNION and, at about ``rate_hz`` (steady
    clock, :data:`RATE_SLACK`), sends its pose: PX4's local NED about ``home``
    (:func:`geodetic_to_ned`, PX4's own projection; the origin set below is home, so PX4's
    local frame is this one) and the ZYX
    Euler angles of its attitude (body FRD -> NED), ``usec`` 0: no TIMESYNC on that link, so
    PX4 stamps it at receipt. EKF2 with GPS off has no global origin: SET_GPS_GLOBAL_ORIGIN =
    home goes with it once a second for the first ``origin_for_s`` (PX4's take-off and
    position hold need a global position). A sample that is not a pose (non-finite, not a
    unit quaternion) is not sent. ``mav``: pymavlink's ``conn.mav``.
    """

    ORIGIN_PERIOD_S = 1.0

    def __init__(self, home: tuple[float, float, float], rate_hz: float,
                 origin_for_s: float = 10.0) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise Px4PlantError(f'mocap rate must be > 0 Hz, got {rate_hz}')
        self.home = tuple(float(x) for x in home)
        self.period_s = 1.0 / float(rate_hz)
        self.origin_for_s = float(origin_for_s)
        self.sent = 0
        self._first: float | None = None
        self._last = -math.inf
        self._origin_at = -math.inf

    def pose(self, msg: Any) -> tuple[np.ndarray, tuple[float, float, float]]:
        """Return (NED position m about home, (roll, pitch, yaw) rad) of a sample."""
        R_NB = rot_from_quat(_unit_quaternion(msg))
        p = geodetic_to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3, self.home)
        if not np.all(np.isfinite(p)):
            raise Px4PlantError('HIL_STATE_QUATERNION has a non-finite position')
        return p, euler_zyx_from_rot(R_NB)

    def on_sample(self, mav: Any, msg: Any, target_system: int, now_steady_s: float) -> None:
        """Send the sample's pose when due (and the origin, early on) through ``mav``."""
        if self._first is None:
            self._first = now_steady_s
        if now_steady_s - self._first <= self.origin_for_s \
                and now_steady_s - self._origin_at >= self.ORIGIN_PERIOD_S:
            self._origin_at = now_steady_s
            mav.set_gps_global_origin_send(int(target_system), int(round(self.home[0] * 1e7)),
                                           int(round(self.home[1] * 1e7)),
                                           int(round(self.home[2] * 1e3)))
        if now_steady_s - self._last < RATE_SLACK * self.period_s:
            return
        try:
            p, (roll, pitch, yaw) = self.pose(msg)
        except (Px4PlantError, AttributeError, TypeError, ValueError):
            return
        self._last = now_steady_s
        mav.vision_position_estimate_send(0, *(float(v) for v in p), roll, pitch, yaw)
        self.sent += 1


class StateLink:
    """SIH's ground-truth endpoint: receive HIL_STATE_QUATERNION, ask for its rate (UDP).

    ``url``: where SIH sends (``udpin:127.0.0.1:<19410 + i>``). SET_MESSAGE_INTERVAL goes back
    on the same socket, i.e. to the PX4 mavlink instance that streams it (the address the
    datagrams came from), every ``request_period_s`` (steady clock) until ``rate_hz`` is seen.
    Each message is stamped with the system time of its receipt (ns). ``threaded``: a reader
    thread waits on the socket and stamps a datagram as it arrives (the node's tick renders
    for 20-30 ms on a loaded machine: read from the tick, a sample would be stamped that
    much late, and a frame drawn from an older pose than its stamp says); otherwise
    :meth:`poll` reads and stamps.
    """

    READ_WAIT_S = 0.05          # s (steady), the reader thread looks at its stop flag this often

    def __init__(self, url: str, rate_hz: float, request_period_s: float = 1.0,
                 threaded: bool = False, relay: MocapRelay | None = None) -> None:
        from ibvs_common.core.mavlink_connection import open_mavlink   # pymavlink only when used
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise Px4PlantError(f'state rate must be > 0 Hz, got {rate_hz}')
        self.rate_hz = float(rate_hz)
        self.request_period_s = float(request_period_s)
        self.conn = open_mavlink(url, source_system=255, source_component=191)
        self.relay = relay                  # motion capture for PX4, sent as samples arrive
        self._asked_at = -math.inf
        self._times: list[float] = []       # steady s of the last received samples
        self.received = 0
        self.requests = 0
        self.target: tuple[int, int] | None = None   # PX4's (system, component): MAV_SYS_ID
        #                                              is 1 + instance in SITL, so learnt
        self._queue: collections.deque = collections.deque()
        self._stop = threading.Event()
        self._thread = None
        if threaded:
            self._thread = threading.Thread(target=self._read_loop, name='px4_state_link',
                                            daemon=True)
            self._thread.start()

    def measured_rate_hz(self) -> float:
        """Return the rate of the last samples (Hz, steady clock), 0 before two."""
        t = self._times
        return (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0

    def _receive(self, blocking: bool) -> bool:
        """Read one datagram's message; queue it stamped if it is ours; False when none."""
        try:
            m = self.conn.recv_match(blocking=blocking, timeout=self.READ_WAIT_S)
        except (OSError, ValueError):      # a malformed datagram: skipped
            return True
        if m is None:
            return False
        receipt_ns, now = time.time_ns(), time.monotonic()
        if m.get_type() == 'HIL_STATE_QUATERNION':
            self.target = (m.get_srcSystem(), m.get_srcComponent())
            self._queue.append((m, receipt_ns))
            self.received += 1
            if self.relay is not None:
                self.relay.on_sample(self.conn.mav, m, self.target[0], now)
            self._times = (self._times + [now])[-50:]
        self._maybe_request(now)
        return True

    def _maybe_request(self, now_steady_s: float) -> None:
        if (self.received and self.measured_rate_hz() < 0.8 * self.rate_hz
                and now_steady_s - self._asked_at >= self.request_period_s):
            self._asked_at = now_steady_s
            self.requests += 1
            self.conn.mav.command_long_send(*self.target, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                            HIL_STATE_QUATERNION_ID, 1e6 / self.rate_hz,
                                            0, 0, 0, 0, 0)

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._receive(blocking=True)
            except Exception:      # noqa: BLE001  a reader that dies would freeze the cameras
                time.sleep(self.READ_WAIT_S)

    def poll(self) -> list:
        """Return the (HIL_STATE_QUATERNION, receipt ns on the system clock) since the last call.

        Never blocks; reads the socket itself when not threaded.
        """
        if self._thread is None:
            while self._receive(blocking=False):
                pass
        out = []
        while self._queue:
            out.append(self._queue.popleft())
        return out

    @property
    def local_port(self) -> int | None:
        """UDP port the link listens on (the kernel's pick for ``udpin:HOST:0``)."""
        from ibvs_common.core.mavlink_connection import local_port
        return local_port(self.conn)

    def close(self) -> None:
        """Stop the reader thread, close the socket."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * self.READ_WAIT_S + 1.0)
        self.conn.close()
