"""A camera's images for one perception node: raw or compressed, stamped on the IMU's clock.

:class:`CameraInput` subscribes ``<camera>_camera/image_raw`` (sensor_msgs/Image) or, with
``image_transport: compressed``, ``<camera>_camera/image_raw/compressed``
(sensor_msgs/CompressedImage, decoded to mono8); moves each stamp by the camera-IMU time
offset of vehicle.yaml (so that every product and attitude lookup uses the exposure time on
the IMU's clock); warns (throttled) when an image's ``frame_id`` is not the camera's; and
says so when no image comes while the other transport's topic has a publisher. It also takes
the camera's ``<camera>_camera/camera_info``.

One CameraInput can feed several nodes of one process (the composed layout,
``ibvs_bringup.composed``): :class:`SharedCameraInputs` gives the front camera's window
detector and wall flow, and the down camera's pad detector and floor flow, one subscription
each for the image and the CameraInfo. rclpy has no intra-process path: every subscription
pays the middleware's take and the conversion of the message to Python, ~0.7 ms of a 752x480
mono8 image on the development machine (docs/performance.md "Where a frame's time goes"),
so two readers of one camera in one process paid it twice a frame. The consumers get the same
message object, one after the other in the order they attached: they must not modify it.
"""
from __future__ import annotations

from typing import Callable

import cv2
import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from ibvs_common.core.config import CameraConfig
from ibvs_common.node_common import IMAGE_QOS, ns_to_stamp
from ibvs_common.core.stamps import NS_PER_S, stamp_to_ns
from ibvs_common.throttled_log import ThrottledLog
from ibvs_common.waiting_messages import take_waiting

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


def image_topic(camera_name: str, transport: str) -> str:
    """Return the image topic of a camera for ``transport`` ('raw' or 'compressed')."""
    raw = f'{camera_name}_camera/image_raw'
    return raw if transport == 'raw' else raw + '/compressed'


class CameraInput:
    """One camera's images, converted and time-corrected, and its CameraInfo, for consumers.

    ``handler(images, taken_ns)`` and ``on_info(camera_info)`` are the first consumer's;
    :meth:`add_consumer` adds another one (a second node of the same process). ``images`` is
    the list of images taken at once, oldest first: the one the executor delivered and those
    already waiting behind it (:func:`ibvs_common.waiting_messages.take_waiting`), so that a
    consumer that is behind can compute the newest and skip the others; ``taken_ns`` the
    time they were taken (ns, the node's ROS clock).
    """

    def __init__(self, node: Node, camera: CameraConfig, transport: str,
                 handler: Callable[[list[Image], int], None], log_prefix: str,
                 on_info: Callable[[CameraInfo], None] | None = None) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"parameter image_transport must be one of {TRANSPORTS}, got "
                             f'{transport!r}')
        self.node, self.prefix = node, log_prefix
        self.camera_name, self.transport = camera.name, transport
        self.handlers: list[Callable[[list[Image], int], None]] = [handler]
        self.info_handlers: list[Callable[[CameraInfo], None]] = \
            [] if on_info is None else [on_info]
        self.frame_id = camera.frame_id
        self.offset_ns = int(round(camera.time_offset_s * NS_PER_S))
        self.log = ThrottledLog(node.get_logger())
        self.received = 0
        self.undecodable = 0
        self.topic = image_topic(camera.name, transport)
        self.other_topic = image_topic(camera.name, 'compressed' if transport == 'raw' else 'raw')
        # CameraInfo first: at one wake-up rclpy takes it before an image
        node.create_subscription(CameraInfo, f'{camera.name}_camera/camera_info', self._on_info,
                                 qos_profile_sensor_data)
        if transport == 'raw':
            self.subscription = node.create_subscription(Image, self.topic, self._on_image,
                                                         IMAGE_QOS)
        else:
            self.subscription = node.create_subscription(CompressedImage, self.topic,
                                                         self._on_compressed, IMAGE_QOS)
        self._silence_timer = node.create_timer(SILENCE_CHECK_S, self._check_silence)

    def add_consumer(self, handler: Callable[[list[Image], int], None],
                     on_info: Callable[[CameraInfo], None] | None = None) -> None:
        """Hand every image (and CameraInfo) to ``handler`` (``on_info``) too, after the others."""
        self.handlers.append(handler)
        if on_info is not None:
            self.info_handlers.append(on_info)

    def _on_info(self, msg: CameraInfo) -> None:
        for on_info in self.info_handlers:
            on_info(msg)

    def _on_image(self, msg: Image) -> None:
        self._deliver([msg] + take_waiting(self.subscription))

    def _on_compressed(self, msg: CompressedImage) -> None:
        images = []
        for compressed in [msg] + take_waiting(self.subscription):
            try:
                images.append(mono8_image(compressed.header, decode_mono8(compressed)))
            except ValueError as exc:
                self.undecodable += 1
                self.log.error(f'{self.prefix}: image dropped: {exc}', THROTTLE_S)
        if images:
            self._deliver(images)

    def _deliver(self, images: list[Image]) -> None:
        """Correct and check each image taken at once, then hand the list to every consumer.

        Every consumer also gets the time they were taken (ns, ROS clock): an image's age is
        judged as taken, not when a consumer's turn comes after the others' processing (the
        second consumer would otherwise find each image a processing time older and skip the
        frames the first one computed: a frame with half its products).
        """
        taken_ns = self.node.get_clock().now().nanoseconds
        for msg in images:
            self.received += 1
            if msg.header.frame_id != self.frame_id:
                self.log.warning(f'{self.prefix}: images on {self.topic} are in frame '
                                 f'{msg.header.frame_id!r}, not {self.frame_id!r} '
                                 '(vehicle.yaml): the camera mount and intrinsics assumed may '
                                 "not be this camera's", THROTTLE_S, key='frame_id')
            if self.offset_ns:
                ns_to_stamp(stamp_to_ns(msg.header.stamp) + self.offset_ns, msg.header.stamp)
        for handler in self.handlers:
            handler(images, taken_ns)

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


