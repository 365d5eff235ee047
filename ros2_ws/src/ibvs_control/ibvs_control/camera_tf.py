"""The cameras' mounts on ``/tf_static``, so that RViz and Foxglove show the cameras.

One tf2_msgs/TFMessage, published once at start with the QoS of tf2_ros's
StaticTransformBroadcaster (reliable, transient local, keep last 1: a late subscriber gets it),
holding one geometry_msgs/TransformStamped per camera of vehicle.yaml: ``base_link`` -> the
camera's optical frame (``ibvs_common.core.camera_tf``: frames, units, convention). The
mode supervisor publishes it (it derotates the bearings with the same mounts); no other node
of the graph, the sim included, publishes ``/tf_static``.

tf2_msgs is imported when publishing, not with the module: it is a Jazzy install's package
(rosdep key ``tf2_msgs``, ros-jazzy-tf2-msgs) that the PyPI wheels of the venv lack. Without
it one warning is logged and nothing is published; the node runs on.
"""
from __future__ import annotations

from typing import Iterable

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ibvs_common.core.camera_tf import camera_transforms, StaticTransform
from ibvs_common.core.config import CameraConfig

TF_STATIC_TOPIC = '/tf_static'
# tf2_ros.StaticTransformBroadcaster's StaticLatchedQoS: depth 1, transient local, reliable
TF_STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL,
                           history=HistoryPolicy.KEEP_LAST)
TF2_MSGS_MISSING = ('tf2_msgs not installed: camera frames not published on /tf_static; '
                    'install ros-jazzy-tf2-msgs')


def transform_msgs(transforms: Iterable[StaticTransform], stamp_ns: int
                   ) -> list[TransformStamped]:
    """Return one geometry_msgs/TransformStamped per transform, stamped ``stamp_ns``."""
    out = []
    for tf in transforms:
        msg = TransformStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg.header.frame_id = tf.parent
        msg.child_frame_id = tf.child
        t, r = msg.transform.translation, msg.transform.rotation
        t.x, t.y, t.z = (float(v) for v in tf.translation)
        r.x, r.y, r.z, r.w = (float(v) for v in tf.q_xyzw)
        out.append(msg)
    return out


def camera_transform_msgs(node: Node, cameras: Iterable[CameraConfig]
                          ) -> list[TransformStamped]:
    """Return the cameras' TransformStamped (``base_link`` -> optical), stamped node-now."""
    return transform_msgs(camera_transforms(cameras), node.get_clock().now().nanoseconds)


def publish_camera_tf(node: Node, cameras: Iterable[CameraConfig]) -> Publisher | None:
    """Publish the cameras' mounts on ``/tf_static`` once, in one TFMessage (module doc).

    Returns the publisher (keep it: its transient-local history is what late subscribers
    get), or None when tf2_msgs is not installed (one warning logged).
    """
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        node.get_logger().warning(TF2_MSGS_MISSING)
        return None
    transforms = camera_transform_msgs(node, cameras)
    publisher = node.create_publisher(TFMessage, TF_STATIC_TOPIC, TF_STATIC_QOS)
    publisher.publish(TFMessage(transforms=transforms))
    node.get_logger().info(f'camera frames on {TF_STATIC_TOPIC}: ' + ', '.join(
        f'{m.header.frame_id} -> {m.child_frame_id}' for m in transforms))
    return publisher
