"""The simulation loop: physics step after step, camera frames delivered when they are due, paced.

:class:`Simulation` composes the stages: :class:`~ibvs_sim.core.physics.PhysicsLoop` (plant,
inner loop, wind, autopilot, contacts) advances in physics steps; as it passes a camera
exposure, :class:`~ibvs_sim.core.capture.FrameCapture` renders it (:class:`~ibvs_sim.core.
cameras.CameraRig`); when sim time reaches a frame's delivery time (its stamp plus the
camera's latency: :mod:`~ibvs_sim.core.camera_model`), the autopilot sends the telemetry due
then and the frame goes out. How sim time moves against the wall clock is the pacing
(:mod:`~ibvs_sim.core.pacing`): free-running, or in lockstep with the graph, which then waits
at each delivery. The first frame (t = 0) shows the initial condition; a collision ends the
run. ROS-free; docs/sim.md "Loop, pacing and events", "Camera model".
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable

from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.camera_model import CameraTiming, frame_clocks, PlannedFrame
from ibvs_sim.core.cameras import CameraRig
from ibvs_sim.core.capture import FrameCapture, Pose
from ibvs_sim.core.dynamics import State, WindConfig
from ibvs_sim.core.events import EventType, SimEvent
from ibvs_sim.core.graph_sync import GraphProducts
from ibvs_sim.core.pacing import LockstepGate, Pacing, RealtimeClock
from ibvs_sim.core.physics import PhysicsLoop, ReferenceSource
from ibvs_sim.core.timing import NS_PER_MS
from ibvs_sim.core.world import WorldConfig

DEFAULT_CAMERA_RATE_HZ = 50.0


@dataclass(frozen=True)
class SimConfig:
    """Simulation settings (the node builds it from its parameters)."""

    pacing: Pacing = Pacing.LOCKSTEP
    lockstep_timeout_s: float = 1.0                  # wall clock, s
    real_time_factor: float = 1.0                    # realtime: sim s per wall s, (0, 10]
    camera_rate_hz: float = DEFAULT_CAMERA_RATE_HZ   # both cameras, Hz (no camera_timing)
    initial_position_I: tuple | None = None          # m, {I}; None = world.yaml
    initial_yaw: float | None = None                 # rad; None = world.yaml
    wind: WindConfig = field(default_factory=WindConfig)
    render: bool = True                              # False: physics only (tests)
    # render the cameras of a frame at once, one thread each (OpenCV and most of numpy run
    # without the GIL; each camera has its own renderer and noise): the same images, sooner
    parallel_render: bool = True
    cameras: tuple[str, ...] = ('front', 'down')
    read_noise_std: float = 0.0                      # grey levels, camera read noise (0: off)
    noise_seed: int = 0                              # read noise, delivery jitter and drops
    # camera -> its timing (camera_model.CameraTiming); None: ideal cameras at camera_rate_hz
    camera_timing: dict | None = None

    def timings(self) -> dict[str, CameraTiming]:
        """Return each camera's timing (an ideal camera at ``camera_rate_hz`` by default)."""
        if self.camera_timing is None:
            return {name: CameraTiming(rate_hz=self.camera_rate_hz) for name in self.cameras}
        return {name: self.camera_timing[name] for name in self.cameras}


@dataclass
class FrameOutput:
    """One delivery: the images published at sim time t, their stamps, ground truth, events.

    ``stamps_ns``: camera -> its image's stamp (exposure instant minus the camera's time
    offset; a camera not in it: ``t_ns``). ``answer_ns``: the stamp of the image of the camera
    the graph's mode is evaluated on, i.e. the frame the graph owes an answer (None: that
    image did not go out). ``imu_ns``: the newest IMU stamp that must reach the graph before
    the images (lockstep; None: ``t_ns``).
    """

    t_ns: int
    images: dict                  # camera name -> (H, W) uint8, empty when rendering is off
    state: State
    events: list
    stamps_ns: dict = field(default_factory=dict)
    answer_ns: int | None = None
    imu_ns: int | None = None

    @property
    def t(self) -> float:
        """Return the delivery (publication) time, seconds since boot."""
        return self.t_ns / NS_PER_S

    def stamp_ns(self, camera: str) -> int:
        """Return the stamp (ns) of ``camera``'s image."""
        return self.stamps_ns.get(camera, self.t_ns)


