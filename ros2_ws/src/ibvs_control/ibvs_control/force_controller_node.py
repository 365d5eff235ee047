"""force_controller: detections + flows + IMU + mode -> the paper's force F and a heading.

Thin ROS wrapper of :class:`~ibvs_control.core.controller.IbvsController` on the timing layer
(core/timing.py; docs/design.md "Time"). Each ``ibvs/supervisor_status`` of a frame is answered
once, in its mode, from that frame's products (they come by its deadline, or the frame is
skipped: never flown on a stale or missing product; while the rate governor sheds the flows,
the status names the earlier flow frame a frame holds its flow from), with the IMU attitude at
the stamp. A frame that hands the mode over to the other camera is answered only if that camera
has an image of the same stamp (timing.py, "Camera handover"). Publishes, stamped with the
frame: ``ibvs/heading_setpoint``, ``ibvs/force_setpoint`` (map, N) and ``ibvs/features``
(docs/interfaces.md).
"""
from __future__ import annotations

from collections import deque

import numpy as np
from rclpy.node import Node

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import QuaternionStamped, Vector3Stamped
from sensor_msgs.msg import Imu, JointState

from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
from ibvs_control.config import ForceControllerNodeConfig
from ibvs_control.core.controller import IbvsController
from ibvs_control.core.frame_inputs import (feature_vector, heading_quat_enu_flu,
                                            SpecificForceBuffer, step_controller)
from ibvs_common.core.frames import GRAVITY, MAP_FRAME, vec_flu_to_frd, vec_I_to_map
from ibvs_common.core.modes import InputKind, Mode, MODE_INPUTS
from ibvs_common.core.attitude_buffer import AttitudeBuffer
from ibvs_control.core.timing import Frame, FrameAssembler
from ibvs_control.product_subscriptions import FrameProductSubscriptions
from ibvs_common.node_common import (
    camera_from_status, COMMAND_QOS, DeadlineTimer, FRAME_QOS, held_from_status, imu_attitude,
    LateImuReport,
    mode_from_status, NS_PER_S,
    ns_to_stamp, SENSOR_QOS, set_quat, set_vector3, vector3)
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog

LOG_THROTTLE_S = 2.0
MIN_SPECIFIC_FORCE = 0.3 * GRAVITY   # m/s^2, least accelerometer reading used in flight


def _mode(number) -> tuple[Mode | None, str]:
    """Convert a mode number from a message to (Mode, '') or (None, why it is refused)."""
    try:
        return Mode(int(number)), ''
    except (TypeError, ValueError):
        return None, f'unknown mode {number!r}: ignored'


