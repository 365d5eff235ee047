"""mode_supervisor: the flight-mode state machine on ROS (docs/spec.md section 3).

Thin ROS wrapper of :class:`~ibvs_control.core.supervisor.ModeSupervisor` on the timing layer
(core/timing.py; docs/design.md "Time"): the mode is evaluated frame by frame on its camera's
frames, each once the products its mode needs are in, or skipped at its deadline. It chooses
the frame stride the graph can hold (core/rate_governor.py), publishes ``ibvs/mode``, one
``ibvs/supervisor_status`` per evaluated frame (its mode and stride) and its frame counts on
``/diagnostics``, and serves ``ibvs/start`` and ``ibvs/abort``. ``ibvs/start`` is refused
while the latest preflight verdict (``ibvs/preflight``) is no-go, unless
``require_preflight_go`` is false (:class:`~ibvs_control.core.preflight_gate.PreflightGate`).
The pilot's mission switch (``ibvs/pilot_input``, from the bridge) starts and aborts as these
services do (:mod:`ibvs_control.core.pilot_input`).
At start it publishes the cameras' mounts on ``/tf_static`` (``publish_camera_tf``;
:mod:`ibvs_control.camera_tf`).
"""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rclpy.node import Node

from sensor_msgs.msg import Imu
from std_msgs.msg import Header, UInt8
from std_srvs.srv import Trigger

from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
from ibvs_common.core.frames import bearings_C_to_I
from ibvs_common.core.frame_grid import period_ns
from ibvs_common.core.lever_arm import camera_bearings_from_body, has_lever_arm
from ibvs_common.core.modes import (
    CAMERA_OF, Camera, FLOW_OF, FLYING_MODES, InputKind, Mode, MODE_INPUTS)
from ibvs_control.camera_tf import publish_camera_tf
from ibvs_control.config import ModeSupervisorNodeConfig
from ibvs_control.core.frame_inputs import unpack_pad
from ibvs_control.core.frame_stats import FrameStats
from ibvs_control.core.pilot_input import PilotAction, PilotInputWatch
from ibvs_control.core.preflight_gate import PreflightGate
from ibvs_control.core.rate_governor import RateGovernor, SupersededFrames, SupervisorGrids
from ibvs_control.core.supervisor import ModeSupervisor
from ibvs_common.core.attitude_buffer import AttitudeBuffer
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_control.core.timing import Frame, FrameAssembler
from ibvs_control.product_subscriptions import FrameProductSubscriptions
from ibvs_common.node_common import (
    COMMAND_QOS, DeadlineTimer, frame_grid_msg, held_key, imu_attitude, LateImuReport, MODE_QOS,
    NS_PER_S,
    PREFLIGHT_TOPIC, preflight_verdict, SENSOR_QOS, superseded_from_msg, SUPERSEDED_TOPIC,
    supervisor_status_msg)
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog
from ibvs_common.waiting_messages import take_waiting

LOG_THROTTLE_S = 2.0
DIAGNOSTICS_PERIOD_S = 1.0          # s (ROS clock) between /diagnostics
DIAGNOSTICS_NAME = 'mode_supervisor: frames'