class Simulation:
    """Produce camera deliveries from the physics, the autopilot and the cameras, paced.

    :meth:`tick` (called often by the node) produces the next delivery when the pacing allows
    it; :meth:`step_frame` produces it at once. Lockstep: MAVLink input is read only between
    deliveries, never during the physics steps before one (a datagram's effect does not
    depend on when it landed during the computation); realtime: at every step, as on a
    vehicle.
    """

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 autopilot: ReferenceSource, config: SimConfig,
                 wall_clock: Callable[[], float] = time.monotonic,
                 products: GraphProducts | None = None,
                 clock_sink: Callable[[int], None] | None = None,
                 physics: PhysicsLoop | None = None) -> None:
        """Compose the parts; ``clock_sink(t_ns)``: lockstep, the clock moves first.

        ``vehicle`` is the true vehicle (plant, camera mounts, intrinsics). ``clock_sink``
        (the node's ``/clock`` publisher) is called in lockstep with a delivery's sim time
        (ns) before anything of that time leaves the sim: the autopilot's telemetry (IMU,
        attitude, its own TIMESYNC requests) and answers, and the images. On a vehicle no
        message of time t reaches the companion before its clock reads t (docs/sim.md).
        ``physics``: the plant and its autopilot when not the sim's own (a real firmware in
        lockstep: :class:`~ibvs_sim.core.firmware.lockstep.FirmwarePhysics`).
        """
        self.world, self.vehicle, self.config = world, vehicle, config
        self.autopilot = autopilot
        self.wall_clock = wall_clock
        self.clock_sink = clock_sink
        self.physics = physics or PhysicsLoop(world, vehicle, autopilot, config.wind,
                                              config.initial_position_I, config.initial_yaw)
        self.clocks = frame_clocks(config.timings(), self.physics.dt_ns, config.noise_seed)
        self.period_ns = min(clock.period_ns for clock in self.clocks)
        self.substeps = max(1, self.period_ns // self.physics.dt_ns)   # per period, about
        self.cameras = CameraRig(world, pad, vehicle, config.cameras, config.read_noise_std,
                                 config.noise_seed, render=config.render,
                                 parallel=config.parallel_render)
        self.capture = FrameCapture(self.clocks, self.cameras)
        self.frame_index = -1                # deliveries so far - 1
        self.events: list[SimEvent] = []
        self.ended = False
        self.realtime = RealtimeClock(config.real_time_factor)
        self.lockstep = LockstepGate(config.lockstep_timeout_s,
                                     products if products is not None else GraphProducts({}))
        self.answer_ms: int | None = None    # lockstep: the stamp (ms) the graph answers next
        self._answer_ns: int | None = None   # ... in ns, and the stamps of its delivery
        self._delivered_ns: dict = {}
        self._started = False
        self._pose = Pose(self.t_ns, self.state.R_IB, self.state.xi_I)   # before a step
        self._events: list[SimEvent] = []     # realtime: contacts since the last delivery

    # --- state views ---
    @property
    def t_ns(self) -> int:
        """Return the sim time since boot, integer nanoseconds."""
        return self.physics.t_ns

    @property
    def t(self) -> float:
        """Return the sim time since boot, seconds."""
        return self.physics.t

    @property
    def state(self) -> State:
        """Return the ground truth."""
        return self.physics.state

    # --- pacing ---
    def tick(self) -> FrameOutput | None:
        """Produce the next delivery if the pacing allows it now, else None (never blocks)."""
        if self.ended:
            return None
        now = self.wall_clock()
        if not self._started:
            self.realtime.start(now, self.t_ns)
            return self._first_frame()
        if self.config.pacing is Pacing.REALTIME:
            return self._free_run(now)
        self.autopilot.poll(self.physics.state_view())
        answer = self.autopilot.last_setpoint_time_boot_ms      # ms, the stamp it answers
        answered = self.answer_ms is None \
            or (answer is not None and answer >= self.answer_ms) \
            or not self.autopilot.awaits_setpoints \
            or self.lockstep.products.handed_over(self._answer_ns, self._delivered_ns) \
            or self.lockstep.products.off_grid(self._answer_ns)
        if self.lockstep.may_step(now, answered, answer):
            return self.step_frame()
        return None

    def _free_run(self, now: float) -> FrameOutput | None:
        """Realtime: step physics up to the sim time of ``now``; emit a delivery if one is due."""
        target = self.realtime.target(now, self.t_ns)

        def late(frame: PlannedFrame, period_ns: int) -> bool:     # a whole period late
            return self.realtime.late(target, frame.instant_ns, period_ns)

        while not self.ended and self.t_ns < target:
            before, event = self._step(receive=True)
            if event is not None:
                self._events.append(event)
                if self.ended:          # a collision ends the run: no frame shows it
                    self.events.extend(self._events)
                    self._events = []
                    return None
            due = self._delivery_due()
            if due:
                self.autopilot.poll(self.physics.state_view())   # telemetry due then
            self.capture.expose(before, self._pose, late)
            if due and self.capture.has_due(self.t_ns):        # unless dropped as late
                events, self._events = self._events, []
                return self._emit(events)
        return None

    # --- simulation ---
    def _substep(self, receive: bool) -> SimEvent | None:
        """One physics step (:meth:`PhysicsLoop.substep`); a collision sets ``ended``."""
        event = self.physics.substep(receive)
        if event is not None and event.type is EventType.COLLISION:
            self.ended = True
        return event

    def _step(self, receive: bool) -> tuple[Pose, SimEvent | None]:
        """One physics step; return the pose before it (for the exposures it passed), an event.

        The caller renders the exposures (:meth:`FrameCapture.expose`) after the telemetry of
        a delivery due at the new time, as before every delivery: the IMU sample of a frame's
        time leaves before its render, so it reaches every node before the images.
        """
        before = self._pose
        event = self._substep(receive)
        self._pose = Pose(self.t_ns, self.state.R_IB, self.state.xi_I)
        return before, event

    def _delivery_due(self) -> bool:
        """Whether a frame (captured, or exposed by now) is to be delivered at the time now."""
        due = self.capture.next_delivery_ns()
        return due is not None and due <= self.t_ns

    def step_frame(self) -> FrameOutput | None:
        """Simulate up to the next delivery and return it (the first one first). None once ended.

        Physics runs on between a frame's exposure and its delivery, and later frames may be
        exposed before an earlier one is delivered (a latency longer than the period).
        """
        if self.ended:
            return None
        if not self._started:
            return self._first_frame()
        new_events = []
        # realtime: datagrams arrive at any step, as on a vehicle; lockstep: between deliveries
        receive = self.config.pacing is Pacing.REALTIME
        while True:
            before, event = self._step(receive)
            if event is not None:
                new_events.append(event)
            if self.ended or self._delivery_due():
                break
            self.capture.expose(before, self._pose)
        # Telemetry due at the delivery time (IMU, attitude) leaves before the images are
        # rendered and published, as a camera-IMU synchronised vehicle delivers it: otherwise
        # the graph derotates the frame with an attitude extrapolated over a whole frame
        # period. Lockstep: the clock moves first (clock_sink).
        self._clock_moves()
        self.autopilot.poll(self.physics.state_view(), receive=receive)
        if not self.ended:
            self.capture.expose(before, self._pose)
        return self._emit(new_events)

    def _clock_moves(self) -> None:
        """Lockstep: hand the delivery's sim time to ``clock_sink`` before its telemetry."""
        if self.clock_sink is not None and self.config.pacing is Pacing.LOCKSTEP:
            self.clock_sink(self.t_ns)

    def poll_before_start(self) -> bool:
        """Serve the autopilot's link before frame 0; return whether setpoints stream already.

        The sim node calls it while it holds the first frame
        (:class:`~ibvs_sim.core.graph_sync.FirstFrameHold`), so that the companion can
        connect, read parameters and start its stream meanwhile. No telemetry leaves yet: the
        IMU at t = 0 goes with frame 0, once the graph is matched (sent earlier, it reaches
        some subscribers and not others, by discovery timing).
        """
        self.autopilot.poll(self.physics.state_view(), telemetry=False)
        return self.autopilot.last_setpoint_time_boot_ms is not None

    def _first_frame(self) -> FrameOutput | None:
        """Start at t = 0: its telemetry and exposures, its delivery or (lockstep) the first."""
        self._started = True
        # the pose of t = 0 (a firmware's pre-roll moved the vehicle since the construction)
        self._pose = Pose(self.t_ns, self.state.R_IB, self.state.xi_I)
        # the telemetry due at t = 0 leaves before frame 0, as before every later delivery
        self._clock_moves()
        self.autopilot.poll(self.physics.state_view(),
                            receive=self.config.pacing is Pacing.REALTIME)
        self.capture.expose(self._pose, self._pose)
        if self.capture.has_due(self.t_ns):
            return self._emit([])
        if self.config.pacing is Pacing.REALTIME:
            return None                 # frame 0 goes out when sim time reaches it
        return self.step_frame()        # nothing out at t = 0: nothing to wait for

    def _emit(self, new_events: list) -> FrameOutput:
        """Return the frames due now as one delivery; note the answer the graph owes."""
        images, stamps = {}, {}
        for frame in self.capture.take_due(self.t_ns):
            images.update(frame.images)
            stamps.update({c: frame.plan.stamps_ns[c] for c in frame.plan.cameras})
        self.frame_index += 1
        self.lockstep.frame_out(self.wall_clock())
        answer_ns = stamps.get(self.lockstep.products.mode_camera())
        self.answer_ms = None if answer_ns is None else answer_ns // NS_PER_MS
        self._answer_ns, self._delivered_ns = answer_ns, stamps
        self.events.extend(new_events)
        return FrameOutput(self.t_ns, images, self.state.copy(), new_events, stamps, answer_ns)

    def close(self) -> None:
        """Stop the render threads (idempotent; a later frame starts them again)."""
        self.cameras.close()
