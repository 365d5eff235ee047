"""Message <-> core conversions shared by the perception nodes (no maths beyond frames.py).

Each function either returns a core value or raises ValueError (ImageFormatError,
CameraModelError) with a readable reason that the node logs, throttled.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from geometry_msgs.msg import Point32, PolygonStamped
from ibvs_common.core.camera import CameraModel
from ibvs_common.node_common import imu_attitude, NS_PER_S
from sensor_msgs.msg import CameraInfo, Image, Imu

from ibvs_perception.core.image import image_to_mono8

if TYPE_CHECKING:
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header


def stamp_to_s(stamp: Time) -> float:
    """builtin_interfaces/Time -> seconds (float)."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def mono8_from_image(msg: Image) -> np.ndarray:
    """sensor_msgs/Image (core.image SUPPORTED_ENCODINGS) -> (H, W) uint8 grey; raises."""
    return image_to_mono8(msg.data, msg.width, msg.height, msg.encoding, msg.step)


def camera_from_info(msg: CameraInfo | None, image: Image) -> CameraModel:
    """Build the CameraModel of a CameraInfo that matches the image; raises ValueError."""
    if msg is None:
        raise ValueError('no CameraInfo received yet')
    model = CameraModel.from_camera_info(msg.width, msg.height, msg.k, msg.d,
                                         msg.distortion_model)
    if (model.width, model.height) != (image.width, image.height):
        raise ValueError(f'CameraInfo size {model.width}x{model.height} != image size '
                         f'{image.width}x{image.height}')
    return model


def attitude_from_imu(msg: Imu) -> tuple[float, tuple, np.ndarray]:
    """(stamp s, q_map_base, Omega_B FRD) of sensor_msgs/Imu, for AttitudeBuffer.add_map_base.

    The check is ``ibvs_common.node_common.imu_attitude`` (one for every node); raises
    ValueError for NaN/Inf or a non-unit quaternion.
    """
    stamp_ns, q_map_base, omega_B = imu_attitude(msg)
    return stamp_ns / NS_PER_S, q_map_base, omega_B


def polygon_from_vectors(header: Header, frame_id: str,
                         vectors: np.ndarray | None) -> PolygonStamped:
    """Build a PolygonStamped whose points are the rows of ``vectors`` (empty for None)."""
    msg = PolygonStamped()
    msg.header.stamp = header.stamp
    msg.header.frame_id = frame_id
    if vectors is not None:
        msg.polygon.points = [Point32(x=float(v[0]), y=float(v[1]), z=float(v[2]))
                              for v in vectors]
    return msg


def vectors_from_polygon(msg: PolygonStamped) -> np.ndarray:
    """(N, 3) array of a PolygonStamped's points; raises ValueError on non-finite values."""
    v = np.array([[p.x, p.y, p.z] for p in msg.polygon.points], dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(v)):
        raise ValueError('polygon holds NaN or Inf')
    return v
