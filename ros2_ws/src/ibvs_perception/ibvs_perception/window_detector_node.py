"""window_detector: front image + CameraInfo + IMU -> window corners and edge normals (bearings).

Publishes one `window/corners` and one `window/edge_normals` (PolygonStamped, optical frame,
stamp of the image) for EVERY image: 4 unit bearings TL, TR, BR, BL / 4 unit normals h_i, or
empty polygons when the window is not (fully) detected or its track was lost. Except for the
images of a frozen camera (``frozen_after_frames`` bit-identical images in a row,
:mod:`~ibvs_perception.frozen_camera`): nothing at all, as if the camera had delivered nothing.

Tracking with the gyro: the attitude at each image stamp (``imu/data``, interpolated or
propagated, :class:`~ibvs_common.core.attitude_buffer.AttitudeBuffer`) gives the camera's rotation
since the previous image, and the detector moves the tracked window by it before searching
and gating (``WindowDetector.process``). Without an attitude at either stamp the frame is
processed without the prediction (as before), never dropped.

The window's size (the frame band's proportions) comes from the window layout file
(``window_layout_file``, default the installed window_layout.yaml), as for the supervisor and
the controller.
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from geometry_msgs.msg import PolygonStamped
from sensor_msgs.msg import CameraInfo, Image, Imu

from ibvs_perception.config import WindowDetectorNodeConfig
from ibvs_perception.core.window import WindowDetector
from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.core.frame_grid import period_ns
from ibvs_common.core.modes import InputKind
from ibvs_perception.frozen_camera import FrozenCameraGuard
from ibvs_perception.camera_input import camera_input, SharedCameraInputs
from ibvs_perception.gated_images import GatedImages
from ibvs_perception.messages import (attitude_from_imu, camera_from_info, mono8_from_image,
                                      polygon_from_vectors, stamp_to_s)
from ibvs_common.core.config import ConfigError, load_vehicle, load_window_layout
from ibvs_common.core.attitude_buffer import AttitudeBuffer
from ibvs_common.node_common import LateImuReport
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog

THROTTLE_S = 2.0
DEBUG_AXIS_PX = 40      # length of the drawn image axes, px
DEBUG_COLOUR = (0, 255, 0)


class WindowDetectorNode(Node):
    """Thin ROS wrapper of :class:`WindowDetector`."""

    def __init__(self, node_name: str = 'window_detector',
                 imu_local: IntraProcessTopic | None = None,
                 camera_inputs: SharedCameraInputs | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, WindowDetectorNodeConfig)
        self.publish_debug = cfg.publish_debug_image
        try:
            camera = load_vehicle(cfg.vehicle_file or None).cameras['front']
            layout = load_window_layout(cfg.window_layout_file or None)
        except (ConfigError, KeyError) as exc:
            self.get_logger().fatal(f'window_detector: cannot load the camera mount or the '
                                    f'window layout: {exc}')
            raise
        self.R_BC, self.frame_id = camera.R_BC, camera.frame_id
        detector_config = dataclasses.replace(
            cfg.detector, window_width_m=layout.width, window_height_m=layout.height,
            frame_band_m=layout.frame_band)
        self.attitudes = AttitudeBuffer(cfg.imu)
        self.late_imu = LateImuReport(self.log, THROTTLE_S, 'window_detector: ')
        self.R_IC_prev: np.ndarray | None = None    # camera attitude at the previous image
        self.detector = WindowDetector(detector_config)
        self.frozen = FrozenCameraGuard(self, 'front', 'window_detector',
                                        cfg.images.frozen_after_frames)
        self.gated = GatedImages(self, InputKind.WINDOW, self.process, 'window_detector',
                                 cfg.images, camera.name, period_ns(camera.rate_hz))
        self.camera_info: CameraInfo | None = None
        self.pub_corners = self.create_publisher(PolygonStamped, 'window/corners', 10)
        self.pub_normals = self.create_publisher(PolygonStamped, 'window/edge_normals', 10)
        self.pub_debug = self.create_publisher(Image, 'window/debug_image', 1) \
            if self.publish_debug else None
        # IMU first: at one wake-up rclpy takes it before an image (in process: taken by
        # each image, ibvs_common.intra_process)
        self.imu = subscribe(self, Imu, 'imu/data', self.on_imu, qos_profile_sensor_data,
                             imu_local)
        self.images = camera_input(self, camera, cfg.images.image_transport,
                                   self.gated.on_images, 'window_detector', self.on_info,
                                   camera_inputs)

    def on_info(self, msg: CameraInfo) -> None:
        self.camera_info = msg

    def on_imu(self, msg: Imu) -> None:
        try:
            if self.attitudes.add_map_base(*attitude_from_imu(msg)):
                self.log.warning('window_detector: imu/data stamps went back (a clock step): IMU '
                                 'history dropped', THROTTLE_S)
        except ValueError as exc:
            self.log.error(f'window_detector: IMU message dropped: {exc}', THROTTLE_S)
        self.late_imu.check(self.attitudes)

    def camera_rotation(self, stamp_s: float) -> np.ndarray | None:
        """Camera rotation since the previous image (WindowDetector.process), or None."""
        R_IB = self.attitudes.attitude_at(stamp_s)
        if R_IB is None:
            self.gated.counts.no_attitude += 1
        R_IC = None if R_IB is None else R_IB @ self.R_BC
        rotation = None if R_IC is None or self.R_IC_prev is None else R_IC.T @ self.R_IC_prev
        self.R_IC_prev = R_IC
        return rotation

    def process(self, msg: Image, publish: bool = True) -> None:
        """Detect the window in one image and publish (a mode-gating primer: nothing to do)."""
        if not publish:
            return
        self.imu.take()
        corners = normals = gray = detection = None
        try:
            gray = mono8_from_image(msg)
            if self.frozen.drop(gray, msg.header.stamp):
                return
            camera = camera_from_info(self.camera_info, msg)
            rotation = self.camera_rotation(stamp_to_s(msg.header.stamp))
            result = self.detector.process(gray, camera, rotation)
            detection = result.detection
            if detection is not None:
                corners, normals = detection.bearings_C, detection.edge_normals_C
            else:
                self.log.info(f'window_detector: no window ({result.status.value}): '
                              f'{result.reason}', THROTTLE_S)
        except ValueError as exc:
            self.log.error(f'window_detector: image dropped: {exc}', THROTTLE_S)
        self.pub_corners.publish(polygon_from_vectors(msg.header, self.frame_id, corners))
        self.pub_normals.publish(polygon_from_vectors(msg.header, self.frame_id, normals))
        if self.pub_debug is not None and gray is not None:
            self.pub_debug.publish(self._debug_image(msg, gray, detection))

    def _debug_image(self, msg: Image, gray: np.ndarray, detection) -> Image:
        """bgr8 image with the detected aperture and its image axes drawn."""
        img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        if detection is not None:
            quad = np.round(detection.corners_px).astype(np.int32)
            cv2.polylines(img, [quad], True, DEBUG_COLOUR, 2)
            centre = quad.mean(axis=0)
            right = (quad[1] + quad[2]) / 2.0 - centre
            down = (quad[2] + quad[3]) / 2.0 - centre
            for axis, colour in ((right, (0, 0, 255)), (down, (255, 0, 0))):
                tip = centre + DEBUG_AXIS_PX * axis / max(np.linalg.norm(axis), 1e-9)
                cv2.arrowedLine(img, tuple(int(x) for x in centre),
                                tuple(int(x) for x in tip), colour, 2)
        out = Image()
        out.header = msg.header
        out.height, out.width = img.shape[:2]
        out.encoding = 'bgr8'
        out.step = img.shape[1] * 3
        out.data = img.tobytes()
        return out


def main(args: list[str] | None = None) -> None:
    """Run the node (console script `window_detector`)."""
    run_node(WindowDetectorNode, 'window_detector', args)


if __name__ == '__main__':
    main()
