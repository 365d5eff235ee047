"""A camera's images for one perception node: raw or compressed, stamped on the IMU's clock.

:class:`CameraInput` subscribes ``<camera>_camera/image_raw`` (sensor_msgs/Image) or, with
``image_transport: compressed``, ``<camera>_camera/image_raw/compressed``
(sensor_msgs/CompressedImage, decoded to mono8); moves each stamp by the camera-IMU time
offset of vehicle.yaml (so that every product and attitude lookup uses the exposure time on
the IMU's clock); warns (throttled) when an image's ``frame_id`` is not the camera's; and
says so when no image comes while the other transport's topic has a publisher.
"""
from __future__ import annotations

from typing import Callable

import cv2
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from ibvs_common.core.config import CameraConfig
from ibvs_common.node_common import IMAGE_QOS, ns_to_stamp
from ibvs_common.core.stamps import NS_PER_S, stamp_to_ns
from ibvs_common.throttled_log import ThrottledLog

THROTTLE_S = 5.0
TRANSPORTS = ('raw', 'compressed')
SILENCE_CHECK_S = 5.0          # s (node clock) between checks that images come at all


def decode_mono8(msg: CompressedImage) -> np.ndarray:
    """Decode a CompressedImage (JPEG, PNG...) to a mono8 array; ValueError if it cannot."""
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if img is None:
        raise ValueError(f'compressed image ({msg.format!r}, {data.size} bytes) could not be '
                         'decoded')
    return img


def mono8_image(header, gray: np.ndarray) -> Image:
    """Build a sensor_msgs/Image (mono8) of ``gray`` with ``header``."""
    out = Image(height=int(gray.shape[0]), width=int(gray.shape[1]), encoding='mono8',
                is_bigendian=0, step=int(gray.shape[1]))
    out.header = header
    out.data = gray.tobytes()
    return out


class CameraInput:
    """One camera's images, converted and time-corrected, handed to ``handler``."""

    def __init__(self, node: Node, camera: CameraConfig, transport: str,
                 handler: Callable[[Image], None], log_prefix: str) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"parameter image_transport must be one of {TRANSPORTS}, got "
                             f'{transport!r}')
        self.node, self.handler, self.prefix = node, handler, log_prefix
        self.frame_id = camera.frame_id
        self.offset_ns = int(round(camera.time_offset_s * NS_PER_S))
        self.log = ThrottledLog(node.get_logger())
        self.received = 0
        self.undecodable = 0
        raw = f'{camera.name}_camera/image_raw'
        self.topic = raw if transport == 'raw' else raw + '/compressed'
        self.other_topic = raw + '/compressed' if transport == 'raw' else raw
        if transport == 'raw':
            node.create_subscription(Image, self.topic, self._deliver, IMAGE_QOS)
        else:
            node.create_subscription(CompressedImage, self.topic, self._on_compressed,
                                     IMAGE_QOS)
        self._silence_timer = node.create_timer(SILENCE_CHECK_S, self._check_silence)

    def _on_compressed(self, msg: CompressedImage) -> None:
        try:
            image = mono8_image(msg.header, decode_mono8(msg))
        except ValueError as exc:
            self.undecodable += 1
            self.log.error(f'{self.prefix}: image dropped: {exc}', THROTTLE_S)
            return
        self._deliver(image)

    def _deliver(self, msg: Image) -> None:
        self.received += 1
        if msg.header.frame_id != self.frame_id:
            self.log.warning(f'{self.prefix}: images on {self.topic} are in frame '
                             f'{msg.header.frame_id!r}, not {self.frame_id!r} (vehicle.yaml): '
                             'the camera mount and intrinsics assumed may not be this '
                             "camera's", THROTTLE_S, key='frame_id')
        if self.offset_ns:
            ns_to_stamp(stamp_to_ns(msg.header.stamp) + self.offset_ns, msg.header.stamp)
        self.handler(msg)

    def _check_silence(self) -> None:
        """Say why nothing comes, once every SILENCE_CHECK_S, until an image has come."""
        if self.received:
            self.node.destroy_timer(self._silence_timer)
            return
        others = self.node.count_publishers(self.other_topic)
        if others:
            self.node.get_logger().error(
                f'{self.prefix}: no image on {self.topic}, but {self.other_topic} has '
                f'{others} publisher(s): set image_transport to match the camera driver')
