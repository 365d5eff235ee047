"""ROS messages of the sim nodes: stamps, mono8 images, camera info, ground-truth odometry.

Shared by the ``sim`` and ``px4_sim`` nodes (and the latency benchmark), so that both simulators
publish the very same messages.
"""
from __future__ import annotations

import numpy as np

from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image

from ibvs_common.core.camera import CameraModel
from ibvs_common.core.frames import (quat_from_rot, quat_wxyz_to_xyzw, rot_map_base_from_R_IB,
                                     vec_frd_to_flu, vec_I_to_map)
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.dynamics import State

MAP_FRAME = 'map'
BASE_FRAME = 'base_link'
MONO8 = 'mono8'


def stamp_from_ns(t_ns: int) -> Time:
    """builtin_interfaces/Time of a sim time in integer nanoseconds."""
    return Time(sec=int(t_ns // NS_PER_S), nanosec=int(t_ns % NS_PER_S))


def image_msg(img: np.ndarray, stamp: Time, frame_id: str) -> Image:
    """Mono8 sensor_msgs/Image from an (H, W) uint8 array."""
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = MONO8
    msg.is_bigendian = 0
    msg.step = int(img.shape[1])
    msg.data = np.ascontiguousarray(img).tobytes()
    return msg


def camera_info_msg(model: CameraModel, stamp: Time, frame_id: str) -> CameraInfo:
    """Build the CameraInfo of a calibrated camera: K, D, R = I, P = [K | 0]."""
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = model.width, model.height
    msg.distortion_model = model.distortion_model
    msg.d = [float(x) for x in model.D]
    msg.k = [float(x) for x in model.K.ravel()]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    P = np.hstack([model.K, np.zeros((3, 1))])
    msg.p = [float(x) for x in P.ravel()]
    return msg


def odometry_msg(state: State, stamp: Time) -> Odometry:
    """Build the ground truth as nav_msgs/Odometry (map ENU / base_link FLU).

    Pose of base_link in map; twist in base_link (Odometry's convention: child frame).
    """
    R_map_base = rot_map_base_from_R_IB(state.R_IB)
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = MAP_FRAME
    msg.child_frame_id = BASE_FRAME
    p = vec_I_to_map(state.xi_I)
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = map(float, p)
    q = quat_wxyz_to_xyzw(quat_from_rot(R_map_base))
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    v_base = R_map_base.T @ vec_I_to_map(state.v_I)
    w_base = vec_frd_to_flu(state.Omega_B)
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    lin.x, lin.y, lin.z = map(float, v_base)
    ang.x, ang.y, ang.z = map(float, w_base)
    return msg
