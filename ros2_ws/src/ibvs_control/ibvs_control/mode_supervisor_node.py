"""mode_supervisor: the flight-mode state machine on ROS (SPEC.md section 3).

Thin ROS wrapper of :class:`ibvs_control.core.supervisor.ModeSupervisor` on the timing layer
(core/timing.py, docs/design.md "Time"). The current mode is evaluated frame by frame on the
frames of its camera (front for IDLE and WINDOW, down for the others): a frame is released
when the products the mode needs are in (WINDOW: window + front flow; CROSSING: down flow;
LANDING: pad + down flow; IDLE: window) or when the ROS clock reaches its stamp +
``frame_deadline_s``; then its products are converted to {I} (bearings: optical -> body FRD
by the camera mount R_BC of vehicle.yaml -> {I} by the IMU attitude interpolated at the
stamp, or propagated to it; flows: map -> {I}), given to the core in a fixed order and the
frame is closed (``end_frame``: auto-start, triggers, staleness). The frame's products that
its mode does not wait for (e.g. the pad in CROSSING) are given to the core after the close;
products of the other camera, and products arriving after their frame was released, on
arrival. So the mode of each frame depends on that frame's needed inputs and on what came
before it, not on the order in which DDS delivered them, and an input the mode does not use
never delays a frame. A timer on the
node clock (``update_rate_hz``) applies the staleness rules when inputs stop altogether.

Clock steps (:mod:`ibvs_common.core.clock_step`): every callback reads the node clock through
a watch. When it went back by more than ``MAX_BACKSTEP_S`` (the system clock stepped back),
the frames and the IMU history are dropped and the core takes every input as missing:
FAILSAFE in a flying mode (:meth:`ModeSupervisor.clock_stepped_back`). The watchdog timer
cannot be relied on for this: rcl does not see a step of system time and would hold the
timer for the length of the step. The stamps of the IMU and of each product kind are
watched too (a camera or a bag on a clock of its own): the history they feed starts again.

Publishes ``ibvs/mode`` (std_msgs/UInt8, reliable, transient local, depth 1) at start and on
every transition (each logged with its reason), and ``ibvs/supervisor_status``
(diagnostic_msgs/DiagnosticArray, reliable) for every evaluated frame, stamped with it: the
force controller flies that frame in that mode. Serves ``ibvs/start`` and ``ibvs/abort``
(std_srvs/Trigger, success + message from the core); an accepted start is applied when the
next frame is closed (``ModeSupervisor.request_start``), an abort at once.

``pad/groups`` (sensor_msgs/JointState, the group names) is paired with the ``pad/landmarks``
of the same stamp (PadPairing): the two topics are not ordered with respect to each other.
"""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from rclpy.node import Node

from sensor_msgs.msg import Imu
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
from ibvs_common.core.frames import bearings_C_to_I
from ibvs_common.core.modes import CAMERA_OF, InputKind, Mode, MODE_INPUTS
from ibvs_control.config import ModeSupervisorNodeConfig
from ibvs_control.core.supervisor import ModeSupervisor
from ibvs_common.core.attitude_buffer import AttitudeBuffer
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_control.core.timing import Frame, FrameAssembler
from ibvs_control.product_subscriptions import FrameProductSubscriptions
from ibvs_common.node_common import (
    COMMAND_QOS, DeadlineTimer, imu_attitude, LateImuReport, MODE_QOS, NS_PER_S, SENSOR_QOS,
    supervisor_status_msg)
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog

