"""The simulation loop: plant + inner attitude loop + autopilot + cameras + contacts + wind.

Time is kept in integer nanoseconds since boot (``t_ns``), so that frame times are exact
multiples of the camera period and a frame's time in milliseconds (what the graph echoes in
SET_ATTITUDE_TARGET.time_boot_ms) is exact. One :meth:`Simulation.step_frame` advances one
camera period (20 ms at 50 Hz) in physics substeps (``PlantParams.physics_rate_hz``); at every
substep the autopilot is polled with the ground truth and its attitude reference is tracked by
the inner loop; contacts are checked at every substep; then both cameras render the new pose
and add their sensor's read noise (``read_noise_std``, :mod:`~ibvs_sim.core.sensor_noise`:
deterministic per seed, camera and frame, so that no two frames are bit-identical).
The initial frame (t = 0) shows the initial condition.

Pacing (:meth:`Simulation.tick`, called often by the node):

- ``realtime`` (free-running): sim time runs at ``real_time_factor`` x the wall clock (e.g.
  0.25 on a machine that cannot render 50 Hz in real time); physics substeps catch up with it
  at every tick, MAVLink is read at every substep, and a camera frame is rendered only if the
  sim is less than one camera period behind its due time: a frame it cannot render on time is
  dropped and counted (``frames_dropped``), never delayed or bunched. A stall of the sim
  process itself longer than ``MAX_CATCH_UP_S`` of sim time re-phases its clock (``stalls``);
- ``lockstep``: the next camera period is simulated only after the autopilot received a
  SET_ATTITUDE_TARGET whose time_boot_ms is at least the last frame's time in ms (the graph's
  answer to that frame) and the graph published every product of that frame
  (:class:`GraphProducts`), or after ``lockstep_timeout_s`` of wall clock; no answer is
  awaited once the autopilot flies a mode of its own after the offboard one (its failsafe
  land: the graph's setpoints no longer fly the vehicle, and a bridge that handed the vehicle
  back sends none: waiting would stall every frame for the time-out); meanwhile the autopilot
  is polled at the same sim time. MAVLink input is read only there, between frames, never
  during a frame's physics substeps: a datagram that lands while a frame is being computed (a
  stream repeat, a command) takes effect at the next frame boundary, not at whichever substep
  the wall clock happened to reach. Two runs of a deterministic graph give the same trajectory.

Events (ground truth, {I}): ``touchdown`` when the envelope bottom reaches the floor (vertical
speed reported), ``collision`` when the envelope touches the wall, window frame or back wall
before touchdown: the run ends there (no more frames).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
import enum
import math
import time
from typing import Callable, Collection, Protocol, Sequence

import numpy as np

from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_sim.core.world import WorldConfig
from ibvs_common.core.frames import rot_from_quat, rot_z, vec_I_to_map
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.autopilot import AttitudeReference, VehicleStateView
from ibvs_sim.core.contacts import FLOOR, min_clearance
from ibvs_sim.core.dynamics import (AttitudeController, PlantParams, QuadrotorPlant, State,
                                    Wind, WindConfig, hover_state)
from ibvs_sim.core.render import SceneRenderer
from ibvs_sim.core.sensor_noise import ReadNoise

NS_PER_MS = 1_000_000
DEFAULT_CAMERA_RATE_HZ = 50.0
MAX_CATCH_UP_S = 0.5          # s of sim time: a longer stall of the sim process re-phases it
STATUS_TOPIC = 'ibvs/supervisor_status'   # lockstep: the mode of each evaluated frame
STATUS_HISTORY = 8            # statuses kept by GraphProducts


class Pacing(str, enum.Enum):
    """How sim time advances against the wall clock."""

    REALTIME = 'realtime'
    LOCKSTEP = 'lockstep'


class EventType(str, enum.Enum):
    """Kinds of contact events."""

    COLLISION = 'collision'
    TOUCHDOWN = 'touchdown'


class ReferenceSource(Protocol):
    """What the simulation needs from the autopilot (ibvs_sim.core.autopilot.Autopilot)."""

    last_setpoint_time_boot_ms: int | None
    awaits_setpoints: bool

    def poll(self, state: VehicleStateView, receive: bool = True,
             telemetry: bool = True) -> None: ...

    def attitude_reference(self, state: VehicleStateView) -> AttitudeReference: ...

    def estimate_error(self, t: float) -> np.ndarray:
        """R_err (3x3) at sim time t: the autopilot's attitude estimate is R_IB R_err."""


