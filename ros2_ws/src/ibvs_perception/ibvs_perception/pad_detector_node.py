"""pad_detector: down image + CameraInfo -> marker centres of complete pad groups (bearings).

Publishes one `pad/landmarks` (PolygonStamped, down optical frame, image stamp: unit bearings
of the marker centres of every complete group, largest group first, layout id order; empty
when no group is complete) and one `pad/groups` (sensor_msgs/JointState: same stamp and
frame, ``name`` = the groups in the landmarks' order, e.g. ['A', 'B']) per image;
nothing for the images of a frozen camera (``frozen_after_frames`` bit-identical images in a
row, :mod:`~ibvs_perception.frozen_camera`), as if the camera had delivered nothing.
"""
from __future__ import annotations

from rclpy.node import Node

from geometry_msgs.msg import PolygonStamped
from ibvs_common.core.config import ConfigError, load_pad_layout, load_vehicle
from sensor_msgs.msg import CameraInfo, Image, JointState

from ibvs_perception.core.pad import PadConfigError, PadDetector
from ibvs_common.core.frame_grid import period_ns
from ibvs_common.core.modes import InputKind
from ibvs_perception.frozen_camera import FrozenCameraGuard
from ibvs_perception.camera_input import camera_input, SharedCameraInputs
from ibvs_perception.gated_images import GatedImages
from ibvs_perception.messages import (camera_from_info, mono8_from_image, polygon_from_vectors,
                                      stamp_to_s)
from ibvs_common.node_common import pad_groups_msg
from ibvs_common.param_descriptors import declare_config
from ibvs_perception.config import PadDetectorNodeConfig
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import ThrottledLog

THROTTLE_S = 2.0


class PadDetectorNode(Node):
    """Thin ROS wrapper of :class:`PadDetector`."""

    def __init__(self, node_name: str = 'pad_detector',
                 camera_inputs: SharedCameraInputs | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, PadDetectorNodeConfig)   # ValueError: a bad parameter
        try:
            self.detector = PadDetector(load_pad_layout(cfg.pad_layout_file or None),
                                        cfg.detector)
            camera = load_vehicle(cfg.vehicle_file or None).cameras['down']
        except (ConfigError, PadConfigError, KeyError) as exc:
            self.get_logger().fatal(f'pad_detector: cannot load the pad layout or the down '
                                    f'camera: {exc}')
            raise
        self.frame_id = camera.frame_id
        self.frozen = FrozenCameraGuard(self, 'down', 'pad_detector',
                                        cfg.images.frozen_after_frames)
        self.gated = GatedImages(self, InputKind.PAD, self.process, 'pad_detector',
                                 cfg.images, camera.name, period_ns(camera.rate_hz))
        self.camera_info: CameraInfo | None = None
        self.pub_landmarks = self.create_publisher(PolygonStamped, 'pad/landmarks', 10)
        self.pub_groups = self.create_publisher(JointState, 'pad/groups', 10)
        self.images = camera_input(self, camera, cfg.images.image_transport,
                                   self.gated.on_images, 'pad_detector', self.on_info,
                                   camera_inputs)

    def on_info(self, msg: CameraInfo) -> None:
        self.camera_info = msg

    def process(self, msg: Image, publish: bool = True) -> None:
        """Detect the pad in one image and publish (a mode-gating primer: nothing to do)."""
        if not publish:
            return
        bearings, names, weights = None, (), ()
        try:
            gray = mono8_from_image(msg)
            if self.frozen.drop(gray, msg.header.stamp):
                return
            camera = camera_from_info(self.camera_info, msg)
            self.detector.frame_period_s = self.gated.frame_period_s
            detection = self.detector.process(gray, camera, stamp_to_s(msg.header.stamp))
            if len(detection.bearings_C):
                bearings, names = detection.bearings_C, detection.group_names
                weights = detection.group_weights
            if detection.rejected_groups:
                self.log.warning(f'pad_detector: group(s) {", ".join(detection.rejected_groups)} '
                                 "complete but off the pad layout (a foreign marker with a pad "
                                 'id?): not used', THROTTLE_S)
        except ValueError as exc:
            self.log.error(f'pad_detector: image dropped: {exc}', THROTTLE_S)
        self.pub_landmarks.publish(polygon_from_vectors(msg.header, self.frame_id, bearings))
        self.pub_groups.publish(pad_groups_msg(msg.header.stamp, self.frame_id, names, weights))


def main(args: list[str] | None = None) -> None:
    """Run the node (console script `pad_detector`)."""
    run_node(PadDetectorNode, 'pad_detector', args)


if __name__ == '__main__':
    main()