LOG_THROTTLE_S = 2.0
CAMERA_NAME = {InputKind.WINDOW: 'front', InputKind.PAD: 'down'}


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
        self._attitudes = AttitudeBuffer(cfg.imu)
        self._late_imu = LateImuReport(self.log, LOG_THROTTLE_S)
        # frames of the current mode's camera wait for the products that mode needs
        self._frames = FrameAssembler(cfg.frame_deadline_s, self._needed)
        self._clock_watch = BackstepWatch()    # the node clock, read in every callback
        self._n_reported = 0
        self._published: Mode | None = None

        self._mode_pub = self.create_publisher(UInt8, 'ibvs/mode', MODE_QOS)
        self._status_pub = self.create_publisher(DiagnosticArray, 'ibvs/supervisor_status',
                                                 COMMAND_QOS)
        # in process (composed), the IMU samples are taken at the start of every callback
        self._imu = subscribe(self, Imu, 'imu/data', self._on_imu, SENSOR_QOS, imu_local)
        self._products = FrameProductSubscriptions(self, self._add)
        self.create_service(Trigger, 'ibvs/start', self._on_start)
        self.create_service(Trigger, 'ibvs/abort', self._on_abort)
        self.create_timer(1.0 / cfg.update_rate_hz, self._on_timer)   # node clock
        self._deadline = DeadlineTimer(self, self._on_deadline)
        self._publish_mode()
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

    def _to_I(self, bearings_C: np.ndarray | None, stamp_ns: int, camera: str
              ) -> tuple[bool, np.ndarray | None]:
        """Derotate bearings to {I} with the attitude at the stamp: (usable?, bearings or None)."""
        if bearings_C is None:
            return True, None
        R_IB = self._attitudes.attitude_at(stamp_ns / NS_PER_S)
        if R_IB is None:
            self._error(f'no IMU attitude at {stamp_ns / NS_PER_S:.3f} s: cannot derotate '
                        f'the {camera} bearings (taken as not detected)')
            return False, None
        return True, bearings_C_to_I(bearings_C, R_IB, self._R_BC[camera])

    def _needed(self, camera) -> frozenset:
        """Products a frame of ``camera`` waits for in the current mode (none: other camera)."""
        inputs = MODE_INPUTS[self._core.mode]
        return inputs.needed if camera == inputs.camera else frozenset()

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
        if camera != MODE_INPUTS[self._core.mode].camera \
                or not (self._frames.is_pending(stamp_ns)
                        or self._frames.open(stamp_ns, camera, now_ns)):
            self._feed(kind, stamp_ns, value)        # other camera, or its frame is gone
        self._release()

    def _on_deadline(self) -> None:
        self._imu.take()
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
                self._core.on_window(t, corners_I)
        elif kind == InputKind.PAD:
            landmarks_C, groups = value or (None, ())
            ok, landmarks_I = self._to_I(landmarks_C, stamp_ns, 'down')
            if ok:
                self._core.on_pad(t, landmarks_I, list(groups))
        elif value is not None:
            self._core.on_flow(t, 'front' if kind == InputKind.FLOW_FRONT else 'down', value)

    def _evaluate(self, frame: Frame) -> None:
        """Give a released frame's needed products to the core in a fixed order, close it.

        Its other products of the same camera (``frame.extras``) are given after the close,
        as if they had arrived after the release: they count from the next frame on, whatever
        the order in which they arrived (e.g. the pad seen in CROSSING).
        """
        t = frame.stamp_ns / NS_PER_S
        for kind, value in frame.inputs.items():      # timing.EVALUATION_ORDER
            self._feed(kind, frame.stamp_ns, value)
        extras = [(k, v) for k, v in frame.extras.items() if CAMERA_OF[k] == frame.tag]
        if frame.tag != MODE_INPUTS[self._core.mode].camera:
            for kind, value in extras:  # the mode moved to the other camera: products only
                self._feed(kind, frame.stamp_ns, value)
            return
        if frame.missing:
            self.log.warning(
                f'frame {t:.3f} s evaluated at its deadline without '
                f'{", ".join(k.value for k in frame.missing)} (late or lost)', LOG_THROTTLE_S)
        self._core.end_frame(t)
        if self._core.auto_start_refusal:
            self._error(f'auto-start refused: {self._core.auto_start_refusal}')
        if self._core.start_refusal:
            self._error(f'ibvs/start dropped: {self._core.start_refusal}')
        self._publish_mode()
        self._publish_status(frame.stamp_ns)
        for kind, value in extras:
            self._feed(kind, frame.stamp_ns, value)

    def _publish_status(self, stamp_ns: int) -> None:
        mode = self._core.mode
        level = DiagnosticStatus.WARN if mode == Mode.FAILSAFE else DiagnosticStatus.OK
        height = self._core.height_estimate
        values = {'pad_height_estimate_m': 'none' if height is None else f'{height:.4f}'}
        self._status_pub.publish(supervisor_status_msg(stamp_ns, int(mode), mode.name, level,
                                                       values))

    # --- services and timer ----------------------------------------------------------------
    def _on_start(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self._imu.take()                   # the start checks the IMU's age
        response.success, response.message = self._core.request_start(self._now())
        self.get_logger().info(f'ibvs/start: {response.message}')
        return response

    def _on_abort(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        self._imu.take()
        response.success, response.message = self._core.abort(self._now(), 'ibvs/abort called')
        self.get_logger().info(f'ibvs/abort: {response.message}')
        self._publish_mode()
        return response

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