@dataclass(frozen=True)
class SimConfig:
    """Simulation settings (the node builds it from its parameters)."""

    pacing: Pacing = Pacing.LOCKSTEP
    lockstep_timeout_s: float = 1.0                  # wall clock, s
    real_time_factor: float = 1.0                    # realtime: sim s per wall s, (0, 10]
    camera_rate_hz: float = DEFAULT_CAMERA_RATE_HZ   # both cameras, Hz
    initial_position_I: tuple | None = None          # m, {I}; None = world.yaml
    initial_yaw: float | None = None                 # rad; None = world.yaml
    wind: WindConfig = field(default_factory=WindConfig)
    render: bool = True                              # False: physics only (tests)
    # render the cameras of a frame at once, one thread each (OpenCV and most of numpy run
    # without the GIL; each camera has its own renderer and noise): the same images, sooner
    parallel_render: bool = True
    cameras: tuple[str, ...] = ('front', 'down')
    read_noise_std: float = 0.0                      # grey levels, camera read noise (0: off)
    noise_seed: int = 0                              # read noise draws (with camera, frame)


@dataclass
class SimEvent:
    """A contact event: collision (run ends) or touchdown."""

    type: EventType
    t: float                      # s, sim time
    surface: str                  # 'floor' | 'wall' | 'window_frame' | 'back_wall'
    position_I: np.ndarray        # m, body origin in {I}
    speed_mps: float              # touchdown: vertical speed; collision: speed

    def to_dict(self) -> dict:
        """Return the JSON object published on ``sim/events`` (position in ``map``, ENU)."""
        return {'type': self.type.value, 't': round(self.t, 6), 'surface': self.surface,
                'position_map': [round(float(x), 6) for x in vec_I_to_map(self.position_I)],
                'speed_mps': round(float(self.speed_mps), 6)}


@dataclass
class FrameOutput:
    """What one camera period produces: images at capture time t, ground truth, events."""

    t_ns: int
    images: dict                  # camera name -> (H, W) uint8, empty when rendering is off
    state: State
    events: list

    @property
    def t(self) -> float:
        """Return the capture time, seconds since boot."""
        return self.t_ns / NS_PER_S


class FirstFrameHold:
    """Whether the first frame may go: the graph is there to answer it.

    Each counted topic has its minimum number of subscribers (``min_counts``, e.g. both
    cameras' images: detector + flow (+ recorder)), so that every node sees the same frames from
    the first one on (an image published before discovery matched a subscriber is lost for it)
    and a bag replay starts its trackers where the live ones started; and, with
    ``need_setpoints``, the companion already streams setpoints, so its link is up and the IMU
    at t = 0 reaches the graph with frame 0 (the bridge starts its stream only once its
    ``imu/data`` consumers are matched, ``min_imu_subscribers``). The conditions must hold for
    ``settle_s`` (discovery completes on all sides) before the release; after ``timeout_s`` the
    frame goes anyway. Times are one monotonic clock (s); no minimum and no need_setpoints
    never holds.
    """

    def __init__(self, min_counts: dict, settle_s: float, timeout_s: float, now: float,
                 need_setpoints: bool = False) -> None:
        if any(int(c) < 0 for c in min_counts.values()) or settle_s < 0.0 \
                or not timeout_s > 0.0:
            raise ValueError(f'need counts >= 0, settle_s >= 0, timeout_s > 0; got '
                             f'{min_counts}, {settle_s}, {timeout_s}')
        self.min_counts = {k: int(c) for k, c in min_counts.items()}
        self.settle_s = float(settle_s)
        self.need_setpoints = bool(need_setpoints)
        self.deadline = now + timeout_s
        self.released = not any(self.min_counts.values()) and not need_setpoints
        self.timed_out = False
        self._since: float | None = None

    def ready(self, counts: dict, now: float, setpoints: bool = False) -> bool:
        """Update with the subscriber count per topic and whether setpoints stream.

        Return True once (and after) released.
        """
        if self.released:
            return True
        if (all(counts.get(k, 0) >= c for k, c in self.min_counts.items())
                and (setpoints or not self.need_setpoints)):
            self._since = now if self._since is None else self._since
            self.released = now - self._since >= self.settle_s
        else:
            self._since = None
            self.released = self.timed_out = now > self.deadline
        return self.released


