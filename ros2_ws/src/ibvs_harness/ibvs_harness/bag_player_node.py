"""Bag player node: replays recorded sensor topics (rosbags), like ``ros2 bag play``.

Publishes the serialized messages unchanged (original header stamps) on their recorded topic
names, paced by bag time times ``rate``, and publishes ``/clock`` from bag time if ``clock`` is
true, so that perception nodes under ``use_sim_time`` see the original time line.

Parameters (:class:`BagPlayerNodeConfig`, docs/parameters.md): ``bag_path`` (required),
``topics`` (default: both cameras' image_raw and camera_info, and imu/data), ``rate``
(default 1.0), ``clock`` (default true), ``start_delay`` (s of wall time before the first
message, to let subscribers match; default 1.0), ``image_delay_s`` (images published that
long after their place in the bag, as a camera delivers them after the IMU; default 0).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
import time

from builtin_interfaces.msg import Time
from ibvs_harness import bag
from ibvs_harness.recorder_node import msg_class
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from ibvs_common.dds_profile import use_dds_profile_here
from ibvs_common.core.params import param
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from rosgraph_msgs.msg import Clock

INFO_SUFFIX = 'camera_info'
IMAGE_SUFFIX = 'image_raw'
PRIME_LEAD_S = 0.5            # s (wall) before playback: first CameraInfo of each camera
REPLAY_TOPICS = ('front_camera/image_raw', 'down_camera/image_raw', 'front_camera/camera_info',
                 'down_camera/camera_info', 'imu/data')


@dataclass(frozen=True)
class BagPlayerNodeConfig:
    """Parameters of the ``bag_player`` tool node."""

    bag_path: str = param('', 'rosbag2 folder to play; required')
    topics: list = param(list(REPLAY_TOPICS), 'relative topic names to play')
    rate: float = param(1.0, 'bag time / wall time (0: 1.0)', 0.0)
    clock: bool = param(True, 'publish /clock from the bag time')
    start_delay: float = param(1.0, 's (wall, steady clock) before the first message', 0.0)
    image_delay_s: float = param(
        0.0, 's (wall, steady clock): each image is published this long after its place in the '
        'bag, the other topics at theirs, as a camera driver delivers an image after the IMU '
        'samples of its stamp (a replay on a busy machine otherwise hands a node an image '
        'before the IMU sample it needs, and the node answers with a propagated attitude)',
        0.0)


class BagPlayerNode(Node):
    """Publish a bag's messages in bag-time order, then report done."""

    def __init__(self, **kwargs) -> None:
        super().__init__('bag_player', **kwargs)
        self.config = self._declare_config()
        types = bag.topic_types(self.config.bag_path)
        self.pubs = {topic: self.create_publisher(msg_class(msgtype), topic, _qos(topic))
                     for topic, msgtype in types.items()
                     if topic in {bag.bag_topic_name(t) for t in self.config.topics}}
        self.clock_pub = self.create_publisher(Clock, '/clock', 10)
        self.stream = bag.read_messages(self.config.bag_path, self.config.topics)
        self.pending = next(self.stream, None)
        self.published = 0
        self.delayed: deque = deque()         # (wall time due, topic, data): images held back
        self.t0_wall = time.monotonic() + self.config.start_delay
        self.t0_bag = self.pending[2] if self.pending else 0
        # each camera's first CameraInfo, published PRIME_LEAD_S before playback: the detectors
        # drop an image that arrives before any CameraInfo, and at the bag's first stamp the
        # image and its info race on different topics
        self.primes = first_messages(self.config.bag_path,
                                     [t for t in self.config.topics if t.endswith(INFO_SUFFIX)])
        self.timer = self.create_timer(0.002, self._tick)
        self.get_logger().info(f'playing {sorted(self.pubs)} of {self.config.bag_path}')

    def _declare_config(self) -> BagPlayerNodeConfig:
        cfg = declare_config(self, BagPlayerNodeConfig)
        if not cfg.bag_path:
            raise ValueError('parameter bag_path is required')
        return replace(cfg, rate=cfg.rate if cfg.rate > 0 else 1.0)

    def _tick(self) -> None:
        if self.primes and time.monotonic() >= self.t0_wall - PRIME_LEAD_S:
            for topic, data in self.primes:
                self.pubs[topic].publish(data)
            self.primes = []
        elapsed_ns = (time.monotonic() - self.t0_wall) * 1e9 * self.config.rate
        while self.pending is not None and self.pending[2] - self.t0_bag <= elapsed_ns:
            topic, _, t_ns, data = self.pending
            if self.config.clock:
                self.clock_pub.publish(Clock(clock=Time(sec=t_ns // 10**9,
                                                        nanosec=t_ns % 10**9)))
            if self.config.image_delay_s > 0.0 and topic.endswith(IMAGE_SUFFIX):
                self.delayed.append((time.monotonic() + self.config.image_delay_s, topic, data))
            else:
                self._publish(topic, data)
            self.pending = next(self.stream, None)
        while self.delayed and self.delayed[0][0] <= time.monotonic():
            self._publish(*self.delayed.popleft()[1:])
        if self.pending is None and not self.delayed:
            self.timer.cancel()
            self.get_logger().info(f'bag finished: {self.published} messages')

    def _publish(self, topic: str, data) -> None:
        self.pubs[topic].publish(data)
        self.published += 1


def first_messages(path: str, topics: list) -> list[tuple[str, bytes]]:
    """Return (bag topic, CDR bytes) of the first message of each of ``topics`` in a bag."""
    first: dict = {}
    if topics:
        for topic, _, _, data in bag.read_messages(path, topics):
            first.setdefault(topic, data)
            if len(first) == len(topics):
                break
    return list(first.items())


def _qos(topic: str) -> QoSProfile:
    if topic.endswith('image_raw'):
        return qos_profile_sensor_data
    return QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


def main(args: list[str] | None = None) -> None:
    """Play the bag once, then keep the node alive until Ctrl-C / SIGTERM."""
    # the images' shared-memory segment is the player's: lossless under a plain `ros2 run` too
    use_dds_profile_here()
    run_node(BagPlayerNode, 'bag_player', args)


if __name__ == '__main__':
    main()
