"""rosbag2 bags of a run, ROS-free (rosbags library): MCAP storage, CDR, Jazzy typestore.

The recorder node hands serialized CDR bytes (rclpy ``raw=True``) to ``BagWriter``; the bag
player and the tests read them back with ``read_messages``. Bags are rosbag2 version 8 with a
``metadata.yaml`` as rosbags writes it, which both ``ros2 bag info/play`` on Jazzy and rosbags
read.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

BAG_VERSION = 8          # rosbag2 metadata version understood by Jazzy's rosbag2 (0.26)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class TopicSpec:
    """One recorded topic: name (as published, relative), ROS 2 type and whether it is an image."""

    topic: str
    msgtype: str            # 'sensor_msgs/msg/Image'
    image: bool = False


# What a run records: both cameras, IMU, detections, flows, features, setpoints, mode and
# ground truth (docs/spec.md section 4 plus the extra topics of docs/interfaces.md).
RUN_TOPICS: tuple = tuple(
    [TopicSpec(f'{c}_camera/image_raw', 'sensor_msgs/msg/Image', True) for c in ('front', 'down')]
    + [TopicSpec(f'{c}_camera/camera_info', 'sensor_msgs/msg/CameraInfo')
       for c in ('front', 'down')]
    + [TopicSpec(f'{c}_camera/translational_flow', 'geometry_msgs/msg/Vector3Stamped')
       for c in ('front', 'down')]
    + [TopicSpec(f'{c}_camera/translational_flow_quality', 'std_msgs/msg/Float32')
       for c in ('front', 'down')]
    + [TopicSpec('imu/data', 'sensor_msgs/msg/Imu'),
       TopicSpec('window/corners', 'geometry_msgs/msg/PolygonStamped'),
       TopicSpec('window/edge_normals', 'geometry_msgs/msg/PolygonStamped'),
       TopicSpec('pad/landmarks', 'geometry_msgs/msg/PolygonStamped'),
       TopicSpec('pad/groups', 'sensor_msgs/msg/JointState'),
       TopicSpec('ibvs/features', 'sensor_msgs/msg/JointState'),
       TopicSpec('ibvs/force_setpoint', 'geometry_msgs/msg/Vector3Stamped'),
       TopicSpec('ibvs/heading_setpoint', 'geometry_msgs/msg/QuaternionStamped'),
       TopicSpec('ibvs/mode', 'std_msgs/msg/UInt8'),
       TopicSpec('sim/ground_truth/odom', 'nav_msgs/msg/Odometry'),
       TopicSpec('sim/events', 'std_msgs/msg/String')])


def qos_profile(reliable: bool, transient_local: bool, depth: int = 10) -> Qos:
    """Return a rosbag2 QoS record (for metadata ``offered_qos_profiles``)."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def bag_topic_name(topic: str) -> str:
    """Return the absolute name a relative topic has in a bag (``ros2 bag`` stores FQNs)."""
    return topic if topic.startswith('/') else '/' + topic


class BagWriter:
    """Write serialized messages into a new MCAP rosbag2 directory (context manager)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict = {}

    def add_topic(self, topic: str, msgtype: str, qos: Iterable[Qos] = ()) -> None:
        """Register a topic (once); ``qos`` is what its publishers offer."""
        name = bag_topic_name(topic)
        if name not in self._connections:
            self._connections[name] = self._writer.add_connection(
                name, msgtype, typestore=TYPESTORE, offered_qos_profiles=list(qos))

    def write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Write one CDR-serialized message received at ``stamp_ns``."""
        self._writer.write(self._connections[bag_topic_name(topic)], int(stamp_ns), data)

    def close(self) -> None:
        """Finish the MCAP file and write metadata.yaml."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class BagError(ValueError):
    """A path that is not a readable rosbag2 folder (the message says why and what to do)."""


def open_reader(path: str | Path) -> Reader:
    """Return an (unopened) rosbags Reader of a rosbag2 folder; BagError with the reason."""
    folder = Path(path)
    if not folder.exists():
        raise BagError(f'bag {str(folder)!r} does not exist')
    if not folder.is_dir():
        raise BagError(f'bag {str(folder)!r} is a file: give the rosbag2 folder that holds it '
                       'and its metadata.yaml')
    if not (folder / 'metadata.yaml').is_file():
        raise BagError(f'bag folder {str(folder)!r} has no metadata.yaml: it is not a rosbag2 '
                       'bag as recorded (`ros2 bag reindex` rebuilds the file from the storage '
                       'files on a ROS install)')
    try:
        return Reader(folder)
    except Exception as exc:          # rosbags' ReaderError and YAML errors: one clear type
        raise BagError(f'bag {str(folder)!r} cannot be read: {exc}') from exc


@contextlib.contextmanager
def _opened(path: str | Path) -> Iterator[Reader]:
    """Open a bag for reading (BagError with the reason), close it after the block."""
    reader = open_reader(path)
    try:
        reader.open()
    except Exception as exc:
        raise BagError(f'bag {str(path)!r} cannot be read: {exc}') from exc
    try:
        yield reader
    finally:
        reader.close()


def read_messages(path: str | Path, topics: Iterable[str] | None = None
                  ) -> Iterator[tuple[str, str, int, bytes]]:
    """Yield (topic, msgtype, bag time ns, CDR bytes) in bag-time order."""
    wanted = None if topics is None else {bag_topic_name(t) for t in topics}
    with _opened(path) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, t_ns, data in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t_ns, bytes(data)


def deserialize(data: bytes, msgtype: str) -> Any:
    """Return the rosbags message object of CDR ``data``."""
    return TYPESTORE.deserialize_cdr(data, msgtype)


def serialize(msg: object, msgtype: str) -> bytes:
    """Return the CDR bytes of a rosbags message object."""
    return bytes(TYPESTORE.serialize_cdr(msg, msgtype))


def topic_types(path: str | Path) -> dict:
    """Return {topic: msgtype} of a bag."""
    with _opened(path) as reader:
        return {c.topic: c.msgtype for c in reader.connections}


def topic_counts(path: str | Path) -> dict:
    """Return {topic: message count} of a bag (from its metadata)."""
    with _opened(path) as reader:
        return {c.topic: c.msgcount for c in reader.connections}