class ModeSupervisorNode(Node):
    """ROS side of the mode supervisor."""

    def __init__(self, node_name: str = 'mode_supervisor',
                 imu_local: IntraProcessTopic | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, ModeSupervisorNodeConfig)
        vehicle = load_vehicle(cfg.vehicle_file or None)
        pad = load_pad_layout(cfg.pad_layout_file or None)
        window = load_window_layout(cfg.window_layout_file or None)
        config = cfg.supervisor_config(window.width, pad)
        self._core = ModeSupervisor(config)
        self._R_BC = {name: vehicle.cameras[name].R_BC for name in ('front', 'down')}
        self._t_BC = {name: vehicle.cameras[name].t_BC for name in ('front', 'down')}
        self._front_model = vehicle.cameras['front'].model    # the corners' image border margin
        self._attitudes = AttitudeBuffer(cfg.imu)
        self._late_imu = LateImuReport(self.log, LOG_THROTTLE_S)
        # frames of the current mode's camera wait for the products that mode needs
        self._frames = FrameAssembler(cfg.frame_deadline_s, self._needed)
        self._governor = RateGovernor(cfg.governor)
        self._lead_ns = int(round(cfg.governor.stride_down_lead_s * NS_PER_S))
        self._rate_hz = {cam: vehicle.cameras[cam.value].rate_hz for cam in Camera}
        self._grids = SupervisorGrids({cam: period_ns(rate) for cam, rate in
                                       self._rate_hz.items()})
        self._stats = FrameStats()
        self._superseded = SupersededFrames()   # grid images the perception nodes skipped
        self._newest_ns = 0                     # newest frame stamp released
        self._last_opened: tuple | None = None  # ((mode, camera, stride, ref), stamp) opened
        self._clock_watch = BackstepWatch()    # the node clock, read in every callback
        self._n_reported = 0
        self._published: Mode | None = None
        self._preflight = PreflightGate(cfg.require_preflight_go, cfg.preflight_max_age_s)
        self._pilot = PilotInputWatch()

        self._mode_pub = self.create_publisher(UInt8, 'ibvs/mode', MODE_QOS)
        self._status_pub = self.create_publisher(DiagnosticArray, 'ibvs/supervisor_status',
                                                 COMMAND_QOS)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                      COMMAND_QOS)
        self._grid_pub = self.create_publisher(DiagnosticArray, 'ibvs/frame_grid', MODE_QOS)
        # in process (composed), the IMU samples are taken at the start of every callback
        self._imu = subscribe(self, Imu, 'imu/data', self._on_imu, SENSOR_QOS, imu_local)
        self._products = FrameProductSubscriptions(self, self._add)
        # the images the perception nodes skipped for newer ones: a gap is the computer's
        self._superseded_sub = self.create_subscription(Header, SUPERSEDED_TOPIC,
                                                        self._on_superseded, COMMAND_QOS)
        # the preflight's verdict (latched; only ibvs/start reads it)
        self.create_subscription(DiagnosticArray, PREFLIGHT_TOPIC, self._on_preflight, MODE_QOS)
        # the pilot's mission switch, as the bridge reads it (latched)
        self.create_subscription(UInt8, 'ibvs/pilot_input', self._on_pilot_input, MODE_QOS)
        self.create_service(Trigger, 'ibvs/start', self._on_start)
        self.create_service(Trigger, 'ibvs/abort', self._on_abort)
        self.create_timer(1.0 / cfg.update_rate_hz, self._on_timer)   # node clock
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)   # node clock
        self._publish_grid()
        self._deadline = DeadlineTimer(self, self._on_deadline)
        self._publish_mode()
        # the cameras' mounts for RViz and Foxglove (latched, once)
        self._tf_static = (publish_camera_tf(self, vehicle.cameras.values())
                           if cfg.publish_camera_tf else None)
        self.get_logger().info(f'mode supervisor ready in {self._core.mode.name}: {config}')

    # --- helpers ---------------------------------------------------------------------------
    def _now_ns(self) -> int:
        """Return the node clock (ns), watched for a step back (:meth:`_on_clock_step`)."""
        now_ns = self.get_clock().now().nanoseconds
        back_ns = self._clock_watch.observe(now_ns)
        if back_ns:
            self._on_clock_step(now_ns, back_ns)
        return now_ns

    def _now(self) -> float:
        return self._now_ns() / NS_PER_S

    def _on_clock_step(self, now_ns: int, back_ns: int) -> None:
        """Drop frames and IMU history after a step back of the clock; the core sets the mode."""
        self.log.error(f'the ROS clock went back by {back_ns / NS_PER_S:.3f} s (a step of the '
                       'system clock?): frames and IMU history dropped, every input missing '
                       'until it comes again', LOG_THROTTLE_S)
        self._frames.reset()
        self._grids.reset()
        self._superseded.clear()
        self._publish_grid()
        self._attitudes.clear()
        self._deadline.arm(None)
        if self._core.clock_stepped_back(now_ns / NS_PER_S, back_ns / NS_PER_S):
            self._publish_mode()
            self._publish_status(now_ns)

    def _error(self, text: str) -> None:
        self.log.error(text, LOG_THROTTLE_S)

    def _publish_mode(self) -> None:
        """Log the core's new transitions and publish the mode when it changed."""
        for tr in self._core.transitions[self._n_reported:]:
            self.get_logger().info(f'mode {tr.from_mode.name} -> {tr.to_mode.name} at '
                                   f't = {tr.t:.3f} s: {tr.reason}')
        self._n_reported = len(self._core.transitions)
        if self._core.mode != self._published:
            self._published = self._core.mode
            self._mode_pub.publish(UInt8(data=int(self._core.mode)))

    def _to_I(self, bearings_C: np.ndarray | None, stamp_ns: int, camera: str,
              groups: tuple = ()) -> tuple[bool, np.ndarray | None]:
        """Derotate bearings to {I} with the attitude at the stamp: (usable?, bearings or None).

        With the camera's lever arm (vehicle.yaml t_BC) they are re-taken from the body origin
        (lever_arm.py: the window's plane from its known width, the pad's from its groups).
        """
        if bearings_C is None:
            return True, None
        R_IB = self._attitudes.attitude_at(stamp_ns / NS_PER_S)
        if R_IB is None:
            self._error(f'no IMU attitude at {stamp_ns / NS_PER_S:.3f} s: cannot derotate '
                        f'the {camera} bearings (taken as not detected)')
            return False, None
        p_I = bearings_C_to_I(bearings_C, R_IB, self._R_BC[camera])
        if not has_lever_arm(self._t_BC[camera]):
            return True, p_I
        cfg = self._core.config
        return True, camera_bearings_from_body(camera, p_I, R_IB @ self._t_BC[camera], cfg.r_w,
                                               cfg.group_half_sides, groups)

    def _needed(self, camera) -> frozenset:
        """Products a frame of ``camera`` waits for in the current mode (none: other camera)."""
        inputs = MODE_INPUTS[self._core.mode]
        return inputs.needed if camera == inputs.camera else frozenset()

    def _held_flows(self, camera: Camera, stamp_ns: int) -> dict:
        """Return the flow a frame of ``camera`` holds from an earlier frame (flows shed), or {}.

        While the governor sheds the flows, a frame off the flow grid takes the flow of the
        newest flow frame before it (SupervisorGrids.flow_source_ns), matched within half a
        period (camera stamps jitter).
        """
        source_ns = self._grids.flow_source_ns(camera, stamp_ns)
        half_ns = self._grids.period_ns(camera) // 2
        if abs(source_ns - stamp_ns) <= half_ns or FLOW_OF[camera] not in self._needed(camera):
            return {}
        return {FLOW_OF[camera]: (source_ns - half_ns, source_ns + half_ns)}

    # --- inputs ----------------------------------------------------------------------------
    def _on_imu(self, msg: Imu) -> None:
        self._now_ns()                         # watch the clock between frames too
        try:
            stamp_ns, q_map_base, omega_B = imu_attitude(msg)
            if self._attitudes.add_map_base(stamp_ns / NS_PER_S, q_map_base, omega_B):
                self.log.warning('imu/data stamps went back (a clock step): IMU history '
                                 'dropped', LOG_THROTTLE_S)
        except ValueError as exc:
            self._error(f'imu/data refused: {exc}')
            return
        self._late_imu.check(self._attitudes)
        self._core.on_imu(stamp_ns / NS_PER_S)
        self._release()

    def _on_superseded(self, msg: Header) -> None:
        """Note a grid image a perception node skipped for a newer one (ibvs/frames_superseded)."""
        name, stamp_ns = superseded_from_msg(msg)
        try:
            camera = Camera(name)
        except ValueError:
            self._error(f'{SUPERSEDED_TOPIC} refused: unknown camera {name!r}')
            return
        self._superseded.note(camera, stamp_ns)

    def _add(self, kind: InputKind, stamp_ns: int, value, err: str) -> None:
        """Route one product: into its frame, or to the core at once (see the module doc)."""
        self._imu.take()
        if err:
            self._error(f'{kind.value} refused: {err}')
        now_ns = self._now_ns()
        steps = self._frames.clock_steps
        if not self._frames.add_input(kind, stamp_ns, value):
            self.log.warning(f'duplicate {kind.value} at {stamp_ns} ns: dropped', LOG_THROTTLE_S)
            return
        if self._frames.clock_steps != steps:
            self.log.warning(f'{kind.value} stamps went back (a clock step): pending frames '
                             'dropped', LOG_THROTTLE_S)
        camera = CAMERA_OF[kind]
        if camera != MODE_INPUTS[self._core.mode].camera:
            self._feed(kind, stamp_ns, value)        # the other camera: on arrival
            self._release()
            return
        self._core.product_seen(kind.value, stamp_ns / NS_PER_S)   # its node is alive
        if self._frames.was_skipped(stamp_ns):       # never applied to a frame it missed
            self._stats.late_dropped += 1
            self.log.warning(f'{kind.value} of t = {stamp_ns / NS_PER_S:.3f} s came after its '
                             'frame was skipped: dropped', LOG_THROTTLE_S)
        elif not self._frames.is_pending(stamp_ns):
            self._new_frame(kind, camera, stamp_ns, value, now_ns)
        self._release()

    def _new_frame(self, kind: InputKind, camera: Camera, stamp_ns: int, value,
                   now_ns: int) -> None:
        """Open the frame of a product of the mode's camera (if on the grid and not done)."""
        level = (self._governor.stride, self._governor.flow_stride)
        if (self._grids.stride(camera), self._grids.flow_stride(camera)) != level:
            self._grids.set_stride(camera, level[0], stamp_ns, self._lead_ns, level[1],
                                   first_frame=True)
            self._publish_grid()                     # the mode's camera changed
        if not self._grids.on_grid(camera, stamp_ns):
            self._stats.off_grid_dropped += 1        # a frame the graph does not compute now
        elif self._frames.open(stamp_ns, camera, now_ns, self._held_flows(camera, stamp_ns)):
            self._stats.opened(camera.value, stamp_ns, now_ns)
            self._count_missed(camera, stamp_ns)
        else:
            self._feed(kind, stamp_ns, value)        # its frame was evaluated: after it

    def _on_deadline(self) -> None:
        self._imu.take()
        self._products.take_waiting()     # products that came, queued behind other callbacks
        self._release()

    def _release(self) -> None:
        """Evaluate the frames that are complete or past their deadline; re-arm the timer."""
        if not self._frames.has_pending:      # most calls: an IMU sample between frames
            return
        for frame in self._frames.release(self._now_ns()):
            self._evaluate(frame)
        self._deadline.arm(self._frames.next_deadline_ns())

    # --- evaluation ------------------------------------------------------------------------
    def _feed(self, kind: InputKind, stamp_ns: int, value) -> None:
        """Give one product to the core (converted to {I})."""
        t = stamp_ns / NS_PER_S
        if kind == InputKind.WINDOW:
            ok, corners_I = self._to_I(value, stamp_ns, 'front')
            if ok:
                # only WINDOW judges a loss: the margin is computed there only
                margin = self._front_model.border_margin_px(value) \
                    if corners_I is not None and self._core.mode == Mode.WINDOW else None
                self._core.on_window(t, corners_I, margin)
        elif kind == InputKind.PAD:
            landmarks_C, groups, weights = unpack_pad(value)
            groups = groups or ()
            ok, landmarks_I = self._to_I(landmarks_C, stamp_ns, 'down', tuple(groups))
            if ok:
                self._core.on_pad(t, landmarks_I, list(groups), weights)
            if ok and landmarks_I is not None and self._core.mode == Mode.CROSSING:
                travel, needed = self._core.crossing_progress
                self.log.info(f'pad seen in CROSSING at {t:.3f} s: floor-flow travel '
                              f'{travel:.3f} of {needed if needed is None else round(needed, 3)}'
                              ' to the window plane plus the margin', LOG_THROTTLE_S)
        elif value is not None:
            self._core.on_flow(t, 'front' if kind == InputKind.FLOW_FRONT else 'down', value)

    def _evaluate(self, frame: Frame) -> None:
        """Give a released frame's needed products to the core in a fixed order, close it.

        Its other products of the same camera (``frame.extras``) are given after the close,
        as if they had arrived after the release: they count from the next frame on, whatever
        the order in which they arrived (e.g. the pad seen in CROSSING).
        """
        t = frame.stamp_ns / NS_PER_S
        extras = [(k, v) for k, v in frame.extras.items() if CAMERA_OF[k] == frame.tag]
        if frame.tag != MODE_INPUTS[self._core.mode].camera:
            for kind, value in extras:  # the mode moved to the other camera: products only
                self._feed(kind, frame.stamp_ns, value)
            return
        if not frame.complete:
            self._skip(frame)
            return
        for kind, value in frame.inputs.items():      # timing.EVALUATION_ORDER
            self._feed(kind, frame.stamp_ns, value)
        self._observe_rate(frame)
        self._core.end_frame(t)
        if self._core.crossing_note:
            self.get_logger().info(self._core.crossing_note)
            self._core.crossing_note = ''
        if self._core.window_loss_note:
            self.log.warning(self._core.window_loss_note, LOG_THROTTLE_S)
            self._core.window_loss_note = ''
        if self._core.auto_start_refusal:
            self._error(f'auto-start refused: {self._core.auto_start_refusal}')
        if self._core.start_refusal:
            self._error(f'ibvs/start dropped: {self._core.start_refusal}')
        self._publish_mode()
        self._publish_status(frame.stamp_ns, frame.tag, frame.held)
        for kind, value in extras:
            self._feed(kind, frame.stamp_ns, value)

    def _skip(self, frame: Frame) -> None:
        """Skip a frame without a product its mode needs: count it, maybe FAILSAFE."""
        t = frame.stamp_ns / NS_PER_S
        missing = tuple(k.value for k in frame.missing)
        self._stats.frame(frame.stamp_ns, missing)
        self._newest_ns = max(self._newest_ns, frame.stamp_ns)
        self.log.warning(f'frame {t:.3f} s skipped: no {", ".join(missing)} by its deadline '
                         f'(late or lost); {self._stats.skipped} skipped in all', LOG_THROTTLE_S)
        self._governor_step(frame, complete=False)
        if self._core.frame_skipped(t, missing):
            self._publish_mode()
            self._publish_status(frame.stamp_ns)

    def _observe_rate(self, frame: Frame) -> None:
        """Count a complete frame and let the governor see it."""
        self._stats.frame(frame.stamp_ns)
        self._newest_ns = max(self._newest_ns, frame.stamp_ns)
        self._governor_step(frame, complete=True,
                            lag_s=(self._now_ns() - frame.stamp_ns) / NS_PER_S)

    def _count_missed(self, camera: Camera, stamp_ns: int) -> None:
        """Count the grid frames before this one that no product came for: skipped too.

        A graph that falls behind skips images for the newest (latest only): their frames
        never open, and without them the governor saw only complete frames and kept a stride
        the computer could not hold (a sixth of a core: one frame in six computed at stride 1,
        the trackers lost across the gaps). Counted within one mode, camera and grid only; the
        first of a gap is not given to the governor (a node one image behind skips one), nor a
        frame no node reported skipping (``ibvs/frames_superseded``): the camera never
        delivered it (a dropout is no want of CPU; ``frames_undelivered``). At every frame,
        when the governor's next step sheds the flows, the first of a gap counts too
        (``RateGovernor.counts_lone_skips``).
        """
        key = (self._core.mode, camera, self._grids.stride(camera), self._grids.ref_ns(camera))
        last = self._last_opened if self._last_opened and self._last_opened[0] == key else None
        self._last_opened = (key, stamp_ns)
        if last is None or stamp_ns <= last[1]:
            return
        step = self._grids.stride(camera) * self._grids.period_ns(camera)
        missed = (stamp_ns - last[1] + step // 2) // step - 1
        self._stats.missed += max(missed, 0)
        # a lone missed frame (a node skipped one image for the next) costs that frame, as a
        # lone skipped one does (unless the next step sheds the flows); each further one in
        # the gap counts as skipped
        if missed <= 0:
            return
        for msg in take_waiting(self._superseded_sub):     # reports queued behind this product
            self._on_superseded(msg)
        tolerance_ns = self._grids.period_ns(camera) // 2
        self._stats.undelivered += missed - self._superseded.count_in_gap(
            camera, last[1], step, missed, tolerance_ns)
        first = 1 if self._governor.counts_lone_skips else 2   # lone ones: to shed the flows
        for k in range(first, min(missed, self._governor.config.stride_window_frames) + 1):
            if not self._superseded.reported(camera, last[1] + k * step, tolerance_ns):
                continue                # never delivered: not the computer's doing
            if self._governor_at(camera, last[1] + k * step, complete=False):
                break                   # a new grid: the frames after it count on it

    def _governor_step(self, frame: Frame, complete: bool, lag_s: float | None = None) -> None:
        self._governor_at(frame.tag, frame.stamp_ns, complete, lag_s)

    def _governor_at(self, camera: Camera, stamp_ns: int, complete: bool,
                     lag_s: float | None = None) -> bool:
        """Let the governor see a frame of ``camera``; apply and publish a new stride (True)."""
        level = self._governor.observe(stamp_ns / NS_PER_S, complete, lag_s,
                                       1.0 / self._rate_hz[camera], camera)
        if level is None:
            return False
        old = (self._grids.stride(camera), self._grids.flow_stride(camera))
        self._grids.set_stride(camera, level.stride, stamp_ns, self._lead_ns, level.flow_stride)
        self._publish_grid()
        rate = self._rate_hz[camera] / level.stride
        self.get_logger().info(
            f'frame stride {old[0]} -> {level.stride}, flow stride {old[1]} -> '
            f'{level.flow_stride} at t = {stamp_ns / NS_PER_S:.3f} s: the {camera.value} '
            f'camera\'s every {level.stride}. frame ({rate:.1f} Hz), its flow on every '
            f'{level.flow_stride}. of them ({rate / level.flow_stride:.1f} Hz) '
            f'({self._governor.reason})')
        return True

    def _publish_status(self, stamp_ns: int, camera: Camera | None = None,
                        held: dict | None = None) -> None:
        """Publish the mode of frame ``stamp_ns`` (``camera``: its camera) or of a time.

        ``held``: kind -> the stamp of a product the frame took from an earlier frame (flows
        shed): the controller answers the frame with the same one.
        """
        mode = self._core.mode
        level = DiagnosticStatus.WARN if mode == Mode.FAILSAFE else DiagnosticStatus.OK
        height = self._core.height_estimate
        values = {'pad_height_estimate_m': 'none' if height is None else f'{height:.4f}'}
        values.update({held_key(kind.value): str(int(src)) for kind, src in (held or {}).items()})
        self._status_pub.publish(supervisor_status_msg(
            stamp_ns, int(mode), mode.name, level, values,
            None if camera is None else camera.value))

    def _publish_grid(self) -> None:
        """Publish each camera's frame grid (stride, reference frame) on ibvs/frame_grid.

        The core's constants counted in computed frames follow the front camera's grid.
        """
        front = Camera.FRONT
        self._core.frame_period_s = (self._grids.stride(front)
                                     * self._grids.period_ns(front) / NS_PER_S)
        self._grid_pub.publish(frame_grid_msg(
            {cam.value: (self._grids.stride(cam), self._grids.ref_ns(cam),
                         self._grids.flow_grid(cam).stride, self._grids.flow_grid(cam).ref_ns)
             for cam in Camera},
            self.get_clock().now().nanoseconds))

    def _publish_diagnostics(self) -> None:
        """Publish the frame counts, the control rate held and the stride on /diagnostics."""
        camera = MODE_INPUTS[self._core.mode].camera
        flow_stride = self._grids.flow_stride(camera)
        values = self._stats.values(self._newest_ns, self._grids.stride(camera), camera.value,
                                    flow_stride)
        degraded = int(values['frames_skipped_last_s']) > 0 or self._grids.stride(camera) > 1 \
            or flow_stride > 1
        shed = f', its flow on every {flow_stride}. of them' if flow_stride > 1 else ''
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if degraded else DiagnosticStatus.OK,
            name=DIAGNOSTICS_NAME, hardware_id='companion computer',
            message=(f"{values['control_rate_hz']} Hz held, every {values['frame_stride']}. "
                     f"{camera.value} frame{shed}, {values['frames_skipped_last_s']} skipped "
                     'in the last second'),
            values=[KeyValue(key=k, value=v) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diagnostics_pub.publish(msg)
        self._publish_grid()                   # again once a second: nothing lost for long

    # --- services and timer ----------------------------------------------------------------
    def _on_preflight(self, msg: DiagnosticArray) -> None:
        """Keep the preflight's latest verdict (an unreadable one counts as no-go)."""
        go, summary = preflight_verdict(msg)
        if go is None:
            self._error(f'{PREFLIGHT_TOPIC} unreadable, taken as no-go: {summary}')
        else:
            self.get_logger().info(f'preflight verdict: {summary}')
        self._preflight.on_verdict(go, summary, self.get_clock().now().nanoseconds / NS_PER_S)

    def _on_start(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        response.success, response.message = self._start('ibvs/start')
        return response

    def _on_abort(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        response.success, response.message = self._abort('ibvs/abort called')
        return response

    def _on_pilot_input(self, msg: UInt8) -> None:
        """Take the pilot's switch: OFF -> ON starts, -> OFF aborts (core/pilot_input.py)."""
        try:
            action = self._pilot.on_input(msg.data)
        except ValueError:
            self._error(f'ibvs/pilot_input {msg.data} is not a PilotInput value: ignored')
            return
        if action == PilotAction.START:
            self._start('pilot switch')
        elif action == PilotAction.ABORT:
            if self._core.mode in FLYING_MODES:
                self._abort('ibvs/pilot_input OFF: the pilot switch, or the vehicle left the '
                            "bridge (a pilot's or GCS's mode switch, link or input loss)")
            elif self._core.cancel_start():
                self.get_logger().warning('pilot switch OFF: the pending start is dropped')
        elif self._pilot.on_without_off and self._core.mode == Mode.IDLE:
            self.get_logger().warning('pilot switch ON without an OFF before it (at boot, or '
                                      'after an RC loss): no start; flip it OFF, then ON')

    def _start(self, source: str) -> tuple[bool, str]:
        """Request a start for ``source``: the preflight gate, then the core's checks."""
        refusal = self._preflight.refusal(self.get_clock().now().nanoseconds / NS_PER_S)
        if refusal is not None:
            self.get_logger().error(f'{source}: start refused: {refusal}')
            return False, refusal
        self._imu.take()                   # the start checks the IMU's age
        ok, message = self._core.request_start(self._now(), source)
        if ok:
            self.get_logger().info(f'{source}: {message}')
        else:
            self.get_logger().error(f'{source}: start refused: {message}')
        note = self._preflight.note()
        if ok and note:
            self.get_logger().warning(f'{source}: {note}')
        return ok, message

    def _abort(self, reason: str) -> tuple[bool, str]:
        """Abort to FAILSAFE (the bridge hands the vehicle to the autopilot's land mode).

        As a staleness transition, it has no frame: its status is stamped now, so that the
        controller answers it (level) and every later stamp's mode is known even while no
        frame comes (the cameras off).
        """
        self._imu.take()
        now_ns = self._now_ns()
        ok, message = self._core.abort(now_ns / NS_PER_S, reason)
        self.get_logger().info(f'abort ({reason}): {message}')
        self._publish_mode()
        if ok:
            self._publish_status(now_ns)
        return ok, message

    def _on_timer(self) -> None:
        """Staleness when inputs stop (frames are evaluated as they are released).

        A transition made here has no frame: its status is stamped with the transition time,
        so that the controller answers it (in FAILSAFE: level, the bridge hands over) and the
        mode of every later stamp is known.
        """
        self._imu.take()                   # the IMU's age: its staleness rule
        now_ns = self._now_ns()
        if self._core.update(now_ns / NS_PER_S, apply_requests=False):
            self._publish_mode()
            self._publish_status(now_ns)


def main(args: list[str] | None = None) -> None:
    """Run the node (``ros2 run ibvs_control mode_supervisor``)."""
    run_node(ModeSupervisorNode, 'mode_supervisor', args)