class ImuBeforeImages:
    """Lockstep harness: hold a frame until ``imu/data`` has reached its time.

    The sim's autopilot sends the telemetry due at a frame's time before the frame is rendered
    (:meth:`Simulation.step_frame`), but it reaches the graph through MAVLink and the bridge,
    while the images go out directly: without this hold, whether a node has the IMU sample at
    the image stamp (interpolation) or only the one before (gyro propagation) would depend on
    scheduling. Before any IMU sample was seen (link or clock sync not up yet) nothing is
    held; a frame waits at most ``timeout_s`` (wall clock, s) and is then released anyway.
    Disabled (pass-through) outside lockstep.
    """

    def __init__(self, timeout_s: float, enabled: bool = True) -> None:
        if not timeout_s > 0.0:
            raise ValueError(f'timeout_s must be > 0, got {timeout_s}')
        self.timeout_s = float(timeout_s)
        self.enabled = bool(enabled)
        self.imu_through_ns: int | None = None     # newest IMU stamp seen
        self.timed_out = False
        self.timeouts = 0
        self.held_s = 0.0                          # wall s frames were held, in all
        self._held: FrameOutput | None = None
        self._since = 0.0

    @property
    def holding(self) -> bool:
        """Whether a frame is held."""
        return self._held is not None

    def note_imu(self, stamp_ns: int) -> None:
        """Note an imu/data stamp (ns, ROS clock = sim time)."""
        if self.imu_through_ns is None or stamp_ns > self.imu_through_ns:
            self.imu_through_ns = int(stamp_ns)

    def hold(self, frame: FrameOutput, now: float) -> FrameOutput | None:
        """Return the frame if it may go now, else keep it (:meth:`release` gives it later)."""
        if not self.enabled or self._covered(frame):
            return frame
        self._held, self._since = frame, now
        return None

    def release(self, now: float) -> FrameOutput | None:
        """Return the held frame once the IMU reached it or the wait timed out, else None."""
        frame = self._held
        self.timed_out = False
        if frame is None:
            return None
        if not self._covered(frame):
            if now - self._since < self.timeout_s:
                return None
            self.timed_out = True
            self.timeouts += 1
        self._held = None
        self.held_s += max(0.0, now - self._since)
        return frame

    def _covered(self, frame: FrameOutput) -> bool:
        return self.imu_through_ns is None or self.imu_through_ns >= frame.t_ns