class SharedCameraInputs:
    """The camera inputs of one process: one :class:`CameraInput` per resolved image topic.

    Built by the composed container and handed to each perception node (module doc). The
    first node to ask for a camera owns its subscriptions; the others are added as consumers.
    """

    def __init__(self) -> None:
        self.inputs: dict[tuple[str, str], CameraInput] = {}   # (image, info) topics

    def attach(self, node: Node, camera: CameraConfig, transport: str,
               handler: Callable[[list[Image], int], None], log_prefix: str,
               on_info: Callable[[CameraInfo], None] | None = None) -> CameraInput:
        """Return the process's input of this camera, with ``handler`` and ``on_info`` added.

        Raises ValueError (a node refuses to start) when a node asks for the camera with
        another frame_id or time offset than the node that subscribed it: one message cannot
        carry two corrections.
        """
        # the names after the node's remappings: nodes remapped apart do not share
        key = tuple(node.resolve_topic_name(t) for t in (
            image_topic(camera.name, transport), f'{camera.name}_camera/camera_info'))
        shared = self.inputs.get(key)
        if shared is None:
            shared = CameraInput(node, camera, transport, handler, log_prefix, on_info)
            self.inputs[key] = shared
            return shared
        offset_ns = int(round(camera.time_offset_s * NS_PER_S))
        if (camera.frame_id, offset_ns) != (shared.frame_id, shared.offset_ns):
            raise ValueError(
                f'{log_prefix}: {camera.name} camera configured with frame_id '
                f'{camera.frame_id!r} and time_offset_s {camera.time_offset_s}, but '
                f'{shared.prefix} in the same process with {shared.frame_id!r} and '
                f'{shared.offset_ns / NS_PER_S} (vehicle_file parameters differ)')
        shared.add_consumer(handler, on_info)
        return shared


def camera_input(node: Node, camera: CameraConfig, transport: str,
                 handler: Callable[[list[Image], int], None], log_prefix: str,
                 on_info: Callable[[CameraInfo], None] | None = None,
                 shared: SharedCameraInputs | None = None) -> CameraInput:
    """Subscribe a node to a camera: through ``shared`` when given (composed), else its own."""
    if shared is not None:
        return shared.attach(node, camera, transport, handler, log_prefix, on_info)
    return CameraInput(node, camera, transport, handler, log_prefix, on_info)
