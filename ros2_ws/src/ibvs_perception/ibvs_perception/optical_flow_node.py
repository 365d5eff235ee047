"""optical_flow: one camera's images + IMU -> translational optical flow phi = v/d (1/s).

One executable, one instance per camera (node names front_optical_flow, down_optical_flow);
parameter `camera` ('front' | 'down') selects the mount R_BC (vehicle.yaml) and the plane:
the floor (eta_t = e3) for the down camera, the window wall (eta_w from `window/corners`,
aperture excluded) for the front camera, with the floor below it as a second plane
(``floor_second_plane``: its points are fitted with their own, unknown distance instead of
biasing the wall's flow). Publishes `<camera>_camera/translational_flow`
(Vector3Stamped, frame `map`, stamp of the image) for EVERY processed image: the flow when
enough inliers, else all three components NaN, "no valid flow at this stamp" (first image, too
few inliers, no window, no attitude), so that the supervisor and the controller know per stamp
whether a flow is coming; and `<camera>_camera/translational_flow_quality` (Float32 inlier
ratio) for every estimate tried. The images of a frozen camera (``frozen_after_frames``
bit-identical images in a row, :mod:`~ibvs_perception.frozen_camera`) are not processed and
get no message at all, as if the camera had delivered nothing.

Each image is processed on arrival (timing layer, docs/design.md "Time"): its attitude is
the IMU's interpolated at the image stamp, or propagated to it with the gyro for at most
``imu_max_extrapolation_s`` (a frame never waits for a later IMU sample); the front camera's
wall plane comes from the newest window detection strictly older than the image, at most
``max_window_age_frames`` computed frames older (it never waits for the same image's
detection, which is computed in parallel). With stamps on one clock the result is a function of the
recorded data, so lockstep runs repeat and bag replays reproduce.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.config import ConfigError, load_vehicle
from ibvs_common.core.frames import e3, MAP_FRAME, vec_I_to_map
from ibvs_common.core.attitude_buffer import AttitudeBuffer
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_msgs.msg import Float32

from ibvs_perception.core.derotation import GyroDerotation
from ibvs_perception.config import OpticalFlowNodeConfig
from ibvs_perception.core.flow import FlowEstimator, wall_normal_from_corners
from ibvs_common.core.frame_grid import period_ns
from ibvs_common.core.modes import InputKind
from ibvs_perception.frozen_camera import FrozenCameraGuard
from ibvs_perception.camera_input import camera_input, SharedCameraInputs
from ibvs_perception.gated_images import GatedImages
from ibvs_perception.messages import (attitude_from_imu, camera_from_info, mono8_from_image,
                                      stamp_to_s, vectors_from_polygon)
from ibvs_common.node_common import LateImuReport, PRODUCT_QOS, stamp_to_ns
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog

THROTTLE_S = 2.0
FRONT, DOWN = 'front', 'down'
N_WINDOW_CORNERS = 4
NO_FLOW = (float('nan'),) * 3    # the "no valid flow at this stamp" vector (docs/interfaces.md)
WINDOW_HISTORY = 10          # recent window detections kept (newest last)


class OpticalFlowNode(Node):
    """Thin ROS wrapper of :class:`FlowEstimator` for one camera."""

    def __init__(self, node_name: str = 'optical_flow',
                 imu_local: IntraProcessTopic | None = None,
                 camera_inputs: SharedCameraInputs | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, OpticalFlowNodeConfig)   # ValueError: a bad parameter
        self.camera_name = cfg.camera
        self.max_window_age_frames = cfg.max_window_age_frames
        self.floor_second_plane = cfg.floor_second_plane
        try:
            camera = load_vehicle(cfg.vehicle_file or None).cameras[self.camera_name]
        except (ConfigError, KeyError) as exc:
            self.get_logger().fatal(f'optical_flow: cannot load the camera mount: {exc}')
            raise
        self.R_BC = camera.R_BC
        self.flow_config = cfg.flow
        self.frozen = FrozenCameraGuard(self, self.camera_name, 'optical_flow',
                                        cfg.images.frozen_after_frames)
        self.gated = GatedImages(
            self, InputKind.FLOW_FRONT if self.camera_name == FRONT else InputKind.FLOW_DOWN,
            self.process, f'{self.camera_name}_optical_flow', cfg.images, camera.name,
            period_ns(camera.rate_hz), flow=True)
        self.attitudes = AttitudeBuffer(cfg.imu)
        self.late_imu = LateImuReport(self.log, THROTTLE_S, 'optical_flow: ')
        self.derotation = GyroDerotation(self.attitudes)
        self.estimator: FlowEstimator | None = None
        self.camera_key: tuple | None = None
        self.camera_info: CameraInfo | None = None
        self.window_msgs: list[PolygonStamped] = []      # newest last
        self.window_stamps = BackstepWatch()              # back: a clock step, forget them
        prefix = f'{self.camera_name}_camera'
        self.pub_flow = self.create_publisher(Vector3Stamped, f'{prefix}/translational_flow', 10)
        self.pub_quality = self.create_publisher(
            Float32, f'{prefix}/translational_flow_quality', 10)
        # IMU and window first: at one wake-up rclpy takes them before an image (in process:
        # the IMU is taken by each image, ibvs_common.intra_process)
        self.imu = subscribe(self, Imu, 'imu/data', self.on_imu, qos_profile_sensor_data,
                             imu_local)
        if self.camera_name == FRONT:
            self.create_subscription(PolygonStamped, 'window/corners', self.on_window,
                                     PRODUCT_QOS)
        self.images = camera_input(self, camera, cfg.images.image_transport,
                                   self.gated.on_images, f'{self.camera_name}_optical_flow',
                                   self.on_info, camera_inputs)

    def on_info(self, msg: CameraInfo) -> None:
        self.camera_info = msg

    def on_window(self, msg: PolygonStamped) -> None:
        if self.window_stamps.observe(stamp_to_ns(msg.header.stamp)):
            self.log.warning('optical_flow: window/corners stamps went back (a clock step): '
                             'earlier detections dropped', THROTTLE_S)
            self.window_msgs = []
        self.window_msgs = self.window_msgs[-(WINDOW_HISTORY - 1):] + [msg]

    def on_imu(self, msg: Imu) -> None:
        try:
            if self.attitudes.add_map_base(*attitude_from_imu(msg)):
                self.log.warning('optical_flow: imu/data stamps went back (a clock step): IMU '
                                 'history dropped', THROTTLE_S)
        except ValueError as exc:
            self.log.error(f'optical_flow: IMU message dropped: {exc}', THROTTLE_S)
        self.late_imu.check(self.attitudes)

    def window_before(self, stamp: float) -> PolygonStamped | None:
        """Return the newest window detection strictly older than ``stamp``, or None."""
        older = [m for m in self.window_msgs if stamp_to_s(m.header.stamp) < stamp]
        return max(older, key=lambda m: stamp_to_s(m.header.stamp)) if older else None

    def process(self, msg: Image, publish: bool = True) -> None:
        """Track into one image and publish its flow (a mode-gating primer: track only)."""
        self.imu.take()
        try:
            camera = camera_from_info(self.camera_info, msg)
            gray = mono8_from_image(msg)
        except ValueError as exc:
            self.log.error(f'optical_flow: image dropped: {exc}', THROTTLE_S)
            return
        if self.frozen.drop(gray, msg.header.stamp):
            return
        key = (camera.width, camera.height, camera.distortion_model, tuple(camera.K.ravel()),
               tuple(camera.D.ravel()))
        if self.estimator is None or key != self.camera_key:
            self.estimator = FlowEstimator(self.flow_config, camera, self.R_BC)
            self.camera_key = key
        stamp = stamp_to_s(msg.header.stamp)
        R_IB = self.derotation.at_frame(stamp)
        if R_IB is None:
            self.gated.counts.no_attitude += 1
            self.log.warning('optical_flow: no IMU attitude at the image stamp', THROTTLE_S)
        eta_I, exclude_I = self.plane(stamp)
        eta2_I = e3 if self.camera_name == FRONT and self.floor_second_plane else None
        self.estimator.frame_period_s = self.gated.frame_period_s
        result = self.estimator.process(gray, stamp, R_IB, eta_I, exclude_I, eta2_I)
        if not publish:
            return
        if result is not None:
            self.pub_quality.publish(Float32(data=float(result.inlier_ratio)))
        valid = result is not None and result.phi_I is not None
        out = Vector3Stamped()
        out.header.stamp = msg.header.stamp
        out.header.frame_id = MAP_FRAME
        out.vector.x, out.vector.y, out.vector.z = (
            (float(x) for x in vec_I_to_map(result.phi_I)) if valid else NO_FLOW)
        self.pub_flow.publish(out)

    def plane(self, stamp: float) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(eta in {I}, excluded corner bearings in {I}) of the observed plane at ``stamp``.

        Down: the floor, eta_t = e3. Front: the window wall from the newest window corners
        strictly older than the image (at most max_window_age_frames computed frames older),
        rotated with the IMU attitude at their stamp.
        """
        if self.camera_name == DOWN:
            return e3, None
        msg = self.window_before(stamp)
        reason = None
        if msg is None or len(msg.polygon.points) != N_WINDOW_CORNERS:
            reason = 'no window detection'
        elif abs(stamp - stamp_to_s(msg.header.stamp)) > \
                self.max_window_age_frames * self.gated.frame_period_s:
            reason = 'window detection too old'
        else:
            R_IB = self.attitudes.attitude_at(stamp_to_s(msg.header.stamp))
            if R_IB is None:
                reason = 'no IMU attitude at the window stamp'
            else:
                try:
                    return wall_normal_from_corners(vectors_from_polygon(msg), R_IB, self.R_BC)
                except ValueError as exc:
                    reason = f'degenerate window corners ({exc})'
        self.log.info(f'optical_flow: no front flow (NaN published): {reason}', THROTTLE_S)
        return None, None


def main(args: list[str] | None = None) -> None:
    """Run the node (console script `optical_flow`)."""
    run_node(OpticalFlowNode, 'optical_flow', args)


if __name__ == '__main__':
    main()