class ForceControllerNode(Node):
    """ROS side of the outer-loop IBVS controller."""

    def __init__(self, node_name: str = 'force_controller',
                 imu_local: IntraProcessTopic | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, ForceControllerNodeConfig)
        vehicle = load_vehicle(cfg.vehicle_file or None)
        r_w = load_window_layout(cfg.window_layout_file or None).width
        pad = load_pad_layout(cfg.pad_layout_file or None)
        config = cfg.controller_config(vehicle, r_w, pad)   # raises GainError
        self._controller = IbvsController(config)
        self._attitudes = AttitudeBuffer(cfg.imu)
        self._late_imu = LateImuReport(self.log, LOG_THROTTLE_S)
        # a frame = one supervisor status (tag: its mode), waiting for that mode's products
        self._frames = FrameAssembler(cfg.frame_deadline_s,
                                      lambda mode: MODE_INPUTS[mode].needed)
        # the disturbance observer's input: imu/data's specific force, per answered frame
        self._specific_force = SpecificForceBuffer() \
            if config.disturbance_law.uses_observer else None
        self._t_answered: float | None = None
        self.skipped = 0                        # frames not answered: a product never came
        self.handovers = 0                      # frames handed over to the other camera
        self._handover_ns: deque[int] = deque(maxlen=8)   # stamps of handover frames
        self._status_stamps = BackstepWatch()   # one publisher's stream: back = clock step

        self._force_pub = self.create_publisher(Vector3Stamped, 'ibvs/force_setpoint',
                                                COMMAND_QOS)
        self._heading_pub = self.create_publisher(QuaternionStamped, 'ibvs/heading_setpoint',
                                                  COMMAND_QOS)
        self._features_pub = self.create_publisher(JointState, 'ibvs/features', COMMAND_QOS)
        # products and IMU first: at one wake-up rclpy takes them before a status
        # in process (composed), the IMU samples are taken at the start of every callback
        self._imu = subscribe(self, Imu, 'imu/data', self._on_imu, SENSOR_QOS, imu_local)
        self._products = FrameProductSubscriptions(self, self._add)
        self.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', self._on_status,
                                 FRAME_QOS)
        self._deadline = DeadlineTimer(self, self._on_deadline)
        self.get_logger().info(f'force controller: gains {config.landing}, {config.window}, '
                               f'{config.crossing}, crossing law {config.crossing_law.value}, '
                               f'disturbance law {config.disturbance_law.value}'
                               + (f' {config.integral}' if config.disturbance_law
                                  .uses_integral else '')
                               + (f' {config.observer}' if config.disturbance_law
                                  .uses_observer else ''))

    # --- inputs ----------------------------------------------------------------------------
    def _on_imu(self, msg: Imu) -> None:
        try:
            stamp_ns, q_map_base, omega_B = imu_attitude(msg)
            stepped = self._attitudes.add_map_base(stamp_ns / NS_PER_S, q_map_base, omega_B)
        except ValueError as exc:
            self.log.error(f'imu/data refused: {exc}', LOG_THROTTLE_S)
            return
        self._late_imu.check(self._attitudes)
        if stepped:
            self._clock_stepped('imu/data', 'IMU history')
            if self._specific_force is not None:
                self._specific_force.clear()
            self._t_answered = None
        if self._specific_force is not None and msg.linear_acceleration_covariance[0] >= 0.0:
            self._add_specific_force(stamp_ns, vector3(msg.linear_acceleration))
        self._release()

    def _add_specific_force(self, stamp_ns: int, f_flu: np.ndarray) -> None:
        """Keep a specific force sample (base_link FLU -> body FRD) for the observer.

        A flying multirotor's accelerometer reads about g (its thrust): a sample under
        MIN_SPECIFIC_FORCE (an unfilled field, free fall) or non-finite is not used. It is
        rotated to {I} with the attitude of its stamp when a frame reads it.
        """
        norm = float(np.linalg.norm(f_flu))
        if not np.isfinite(norm) or norm < MIN_SPECIFIC_FORCE:
            self.log.warning(f'imu/data linear_acceleration |f| = {norm:.2f} m/s^2 is not a '
                             'flying specific force: the disturbance observer ignores it',
                             LOG_THROTTLE_S)
            return
        self._specific_force.add(stamp_ns / NS_PER_S, vec_flu_to_frd(f_flu))

    def _on_status(self, msg: DiagnosticArray) -> None:
        """Open the frame the supervisor evaluated, to be answered in the mode it reports."""
        self._imu.take()
        stamp_ns, number, err = mode_from_status(msg)
        mode, err = (None, err) if err else _mode(number)
        camera = camera_from_status(msg)
        if err:
            self._refused('ibvs/supervisor_status', err)
            return
        if self._status_stamps.observe(stamp_ns):
            self._frames.reset()
            self._clock_stepped('ibvs/supervisor_status', 'pending frames')
        held, err = held_from_status(msg)
        try:
            held = {InputKind(name): (src, src) for name, src in held.items()}
        except ValueError:
            held, err = {}, f'unknown product in {sorted(held)}'
        if err:     # the frame waits for its own products: skipped if they never come
            self._refused('ibvs/supervisor_status held products', err)
        if not self._frames.open(stamp_ns, mode, self.get_clock().now().nanoseconds, held):
            self.log.warning(f'status of {stamp_ns} ns is a duplicate or older than '
                             'a frame already answered: dropped', LOG_THROTTLE_S)
        elif camera is not None and camera != MODE_INPUTS[mode].camera.value:
            self._handover_ns.append(stamp_ns)     # a frame of the camera the mode left
        self._release()

    def _refused(self, what: str, err: str) -> None:
        self.log.error(f'{what} refused: {err}', LOG_THROTTLE_S)

    def _clock_stepped(self, what: str, dropped: str) -> None:
        self.log.warning(f'{what} stamps went back (a step of the clock): {dropped} dropped',
                         LOG_THROTTLE_S)

    def _add(self, kind: InputKind, stamp_ns: int, value, err: str) -> None:
        """Keep one product (a bad one counts as 'not detected') and answer what it completes."""
        self._imu.take()
        if err:
            self._refused(kind.value, err)
        steps = self._frames.clock_steps
        if not self._frames.add_input(kind, stamp_ns, value):
            self.log.warning(f'duplicate {kind.value}: dropped', LOG_THROTTLE_S)
        if self._frames.clock_steps != steps:
            self._clock_stepped(kind.value, 'pending frames')
        self._release()

    def _on_deadline(self) -> None:
        self._imu.take()
        self._products.take_waiting()     # products that came, queued behind other callbacks
        self._release()

    def _release(self) -> None:
        if not self._frames.has_pending:      # most calls: an IMU sample between frames
            return
        for frame in self._frames.release(self.get_clock().now().nanoseconds):
            self._answer(frame)
        self._deadline.arm(self._frames.next_deadline_ns())

    # --- output ----------------------------------------------------------------------------
    def _answer(self, frame: Frame) -> None:
        if not frame.complete and frame.stamp_ns in self._handover_ns:
            self.handovers += 1     # the new camera has no image of this stamp: its next one
            self.log.info(f'frame {frame.stamp_ns / NS_PER_S:.3f} s hands {frame.tag.name} over '
                          f'to the {MODE_INPUTS[frame.tag].camera.value} camera: answered from '
                          'its next frame', LOG_THROTTLE_S)
            return
        if not frame.complete:      # never answered from a stale or missing product
            self.skipped += 1
            self.log.warning(
                f'frame {frame.stamp_ns / NS_PER_S:.3f} s skipped: no '
                f'{", ".join(k.value for k in frame.missing)} by its deadline (late or lost); '
                f'{self.skipped} skipped in all', LOG_THROTTLE_S)
            return
        t = frame.stamp_ns / NS_PER_S
        f_I = None
        if self._specific_force is not None:
            f_I = self._specific_force.mean_between(self._t_answered, t,
                                                    self._attitudes.attitude_at)
        self._t_answered = t
        out, F_I = step_controller(self._controller, frame.tag, frame,
                                   self._attitudes.attitude_at(t), f_I,
                                   self._attitudes.rate_at(t))
        if out is None:
            self.log.warning('no IMU attitude (or no valid output): answering with hover',
                             LOG_THROTTLE_S)
        else:
            heading = QuaternionStamped()
            ns_to_stamp(frame.stamp_ns, heading.header.stamp)
            heading.header.frame_id = MAP_FRAME
            set_quat(heading.quaternion, heading_quat_enu_flu(out.yaw_des))
            self._heading_pub.publish(heading)
        force = Vector3Stamped()
        ns_to_stamp(frame.stamp_ns, force.header.stamp)
        force.header.frame_id = MAP_FRAME
        set_vector3(force.vector, vec_I_to_map(F_I))
        self._force_pub.publish(force)
        if out is not None:
            names, values = feature_vector(out.features)
            features = JointState(name=names, position=values)
            ns_to_stamp(frame.stamp_ns, features.header.stamp)
            features.header.frame_id = ''   # values are in the paper frame {I}
            self._features_pub.publish(features)


def main(args: list[str] | None = None) -> None:
    """Run the node (``ros2 run ibvs_control force_controller``); exit 1 on bad gains."""
    run_node(ForceControllerNode, 'force_controller', args)