class AnswerLatency:
    """Image -> setpoint latency of the graph, as the simulated vehicle sees it (wall clock).

    :meth:`published` notes when each frame's images left (wall s); :meth:`answered` is called
    for every SET_ATTITUDE_TARGET with a new time_boot_ms and the wall time the autopilot read
    it (``Autopilot.new_setpoints``): the published frame nearest that time, within
    ``tolerance_ms``, is answered (the bridge maps the image stamp to time_boot_ms through its
    TIMESYNC estimate: exact in lockstep, within a few ms when the clocks run), and its
    latency is the read minus the publication (the autopilot reads at each physics substep of
    a tick: resolution about the sim node's tick period). ``stamp_errors_ms`` keeps
    time_boot_ms minus the frame's time. Frames whose own answer never came count as
    unanswered.
    """

    def __init__(self, keep: int = 200, tolerance_ms: int = 9) -> None:
        self._published: dict[int, float] = {}     # frame ms -> wall s
        self._keep = int(keep)
        self.tolerance_ms = int(tolerance_ms)
        self.latencies_s: list[float] = []
        self.stamp_errors_ms: list[int] = []
        self.frames = 0
        self._last_ms: int | None = None

    def published(self, t_ns: int, wall: float) -> None:
        """Note that the frame at sim time ``t_ns`` was published at ``wall``."""
        self.frames += 1
        self._published[t_ns // NS_PER_MS] = wall
        while len(self._published) > self._keep:
            del self._published[min(self._published)]

    def answered(self, time_boot_ms: int | None, wall: float) -> None:
        """Note the newest setpoint's time_boot_ms as read at ``wall``."""
        if time_boot_ms is None or time_boot_ms == self._last_ms:
            return
        self._last_ms = time_boot_ms
        ms = int(time_boot_ms)
        near = [k for k in self._published if abs(k - ms) <= self.tolerance_ms]
        if near:
            frame_ms = min(near, key=lambda k: abs(k - ms))
            self.latencies_s.append(wall - self._published.pop(frame_ms))
            self.stamp_errors_ms.append(ms - frame_ms)

    def stats(self) -> dict:
        """Median, p95, p99, max (ms) and the fraction of published frames answered."""
        lat = np.asarray(self.latencies_s, dtype=float) * 1e3
        out = {'frames_published': self.frames, 'frames_answered': int(lat.size),
               'answered_fraction': float(lat.size / self.frames) if self.frames else 0.0}
        if lat.size:
            out.update({f'latency_{k}_ms': float(v) for k, v in (
                ('median', np.median(lat)), ('p95', np.percentile(lat, 95)),
                ('p99', np.percentile(lat, 99)), ('max', lat.max()))})
            errors = np.abs(self.stamp_errors_ms)
            out.update({'answer_stamp_error_max_ms': int(errors.max()),
                        'answer_stamp_exact_fraction': float(np.mean(errors == 0))})
        return out


def wall_budget(wall_s: float, frames: int, parts: dict) -> dict:
    """Where a run's wall clock went, per frame published (ms): the ``sim/stats`` figures.

    ``wall_s``: wall clock (s) since frame 0 was published; ``parts``: name -> wall s spent in
    it (the sim node: physics substeps, render with read noise, publish, imu_hold: a rendered
    frame waiting for imu/data in lockstep). ``graph_wait`` is the rest: the sim waiting for
    the graph's answer and products (lockstep) or for the wall clock (realtime), and its own
    ticks. Returns ``sim_wall_s`` and ``wall_<part>_ms_per_frame``; empty before any frame.
    """
    if frames <= 0 or wall_s <= 0.0:
        return {}
    parts = dict(parts)
    parts['graph_wait'] = max(0.0, wall_s - sum(parts.values()))
    return {'sim_wall_s': round(wall_s, 3),
            **{f'wall_{k}_ms_per_frame': round(v * 1e3 / frames, 3) for k, v in parts.items()}}


class GraphProducts:
    """Lockstep harness: the products the graph makes of a frame, waited for before the next.

    The graph answers a frame (SET_ATTITUDE_TARGET) once the products its mode needs are in;
    the others (the pad while CROSSING) may still be computing. In lockstep, sim time moves on
    only when, besides the answer, every product of the last frame was published
    (``products``: topic -> camera), so that no node is still computing when the next frame
    comes and runs repeat under any load. Only the cameras whose images went out are
    expected, and only topics with a publisher. A perception node computes its product only
    in the modes that use it (mode gating, ``used_in``: topic -> modes; a topic not in it is
    made in every mode): so the harness also waits for the supervisor's status of the frame
    (``ibvs/supervisor_status``, published before the answer) and expects the products the
    frame's mode uses (all of them before any status, as the nodes make them). A product or
    the status still missing when the lockstep wait ends (a dead node) is given up: not
    waited for until it is published again. Every product is stamped with its image.
    """

    def __init__(self, products: dict, used_in: dict | None = None) -> None:
        self.products = dict(products)
        self.used_in = {t: frozenset(int(m) for m in modes)
                        for t, modes in (used_in or {}).items()}
        self.newest_ns: dict[str, int] = {}
        self.given_up: set[str] = set()
        self.expected: set[str] = set()
        self.frame_ns: int | None = None
        self.status_expected = False
        self.statuses: list[tuple[int, int]] = []     # (stamp ns, mode), newest last

    def expect(self, frame_ns: int, cameras: Collection[str], publishers: dict) -> None:
        """Expect the products of the frame at ``frame_ns`` (images of ``cameras`` went out)."""
        self.frame_ns = int(frame_ns)
        self.expected = {t for t, cam in self.products.items()
                         if cam in cameras and publishers.get(t, 0) > 0
                         and t not in self.given_up}
        self.status_expected = bool(self.used_in) and publishers.get(STATUS_TOPIC, 0) > 0 \
            and STATUS_TOPIC not in self.given_up

    def note_status(self, stamp_ns: int, mode: int) -> None:
        """Note the supervisor's mode of the frame at ``stamp_ns``."""
        self.statuses = self.statuses[-(STATUS_HISTORY - 1):] + [(int(stamp_ns), int(mode))]
        self.given_up.discard(STATUS_TOPIC)

    def mode_at(self, stamp_ns: int) -> int | None:
        """Mode of the newest status stamped at or before ``stamp_ns``, or None."""
        older = [mode for t, mode in self.statuses if t <= stamp_ns]
        return older[-1] if older else None

    def note(self, topic: str, stamp_ns: int) -> bool:
        """Note a published product stamped ``stamp_ns``; return True if it was given up."""
        if stamp_ns > self.newest_ns.get(topic, -1):
            self.newest_ns[topic] = int(stamp_ns)
        back = topic in self.given_up
        self.given_up.discard(topic)
        return back

    def missing(self) -> list[str]:
        """Return the expected products of the last frame not yet published.

        The frame's status first, when one is expected; then the products its mode uses.
        """
        if self.frame_ns is None:
            return []
        if self.status_expected and not any(t >= self.frame_ns for t, _ in self.statuses):
            return [STATUS_TOPIC]
        mode = self.mode_at(self.frame_ns)
        return sorted(t for t in self.expected if self.newest_ns.get(t, -1) < self.frame_ns
                      and (mode is None or t not in self.used_in or mode in self.used_in[t]))

    def give_up(self) -> list[str]:
        """Stop waiting for the missing status and products (until they come again)."""
        gone: list[str] = []
        while (now_missing := self.missing()):
            gone += now_missing
            self.given_up.update(now_missing)
            self.expected.difference_update(now_missing)
            if STATUS_TOPIC in now_missing:
                self.status_expected = False
        return gone


def fault_windows(name: str, flat: Sequence[float] | Sequence[Sequence[float]]
                  ) -> tuple[tuple[float, float], ...]:
    """Return the (start, end) sim-time windows (s) of a sequence start, end, start, end, ...

    The sequence may be flat or of pairs. ValueError, naming ``name``, for an odd or empty
    sequence or a window with end < start.
    """
    v = np.asarray(flat, dtype=float).ravel().tolist()
    if not v or len(v) % 2:
        raise ValueError(f'{name} needs [start, end, ...] pairs, got {v}')
    windows = tuple(zip(v[0::2], v[1::2]))
    for a, b in windows:
        if not (math.isfinite(a) and math.isfinite(b) and b >= a):
            raise ValueError(f'{name} needs start <= end in each window, got [{a}, {b}]')
    return windows


class CameraFaults:
    """Fault injection on the published camera images (test harness), by sim-time windows.

    ``off_s`` and ``frozen_s`` map a camera name to its [start, end) window in sim seconds, or
    to several: a flat sequence (start, end, start, end, ...) (start == end: never). Off: the
    camera's images are withheld. Frozen: the camera keeps delivering the image of the first
    frame in the window with the new frames' stamps, as a hung camera driver that re-publishes
    its last buffer (read noise included: the very same bytes). :meth:`apply` gives each
    frame's images to publish.
    """

    def __init__(self, off_s: dict | None = None, frozen_s: dict | None = None) -> None:
        self.off_s = {k: fault_windows(k, v) for k, v in (off_s or {}).items()}
        self.frozen_s = {k: fault_windows(k, v) for k, v in (frozen_s or {}).items()}
        self.held: dict[str, tuple[float, np.ndarray]] = {}   # frozen camera -> (t, image)

    @staticmethod
    def _active(windows: tuple | None, t: float) -> bool:
        return windows is not None and any(a <= t < b for a, b in windows)

    def apply(self, t: float, images: dict) -> tuple[dict, list, list]:
        """Return (images to publish, cameras withheld, cameras frozen) of the frame at ``t``."""
        withheld = [n for n in images if self._active(self.off_s.get(n), t)]
        frozen = [n for n in images if n not in withheld
                  and self._active(self.frozen_s.get(n), t)]
        out = {}
        for name, img in images.items():
            if name in withheld:
                continue
            if name in frozen:
                img = self.held.setdefault(name, (t, img))[1]
            else:
                self.held.pop(name, None)
            out[name] = img
        return out, withheld, frozen


class Simulation:
    """Compose plant, inner loop, autopilot, renderers, contacts and wind (see module doc)."""

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 autopilot: ReferenceSource, config: SimConfig,
                 wall_clock: Callable[[], float] = time.monotonic,
                 products: GraphProducts | None = None,
                 clock_sink: Callable[[int], None] | None = None) -> None:
        """Compose the parts; ``clock_sink(t_ns)``: lockstep, the clock moves first.

        ``clock_sink`` (the node's ``/clock`` publisher) is called in lockstep with a frame's
        sim time (ns) before anything of that time leaves the sim: the autopilot's telemetry
        (IMU, attitude, its own TIMESYNC requests) and answers, and the frame itself. On a
        vehicle no message of time t reaches the companion before its clock reads t; a
        lockstep ``/clock`` published only with the images lagged the autopilot's messages
        by a frame, and the bridge's clock sync read them as a time jump (docs/sim.md).
        """
        self.world, self.vehicle, self.config = world, vehicle, config
        self.autopilot = autopilot
        self.wall_clock = wall_clock
        self.clock_sink = clock_sink
        self.params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
        self.plant = QuadrotorPlant(self.params)
        self.controller = AttitudeController(self.params)
        self.wind = Wind(config.wind)
        self.period_ns = int(round(NS_PER_S / config.camera_rate_hz))
        self.dt_ns = int(round(NS_PER_S / self.params.physics_rate_hz))
        if self.period_ns % self.dt_ns:
            raise ValueError(f'camera period {self.period_ns} ns is not a multiple of the '
                             f'physics step {self.dt_ns} ns')
        self.substeps = self.period_ns // self.dt_ns
        self.renderers = ({name: SceneRenderer(world, pad, vehicle.cameras[name])
                           for name in config.cameras} if config.render else {})
        self._render_pool = None              # parallel_render: threads of all but one camera
        self.read_noise = {name: ReadNoise(
            config.read_noise_std, (vehicle.cameras[name].model.height,
                                    vehicle.cameras[name].model.width),
            config.noise_seed, name) for name in self.renderers}
        xi0 = np.asarray(config.initial_position_I if config.initial_position_I is not None
                         else world.initial_position_I, float)
        yaw0 = world.initial_yaw if config.initial_yaw is None else float(config.initial_yaw)
        if xi0.shape != (3,) or not np.all(np.isfinite(xi0)) or not math.isfinite(yaw0):
            raise ValueError(f'invalid initial condition {xi0}, yaw {yaw0}')
        self.state = hover_state(self.params, xi0, rot_z(yaw0))
        self.t_ns = 0
        self.frame_index = -1                # no frame produced yet
        self.events: list[SimEvent] = []
        self.touched_down = False
        self.ended = False
        if not (math.isfinite(config.real_time_factor) and 0.0 < config.real_time_factor <= 10.0):
            raise ValueError(f'real_time_factor must be in (0, 10], got '
                             f'{config.real_time_factor}')
        self.lockstep_timeouts = 0
        self.products = products if products is not None else GraphProducts({})
        self.products_given_up: list[str] = []   # lockstep: products no longer waited for
        self.frames_dropped = 0               # realtime: frames not rendered on time
        self.stalls = 0                       # realtime: re-phased after a stall of the sim
        self.reference: AttitudeReference | None = None
        # wall clock (perf_counter, s) spent in the physics substeps and in rendering the
        # frames (read noise included): the sim's own share of a run (sim/stats)
        self.physics_wall_s = 0.0
        self.render_wall_s = 0.0
        self._waiting_since_wall: float | None = None
        # lockstep: wall wait for the answer to the last frame; shorter when fault injection
        # withheld some of its images (the graph may have nothing to answer)
        self.answer_wait_s = config.lockstep_timeout_s
        self._wall0 = 0.0                     # realtime: wall time at sim time _t0_ns
        self._t0_ns = 0
        self._next_frame_ns = 0               # realtime: time of the next camera frame
        self._events: list[SimEvent] = []     # realtime: contacts since the last frame

    # --- state views ---
    @property
    def t(self) -> float:
        """Return the sim time since boot, seconds."""
        return self.t_ns / NS_PER_S

    def state_view(self) -> VehicleStateView:
        """Ground truth as the autopilot sees it."""
        s = self.state
        return VehicleStateView(self.t, s.xi_I.copy(), s.v_I.copy(), s.R_IB.copy(),
                                s.Omega_B.copy(), self.plant.last_specific_force_B.copy())

    def last_frame_ms(self) -> int:
        """Time of the last published frame in whole milliseconds since boot."""
        return self.t_ns // NS_PER_MS

    # --- pacing ---
    def tick(self) -> FrameOutput | None:
        """Produce the next frame if the pacing allows it now, else None (never blocks)."""
        if self.ended:
            return None
        now = self.wall_clock()
        if self.frame_index < 0:
            self._wall0, self._t0_ns, self._next_frame_ns = now, self.t_ns, self.period_ns
            return self._first_frame()
        if self.config.pacing is Pacing.REALTIME:
            return self._free_run(now)
        self.autopilot.poll(self.state_view())
        answered = self.autopilot.last_setpoint_time_boot_ms
        answered = (answered is not None and answered >= self.last_frame_ms()) \
            or not self.autopilot.awaits_setpoints
        if answered and not self.products.missing():
            return self.step_frame()
        if now - self._waiting_since_wall >= self.answer_wait_s:
            if not answered and self.answer_wait_s >= self.config.lockstep_timeout_s:
                self.lockstep_timeouts += 1
            self.products_given_up += self.products.give_up()
            return self.step_frame()
        return None

    def sim_ns_at(self, wall: float) -> int:
        """Realtime: the sim time (ns) that the wall time ``wall`` (s) stands for."""
        return self._t0_ns + round((wall - self._wall0) * self.config.real_time_factor * NS_PER_S)

    def _free_run(self, now: float) -> FrameOutput | None:
        """Realtime: step physics up to the sim time of ``now``; emit a frame if one is due."""
        target = self.sim_ns_at(now)
        if target - self.t_ns > MAX_CATCH_UP_S * NS_PER_S:      # the sim itself stalled
            self.stalls += 1
            self._wall0, self._t0_ns = now, self.t_ns
            target = self.t_ns
        while not self.ended and self.t_ns < target:
            event = self._substep(receive=True)
            if event is not None:
                self._events.append(event)
                if self.ended:          # a collision ends the run: no frame shows it
                    self.events.extend(self._events)
                    self._events = []
                    return None
            if self.t_ns < self._next_frame_ns:
                continue
            frame_ns = self._next_frame_ns
            self._next_frame_ns += self.period_ns
            self.autopilot.poll(self.state_view())         # telemetry due at the frame time
            if target - frame_ns >= self.period_ns:          # a whole period late: drop it
                self.frames_dropped += 1
                continue
            events, self._events = self._events, []
            return self._emit(events)
        return None

    # --- simulation ---
    def _substep(self, receive: bool) -> SimEvent | None:
        """One physics step: autopilot, inner loop, plant, contacts (sets ``ended``)."""
        t0 = time.perf_counter()
        try:
            return self._physics_step(receive)
        finally:
            self.physics_wall_s += time.perf_counter() - t0

    def _physics_step(self, receive: bool) -> SimEvent | None:
        view = self.state_view()
        self.autopilot.poll(view, receive=receive)
        self.reference = self.autopilot.attitude_reference(view)
        # The autopilot's loop drives its estimate R_IB R_err to the reference R_d, so the
        # truth settles at R_d R_err^T: an estimate error is flown, as on a real autopilot.
        R_d = rot_from_quat(self.reference.q_IB_wxyz)
        cmd = self.controller.rotor_commands(
            self.state, R_d @ self.autopilot.estimate_error(self.t).T,
            self.reference.thrust_norm)
        self.state = self.plant.step(self.state, cmd, self.wind.force_I(self.t))
        self.t_ns += self.dt_ns
        event = self._check_contacts()
        if event is not None and event.type is EventType.COLLISION:
            self.ended = True
        return event

    def step_frame(self) -> FrameOutput | None:
        """Simulate one camera period and render (the initial frame first). None once ended."""
        if self.ended:
            return None
        if self.frame_index < 0:
            return self._first_frame()
        new_events = []
        # realtime: datagrams arrive at any substep, as on a vehicle; lockstep: between frames
        receive = self.config.pacing is Pacing.REALTIME
        for _ in range(self.substeps):
            event = self._substep(receive)
            if event is not None:
                new_events.append(event)
                if self.ended:
                    break
        # Telemetry due at the frame time (IMU, attitude) leaves before the frame is rendered
        # and published, as a camera-IMU synchronised vehicle delivers it: otherwise the
        # graph derotates the frame with an attitude extrapolated over a whole frame period.
        # Lockstep: the clock moves first (clock_sink).
        self._clock_moves()
        self.autopilot.poll(self.state_view(), receive=receive)
        return self._emit(new_events)

    def _clock_moves(self) -> None:
        """Lockstep: hand the frame's sim time to ``clock_sink`` before its telemetry."""
        if self.clock_sink is not None and self.config.pacing is Pacing.LOCKSTEP:
            self.clock_sink(self.t_ns)

    def poll_before_start(self) -> bool:
        """Serve the autopilot's link before frame 0; return whether setpoints stream already.

        The sim node calls it while it holds the first frame (:class:`FirstFrameHold`), so
        that the companion can connect, read parameters and start its stream meanwhile. No
        telemetry leaves yet: the IMU at t = 0 goes with frame 0, once the graph is matched
        (sent earlier, it reaches some subscribers and not others, by discovery timing).
        """
        self.autopilot.poll(self.state_view(), telemetry=False)
        return self.autopilot.last_setpoint_time_boot_ms is not None

    def _first_frame(self) -> FrameOutput:
        # the telemetry due at t = 0 leaves before frame 0, as before every later frame
        self._clock_moves()
        self.autopilot.poll(self.state_view(), receive=self.config.pacing is Pacing.REALTIME)
        return self._emit([])

    def _emit(self, new_events: list) -> FrameOutput:
        self.frame_index += 1
        self._waiting_since_wall = self.wall_clock()
        t0 = time.perf_counter()
        images = self.render_cameras(self.state.R_IB, self.state.xi_I, self.frame_index)
        self.render_wall_s += time.perf_counter() - t0
        self.events.extend(new_events)
        return FrameOutput(self.t_ns, images, self.state.copy(), new_events)

    def render_cameras(self, R_IB: np.ndarray, xi_I: np.ndarray, frame_index: int) -> dict:
        """Return every camera's image (read noise of frame ``frame_index`` added) at a pose.

        With ``parallel_render`` the cameras but the last render on worker threads while the
        last renders here; the images are the same as one after the other (each camera has its
        own renderer and noise bank, and nothing they share is written).
        """
        def one(name: str) -> np.ndarray:
            return self.read_noise[name].apply(self.renderers[name].render(R_IB, xi_I),
                                               frame_index)

        names = list(self.renderers)
        if not self.config.parallel_render or len(names) < 2:
            return {name: one(name) for name in names}
        if self._render_pool is None:
            self._render_pool = ThreadPoolExecutor(max_workers=len(names) - 1,
                                                   thread_name_prefix='render')
        futures = {name: self._render_pool.submit(one, name) for name in names[:-1]}
        last = one(names[-1])
        return {name: futures[name].result() if name in futures else last for name in names}

    def close(self) -> None:
        """Stop the render threads (idempotent; a later frame starts them again)."""
        pool, self._render_pool = self._render_pool, None
        if pool is not None:
            pool.shutdown(wait=True)

    def _check_contacts(self) -> SimEvent | None:
        if self.touched_down:
            return None
        s = self.state
        clearance, surface = min_clearance(s.xi_I, self.world, self.vehicle.envelope_radius,
                                           self.vehicle.envelope_height)
        if clearance > 0.0:
            return None
        if surface == FLOOR:
            self.touched_down = True
            # the plant's floor stops the body within the step: report the speed before it
            v_z = float(s.v_I[2]) if s.v_I[2] > 0.0 else float(self.plant.last_impact_speed)
            return SimEvent(EventType.TOUCHDOWN, self.t, surface, s.xi_I.copy(), v_z)
        return SimEvent(EventType.COLLISION, self.t, surface, s.xi_I.copy(),
                        float(np.linalg.norm(s.v_I)))
