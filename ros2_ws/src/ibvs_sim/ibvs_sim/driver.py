"""What the ``sim`` node does at each tick, ROS-free: frames in step with the graph, and out.

:class:`SimDriver` runs the :class:`~ibvs_sim.core.sim_core.Simulation` for the node: it holds
frame 0 until the graph is there (:class:`~ibvs_sim.core.graph_sync.FirstFrameHold`), holds
each lockstep frame until ``imu/data`` reached it
(:class:`~ibvs_sim.core.graph_sync.ImuBeforeImages`), applies the test-only camera faults,
decides when ``/clock`` goes out, expects the graph's products of each frame, and keeps the
timing figures of ``sim/stats``. The node turns what it hands to its :class:`GraphPort` into
messages and feeds it the graph's messages (:meth:`SimDriver.note_imu`, ...).
"""
from __future__ import annotations

import time
from typing import Any, Protocol

import numpy as np

from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_common.core.frame_grid import period_ns
from ibvs_common.core.modes import Mode
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.config import SimNodeConfig
from ibvs_sim.core.autopilot import Autopilot
from ibvs_sim.core.dynamics import State
from ibvs_sim.core.events import SimEvent
from ibvs_sim.core.firmware.lockstep import ardupilot_lockstep, px4_lockstep
from ibvs_sim.core.firmware.px4_hil import FirmwareLinkError
from ibvs_sim.core.firmware.relay import CompanionPort, CompanionRelay
from ibvs_sim.core.graph_sync import (FirstFrameHold, graph_products, ImuBeforeImages,
                                      STATUS_TOPIC)
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import FrameOutput, Simulation
from ibvs_sim.core.timing import AnswerLatency, NS_PER_MS, wall_budget
from ibvs_sim.core.world import WorldConfig

LOG_THROTTLE_S = 2.0
FLYING_MODES = (Mode.WINDOW, Mode.CROSSING, Mode.LANDING)   # the graph's setpoints fly
PREROLL_STEPS_PER_TICK = 100  # physics steps (0.2 s sim) of a firmware's pre-roll per tick
SUBSCRIBER_SETTLE_S = 2.0     # s (wall), image subscribers and setpoints this long before frame 0
CLOCK_REPEAT_S = 0.1          # s (wall), /clock repeated while sim time stands still: a node
#                               whose /clock subscription matched late still learns the time
FAULT_ANSWER_WAIT_S = 0.3     # s (wall), lockstep: wait for the answer to (and the products of)
#                               a frame with images off or frozen (the graph may not answer it)


class GraphPort(Protocol):
    """What the driver needs of the ROS graph (the sim node): publishers and their matches."""

    def publish_clock(self, t_ns: int) -> None:
        """Publish ``/clock`` at sim time ``t_ns``."""

    def publish_images(self, images: dict, stamps_ns: dict) -> None:
        """Publish each camera's camera_info and image (camera -> mono8 array), stamped."""

    def publish_ground_truth(self, t_ns: int, state: State) -> None:
        """Publish the ground truth of ``t_ns``."""

    def publish_event(self, event: SimEvent) -> None:
        """Publish a contact event."""

    def count_image_subscribers(self) -> dict:
        """Return camera -> the number of subscribers of its images."""

    def count_publishers(self, topic: str) -> int:
        """Return the number of publishers of ``topic``."""


class Log(Protocol):
    """The node's logger (rclpy's: ``throttle_duration_sec`` accepted)."""

    def info(self, message: str, **kwargs: Any) -> Any: ...

    def warning(self, message: str, **kwargs: Any) -> Any: ...

    def error(self, message: str, **kwargs: Any) -> Any: ...


