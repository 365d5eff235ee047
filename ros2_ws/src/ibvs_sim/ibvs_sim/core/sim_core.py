"""The simulation loop: one camera frame after another, paced against the wall clock.

:class:`Simulation` composes the stages of a frame: :class:`~ibvs_sim.core.physics.
PhysicsLoop` (plant, inner loop, wind, autopilot, contacts) advances one camera period in
physics substeps, the autopilot sends the telemetry due at the frame time, and
:class:`~ibvs_sim.core.cameras.CameraRig` renders both cameras at the new pose. How sim time
moves against the wall clock is the pacing (:mod:`~ibvs_sim.core.pacing`): free-running, or
in lockstep with the graph. The initial frame (t = 0) shows the initial condition; a collision
ends the run (no more frames). ROS-free; docs/sim.md "Loop, pacing and events".
"""
from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Callable

from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.cameras import CameraRig
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


class Simulation:
    """Produce camera frames from the physics, the autopilot and the cameras, paced.

    :meth:`tick` (called often by the node) produces the next frame when the pacing allows it;
    :meth:`step_frame` produces it at once. Lockstep: MAVLink input is read only between
    frames, never during a frame's physics substeps (a datagram's effect does not depend on
    when it landed during the computation); realtime: at every substep, as on a vehicle.
    """

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 autopilot: ReferenceSource, config: SimConfig,
                 wall_clock: Callable[[], float] = time.monotonic,
                 products: GraphProducts | None = None,
                 clock_sink: Callable[[int], None] | None = None) -> None:
        """Compose the parts; ``clock_sink(t_ns)``: lockstep, the clock moves first.

        ``clock_sink`` (the node's ``/clock`` publisher) is called in lockstep with a frame's
        sim time (ns) before anything of that time leaves the sim: the autopilot's telemetry
        (IMU, attitude, its own TIMESYNC requests) and answers, and the frame itself. On a
        vehicle no message of time t reaches the companion before its clock reads t
        (docs/sim.md).
        """
        self.world, self.vehicle, self.config = world, vehicle, config
        self.autopilot = autopilot
        self.wall_clock = wall_clock
        self.clock_sink = clock_sink
        self.physics = PhysicsLoop(world, vehicle, autopilot, config.wind,
                                   config.initial_position_I, config.initial_yaw)
        self.period_ns = int(round(NS_PER_S / config.camera_rate_hz))
        if self.period_ns % self.physics.dt_ns:
            raise ValueError(f'camera period {self.period_ns} ns is not a multiple of the '
                             f'physics step {self.physics.dt_ns} ns')
        self.substeps = self.period_ns // self.physics.dt_ns
        self.cameras = CameraRig(world, pad, vehicle, config.cameras, config.read_noise_std,
                                 config.noise_seed, render=config.render,
                                 parallel=config.parallel_render)
        self.frame_index = -1                # no frame produced yet
        self.events: list[SimEvent] = []
        self.ended = False
        self.realtime = RealtimeClock(config.real_time_factor, self.period_ns)
        self.lockstep = LockstepGate(config.lockstep_timeout_s,
                                     products if products is not None else GraphProducts({}))
        self._events: list[SimEvent] = []     # realtime: contacts since the last frame

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
            self.realtime.start(now, self.t_ns)
            return self._first_frame()
        if self.config.pacing is Pacing.REALTIME:
            return self._free_run(now)
        self.autopilot.poll(self.physics.state_view())
        answered = self.autopilot.last_setpoint_time_boot_ms
        answered = (answered is not None and answered >= self.last_frame_ms()) \
            or not self.autopilot.awaits_setpoints
        if self.lockstep.may_step(now, answered):
            return self.step_frame()
        return None

    def _free_run(self, now: float) -> FrameOutput | None:
        """Realtime: step physics up to the sim time of ``now``; emit a frame if one is due."""
        target = self.realtime.target(now, self.t_ns)
        while not self.ended and self.t_ns < target:
            event = self._substep(receive=True)
            if event is not None:
                self._events.append(event)
                if self.ended:          # a collision ends the run: no frame shows it
                    self.events.extend(self._events)
                    self._events = []
                    return None
            frame_ns = self.realtime.take_frame(self.t_ns)
            if frame_ns is None:
                continue
            self.autopilot.poll(self.physics.state_view())    # telemetry due at the frame time
            if self.realtime.late(target, frame_ns):           # a whole period late: drop it
                continue
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
        self.autopilot.poll(self.physics.state_view(), receive=receive)
        return self._emit(new_events)

    def _clock_moves(self) -> None:
        """Lockstep: hand the frame's sim time to ``clock_sink`` before its telemetry."""
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

    def _first_frame(self) -> FrameOutput:
        # the telemetry due at t = 0 leaves before frame 0, as before every later frame
        self._clock_moves()
        self.autopilot.poll(self.physics.state_view(),
                            receive=self.config.pacing is Pacing.REALTIME)
        return self._emit([])

    def _emit(self, new_events: list) -> FrameOutput:
        self.frame_index += 1
        self.lockstep.frame_out(self.wall_clock())
        images = self.cameras.frame(self.state.R_IB, self.state.xi_I, self.frame_index)
        self.events.extend(new_events)
        return FrameOutput(self.t_ns, images, self.state.copy(), new_events)

    def close(self) -> None:
        """Stop the render threads (idempotent; a later frame starts them again)."""
        self.cameras.close()