class SimDriver:
    """Run the simulation for the sim node: holds, faults, ``/clock``, products, timing."""

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 cfg: SimNodeConfig, port: GraphPort, log: Log) -> None:
        """Build the autopilot (its MAVLink endpoint opens) and the simulation of ``cfg``.

        ``vehicle`` is the true vehicle (``true_vehicle_file``): the plant, the cameras the
        sim renders and their timing.
        """
        self.port, self.log = port, log
        sim_config = cfg.sim_config(vehicle)
        self.firmware = None
        self.radio = cfg.radio()       # the pilot's RC input (None: no RC), both autopilots
        if cfg.firmware:       # a real firmware flies the plant; the sim relays the companion
            start = (sim_config.initial_position_I if sim_config.initial_position_I is not None
                     else tuple(world.initial_position_I))
            yaw = (sim_config.initial_yaw if sim_config.initial_yaw is not None
                   else world.initial_yaw)
            instance = int(cfg.firmware_instance)
            if cfg.firmware == 'ardupilot':
                self.firmware = ardupilot_lockstep(world, vehicle, instance,
                                                   np.asarray(start, float), float(yaw),
                                                   sim_config.wind)
                port = CompanionPort.ardupilot(instance)
            else:
                self.firmware = px4_lockstep(world, vehicle, instance, np.asarray(start, float),
                                             float(yaw), sim_config.wind, int(cfg.seed),
                                             radio=self.radio)
                port = CompanionPort.px4(instance)
            self.autopilot = CompanionRelay(str(cfg.mavlink_url), instance, boot_offset_ms=0,
                                            port=port)
            if port.timesync_in_lockstep:
                self.firmware.after_substep = self.autopilot.pass_timesync
        else:
            self.autopilot = Autopilot(cfg.autopilot_config(vehicle, world.floor_z,
                                                            self.radio))
        self.products = graph_products()
        if self.firmware is not None:
            self.autopilot.graph_flies = self._graph_flies
        self.sim = Simulation(world, pad, vehicle, self.autopilot, sim_config,
                              products=self.products, clock_sink=self._clock,
                              physics=self.firmware)
        self.latency = AnswerLatency()
        self.faults = cfg.camera_faults()
        self.imu_hold = ImuBeforeImages(self.sim.config.lockstep_timeout_s,
                                        enabled=self.sim.config.pacing is Pacing.LOCKSTEP)
        self.first_frame_hold = FirstFrameHold(
            {n: cfg.min_image_subscribers for n in self.sim.config.cameras},
            SUBSCRIBER_SETTLE_S, cfg.subscriber_wait_timeout_s, time.monotonic(),
            # a firmware is frozen before frame 0 (lockstep): no stream to wait for
            need_setpoints=cfg.start_on_setpoints and not cfg.firmware)
        self._clock_ns = -1
        self._clock_wall = 0.0
        self._ended_logged = False
        self._events_published = 0
        self._first_frame_wall: float | None = None   # steady s, frame 0 published
        self._publish_wall_s = 0.0                     # perf_counter s spent publishing

    def _graph_flies(self) -> bool:
        """Whether the supervisor's latest mode flies the vehicle on the graph's setpoints."""
        statuses = self.products.statuses
        return bool(statuses) and statuses[-1][1] in FLYING_MODES

    # --- the graph's messages ---
    def note_imu(self, stamp_ns: int) -> None:
        """Note an ``imu/data`` stamp (ns, sim time)."""
        self.imu_hold.note_imu(stamp_ns)

    def note_status(self, stamp_ns: int, mode: int) -> None:
        """Note the supervisor's mode of the frame at ``stamp_ns``."""
        self.products.note_status(stamp_ns, mode)

    def note_grid(self, camera: str, stride: int, ref_ns: int, flow: bool = False) -> None:
        """Note the graph's frame grid of ``camera`` (ibvs/frame_grid; ``flow``: its flow's)."""
        timing = self.sim.config.timings().get(camera)
        if timing is not None:
            self.products.note_grid(camera, period_ns(timing.rate_hz), stride, ref_ns, flow)

    def note_product(self, topic: str, stamp_ns: int) -> None:
        """Note a product of the graph stamped ``stamp_ns``; log one given up that came back."""
        if self.products.note(topic, stamp_ns):
            self.log.info(
                f'lockstep: {topic} published again (stamp t = {stamp_ns / NS_PER_S:.3f} '
                f's, sim t = {self.sim.t:.3f} s): waited for again')

    # --- the tick ---
    def flip_pilot_switch(self, on: bool) -> str:
        """Flip the radio's mission switch now (sim time), as the pilot; '' or why not."""
        if self.radio is None:
            return 'no radio (pilot_switch_channel 0)'
        self.radio.flip(on, self.sim.t)
        return ''

    def tick(self) -> None:
        """Release what may go now, advance the simulation as the pacing allows, publish."""
        if not self.first_frame_hold.released and not self._first_frame_may_go():
            return
        held = self.imu_hold.release(time.monotonic())
        if held is not None:
            if self.imu_hold.timed_out:
                self.log.warning(
                    f'lockstep: imu/data did not reach t = {held.t:.3f} s within '
                    f'{self.imu_hold.timeout_s} s (wall): frame published without it'
                    + ('; frames are no longer held for it until it comes again'
                       if self.imu_hold.silent else ''),
                    throttle_duration_sec=LOG_THROTTLE_S)
            self._publish(held)
        if self.imu_hold.holding:
            return
        lockstep, realtime = self.sim.lockstep, self.sim.realtime
        timeouts_before, dropped_before = lockstep.timeouts, realtime.frames_dropped
        silent_before = lockstep.silent
        given_up_before = len(lockstep.given_up)
        try:
            out = self.sim.tick()
        except ValueError as exc:   # RenderError, non-finite state: stop, do not publish NaN
            self.sim.ended = True
            self.log.error(f'simulation stopped: {exc}', throttle_duration_sec=LOG_THROTTLE_S)
            return
        if lockstep.timeouts > timeouts_before:
            self.log.warning(
                f'lockstep: no setpoint answered a frame within '
                f'{self.sim.config.lockstep_timeout_s} s (wall): simulated up to '
                f't = {self.sim.t:.3f} s with the last one; {lockstep.timeouts} '
                'time-outs so far (the run no longer repeats exactly)',
                throttle_duration_sec=LOG_THROTTLE_S)
        if lockstep.silent != silent_before:
            self.log.warning(
                f'lockstep: {lockstep.silent_after} time-outs in a row: no setpoint is waited '
                f'for until one comes again (t = {self.sim.t:.3f} s; the bridge died or '
                'stopped streaming?)' if lockstep.silent else
                f'lockstep: a setpoint came again at t = {self.sim.t:.3f} s: each frame waits '
                'for its answer again')
        if len(lockstep.given_up) > given_up_before:
            self.log.warning(
                f'lockstep: {", ".join(lockstep.given_up[given_up_before:])} not '
                f'published within {lockstep.answer_wait_s} s (wall) of the frame at t = '
                f'{(self.products.frame_ns or 0) / NS_PER_S:.3f} s: no longer waited for '
                'until it comes again')
        if realtime.frames_dropped > dropped_before:
            self.log.warning(
                f'free-running: could not render on time at t = {self.sim.t:.3f} s: '
                f'{realtime.frames_dropped} frame(s) dropped so far (lower real_time_factor)',
                throttle_duration_sec=LOG_THROTTLE_S)
        answers = self.autopilot.new_setpoints
        while answers:
            self.latency.answered(*answers.popleft())
        if self.sim.config.pacing is Pacing.REALTIME or self._clock_ns >= 0:
            # free-running: /clock runs on between frames; lockstep: repeated while it waits
            self._clock(self.sim.t_ns if self.sim.config.pacing is Pacing.REALTIME
                        else self._clock_ns)
        if out is not None:
            # an injected IMU fault: imu/data will not reach the frame, do not wait for it
            if not self.autopilot.imu_fault_at(out.t):
                # every IMU sample sent by the delivery reaches the graph before the images
                imu_ms = self.autopilot.last_attitude_ms
                out.imu_ns = None if imu_ms is None else imu_ms * NS_PER_MS
                out = self.imu_hold.hold(out, time.monotonic())
            if out is not None:
                self._publish(out)
        elif self.sim.ended and not self._ended_logged:
            self._ended_logged = True
            for event in self.sim.events[self._events_published:]:
                self._event(event)
            self.log.error(
                f'run ended at t = {self.sim.t:.3f} s: '
                f'{self.sim.events[-1].to_dict() if self.sim.events else "(no event)"}')

    def _first_frame_may_go(self) -> bool:
        """Ask the hold with the subscriber counts; log the wait and a timeout.

        With a firmware, first its pre-roll: it boots, takes off and holds at the start
        (a slice of it per tick); the companion link is relayed only from then on.
        """
        if self.firmware is not None and not self.firmware.ready:
            if self.sim.ended:          # the pre-roll failed: never start the clock after it
                return False
            try:
                ready = self.firmware.preroll(PREROLL_STEPS_PER_TICK)
            except FirmwareLinkError as exc:
                self.sim.ended = True
                self.log.error(f'firmware: {exc}', throttle_duration_sec=LOG_THROTTLE_S)
                return False
            self.autopilot.discard_firmware()
            if not ready:
                self.log.info(f'frame 0 waits for the firmware: {self.firmware.status()}',
                              throttle_duration_sec=LOG_THROTTLE_S)
                return False
            self.autopilot.boot_offset_ms = self.firmware.boot_offset_ms
            self.log.info(f'firmware holds at the start: {self.firmware.status()}; sim time '
                          f'starts (the firmware clock is {self.firmware.boot_offset_ms} ms '
                          'ahead)')
        counts = self.port.count_image_subscribers()
        streaming = self.sim.poll_before_start()
        state = (f'subscribers {counts} (needed {self.first_frame_hold.min_counts}), '
                 f'setpoints streaming: {streaming}')
        if self.first_frame_hold.ready(counts, time.monotonic(), streaming):
            if self.first_frame_hold.timed_out:
                self.log.warning(f'frame 0 goes without its whole graph: {state}')
            return True
        self.log.info(f'frame 0 waits for the graph: {state}',
                      throttle_duration_sec=LOG_THROTTLE_S)
        return False

    # --- out ---
    def _clock(self, t_ns: int) -> None:
        """Publish /clock when time moved, or again after CLOCK_REPEAT_S of wall clock."""
        now = time.monotonic()
        if t_ns > self._clock_ns or (t_ns == self._clock_ns
                                     and now - self._clock_wall >= CLOCK_REPEAT_S):
            self._clock_ns, self._clock_wall = t_ns, now
            self.port.publish_clock(t_ns)

    def _publish(self, out: FrameOutput) -> None:
        t0 = time.perf_counter()
        if self._first_frame_wall is None:
            self._first_frame_wall = time.monotonic()
        try:
            self._publish_frame(out)
        finally:
            self._publish_wall_s += time.perf_counter() - t0

    def _publish_frame(self, out: FrameOutput) -> None:
        # a guard, no-op as the sim runs: the clock already moved to the frame's time
        # (lockstep: Simulation.clock_sink before the frame's telemetry; realtime: each tick)
        self._clock(out.t_ns)
        images, withheld, frozen = self.faults.apply(out.t, out.images)
        # lockstep: the graph may have nothing to answer (its mode's camera is off), or drop
        # a frozen camera's images (its products are then given up after this short wait)
        imu_fault = self.autopilot.imu_fault_at(out.t)
        self.sim.lockstep.answer_wait_s = (FAULT_ANSWER_WAIT_S if withheld or frozen
                                           or imu_fault else self.sim.config.lockstep_timeout_s)
        if imu_fault:
            self.log.warning(f'fault injection: IMU {imu_fault} at t = {out.t:.3f} s',
                             throttle_duration_sec=LOG_THROTTLE_S)
        if withheld:
            self.log.warning(f'fault injection: {", ".join(withheld)} camera off at '
                             f't = {out.t:.3f} s', throttle_duration_sec=LOG_THROTTLE_S)
        if frozen:
            self.log.warning(
                f'fault injection: {", ".join(frozen)} camera frozen at t = {out.t:.3f} s: '
                f'its image of t = {self.faults.held[frozen[0]][0]:.3f} s again, new stamp',
                throttle_duration_sec=LOG_THROTTLE_S)
        stamps = {name: out.stamp_ns(name) for name in images}
        self.port.publish_images(images, stamps)
        # the graph's answer echoes the stamp of the mode's camera (or none is owed)
        answer_ns = out.t_ns if out.answer_ns is None else out.answer_ns
        self.latency.published(answer_ns, time.monotonic(), self.products.on_grid(
            self.products.mode_camera(), answer_ns))
        self.port.publish_ground_truth(out.t_ns, out.state)
        for event in out.events:
            self._event(event)
        if self.imu_hold.enabled:
            answer = out.answer_ns
            self.products.expect(out.t_ns if answer is None else answer, list(images),
                                 {t: self.port.count_publishers(t)
                                  for t in (*self.products.products, STATUS_TOPIC)},
                                 stamps, status=answer is not None)

    def _event(self, event: SimEvent) -> None:
        self._events_published += 1
        self.port.publish_event(event)
        self.log.info(f'event: {event.to_dict()}')

    # --- sim/stats ---
    def stats(self) -> dict:
        """Return the figures of ``sim/stats``: frames, waits, latency, the wall budget.

        Also the autopilot's own TIMESYNC requests and the bridge's answers to them (checked:
        ts1 one of the requests), as PX4 asks.
        """
        sim = self.sim
        if self.firmware is not None:
            autopilot = {f'relay_{k}': v for k, v in self.autopilot.forwarded.items()}
            autopilot['relay_timesync_unanswered'] = self.autopilot.timesync_unanswered
            autopilot['firmware_exchanges'] = self.firmware.plant.exchanges
        else:
            counters = self.autopilot.counters
            autopilot = {'autopilot_timesync_requests': counters.timesync_requests_sent,
                         'autopilot_timesync_answers': counters.timesync_answers_received,
                         'autopilot_timesync_foreign': counters.timesync_answers_foreign}
        armed = self.autopilot.armed
        if armed is not None:           # the vehicle's own word, whatever the bridge says
            autopilot['autopilot_armed'] = int(bool(armed))
        return {'pacing': sim.config.pacing.value,
                'real_time_factor': sim.config.real_time_factor,
                'sim_time_s': sim.t, 'frames_dropped': sim.realtime.frames_dropped,
                'stalls': sim.realtime.stalls, 'lockstep_timeouts': sim.lockstep.timeouts,
                'products_given_up': len(sim.lockstep.given_up),
                'answer_silences': sim.lockstep.silences,
                'imu_hold_timeouts': self.imu_hold.timeouts,
                **autopilot, **self.latency.stats(),
                **self._wall_budget()}

    def _wall_budget(self) -> dict:
        """Where the wall clock went since frame 0 (:func:`~ibvs_sim.core.timing.wall_budget`)."""
        if self._first_frame_wall is None:
            return {}
        return wall_budget(time.monotonic() - self._first_frame_wall, self.latency.frames, {
            'physics': self.sim.physics.wall_s, 'render': self.sim.cameras.wall_s,
            'publish': self._publish_wall_s, 'imu_hold': self.imu_hold.held_s})

    def close(self) -> None:
        """Close the MAVLink endpoint (and a firmware's links), stop the render threads."""
        self.autopilot.close()
        if self.firmware is not None:
            self.firmware.close()
        self.sim.close()
