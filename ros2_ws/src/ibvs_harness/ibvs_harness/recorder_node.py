"""Recorder node: writes the run's topics, as serialized CDR, into an MCAP rosbag2 bag.

Like ``ros2 bag record``: each topic is subscribed once a publisher appears, with a QoS
compatible with what the publishers offer (reliable / transient-local only when all offer it),
and messages are stamped with the receive time on the node's clock (sim time under
``use_sim_time``). Images can be decimated (``image_every``) to keep bags small, and capped
(``max_image_mb``): two 752x480 mono8 cameras at 50 Hz write 36 MB/s, which fills an
onboard computer's SD card in minutes. Past the cap the images are no longer written (said
once in the log); every other topic goes on, so a long day on the vehicle keeps its
telemetry. A free-disk floor (``min_free_disk_mb``, checked every ``DISK_CHECK_PERIOD_S``)
ends the recording before the disk fills: the bag is closed while there is room for its
metadata, said once as an error, and nothing more is written; a write that fails (a full
disk, an I/O error) ends it the same way. The recorder never raises for it: the flight path
does not depend on it. With ``split_s`` the recording is split in time: ``bag_path`` is then
a folder of bags ``part_000``, ``part_001``, ..., each closed (readable) when the next one
starts, so that a power cut loses only the part being written.

Parameters (:class:`RecorderNodeConfig`, docs/parameters.md): ``bag_path`` (required, must
not exist), ``image_every`` (int, default 1), ``max_image_mb`` (0: no cap),
``min_free_disk_mb`` (0: no floor), ``split_s`` (0: one bag), ``topics`` (list of relative
names; default: every topic of ``bag.RUN_TOPICS``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import importlib
import os
import shutil

from ibvs_harness import bag
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ibvs_common.core.params import param
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node

DISCOVERY_PERIOD_S = 0.2      # s (steady clock), how often new publishers are looked for
DISK_CHECK_PERIOD_S = 1.0     # s (steady clock), how often the free disk space is checked


@dataclass(frozen=True)
class RecorderNodeConfig:
    """Parameters of the ``recorder`` tool node."""

    bag_path: str = param('', 'new directory of the bag (must not exist); required')
    image_every: int = param(
        1, 'record every N-th message of the image_raw topics (0 or 1: every one)', 0)
    max_image_mb: float = param(
        0.0, 'MB (10^6 bytes) of image messages after which the image topics are no longer '
        'recorded (the other topics are); 0: no cap', 0.0)
    min_free_disk_mb: float = param(
        500.0, 'MB (10^6 bytes) free on the bag\'s file system below which the recording ends '
        '(the bag closed, nothing more written; checked every second, steady clock); 0: no '
        'floor', 0.0)
    split_s: float = param(
        0.0, 's (steady clock): start a new bag this often; bag_path is then a folder of '
        'bags part_000, part_001, ..., each closed and readable when the next starts (a power '
        'cut loses only the part being written); 0: one bag', 0.0)
    topics: list = param([t.topic for t in bag.RUN_TOPICS],
                         'relative topic names to record (default: all of bag.RUN_TOPICS)')


def msg_class(msgtype: str) -> type:
    """Return the rclpy message class of 'pkg/msg/Name'."""
    pkg, _, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.msg'), name)


def subscription_qos(offered: list) -> tuple[QoSProfile, list]:
    """Return the QoS to subscribe with, and the offered profiles as rosbags records."""
    reliable = bool(offered) and all(
        q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    qos = QoSProfile(depth=100,
                     reliability=ReliabilityPolicy.RELIABLE if reliable
                     else ReliabilityPolicy.BEST_EFFORT,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                     else DurabilityPolicy.VOLATILE)
    records = [bag.qos_profile(q.reliability == ReliabilityPolicy.RELIABLE,
                               q.durability == DurabilityPolicy.TRANSIENT_LOCAL,
                               max(1, q.depth)) for q in offered]
    return qos, records


class RecorderNode(Node):
    """Subscribe to the run topics as they appear and write their CDR bytes to a bag."""

    def __init__(self, **kwargs) -> None:
        super().__init__('recorder', **kwargs)
        self.config = self._declare_config()
        self.parts = 0                # bags written so far (split_s)
        self.records: dict = {}       # topic -> (msgtype, offered QoS), for each new part
        if self.config.split_s > 0.0:
            os.makedirs(self.config.bag_path)          # a folder of parts; must not exist
        self.writer = bag.BagWriter(self._part_path())
        self.specs = {t.topic: t for t in bag.RUN_TOPICS if t.topic in self.config.topics}
        self.subs: dict = {}
        self.counts: dict = {}
        self.image_bytes = 0          # image bytes written
        self.images_over_cap = 0      # image messages not written: past max_image_mb
        self.stopped = ''             # why the recording ended early ('' while recording)
        self.not_written = 0          # messages received after it ended
        # steady clock: under use_sim_time a sim-time timer would not fire before the first
        # /clock, and the first frames would go unrecorded
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.discovery_timer = self.create_timer(DISCOVERY_PERIOD_S, self._discover,
                                                 clock=steady)
        self.disk_timer = self.create_timer(DISK_CHECK_PERIOD_S, self._check_disk, clock=steady)
        if self.config.split_s > 0.0:
            self.split_timer = self.create_timer(self.config.split_s, self._split, clock=steady)
        self._check_disk()
        self.get_logger().info(f'recording {len(self.specs)} topics to {self.config.bag_path}')

    def _declare_config(self) -> RecorderNodeConfig:
        cfg = declare_config(self, RecorderNodeConfig)
        if not cfg.bag_path:
            raise ValueError('parameter bag_path is required')
        return replace(cfg, image_every=max(1, cfg.image_every))

    def _discover(self) -> None:
        if self.stopped:                     # the bag is closed: no new topic
            return
        for topic, spec in self.specs.items():
            if topic in self.subs:
                continue
            offered = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            if offered:
                self._subscribe(spec, offered)

    def _part_path(self) -> str:
        """Return the path of the next bag: bag_path, or its next part with split_s."""
        path = self.config.bag_path
        if self.config.split_s > 0.0:
            path = os.path.join(path, f'part_{self.parts:03d}')
        self.parts += 1
        return path

    def _split(self) -> None:
        """Close the bag being written and go on in a new part with the same topics."""
        if self.stopped:
            return
        try:
            self.writer.close()
            self.writer = bag.BagWriter(self._part_path())
            for topic, (msgtype, records) in self.records.items():
                self.writer.add_topic(topic, msgtype, records)
        except OSError as exc:
            self._stop(f'starting part {self.parts - 1} failed ({exc})')

    def _subscribe(self, spec: bag.TopicSpec, offered: list) -> None:
        qos, records = subscription_qos(offered)
        self.records[spec.topic] = (spec.msgtype, records)
        self.writer.add_topic(spec.topic, spec.msgtype, records)
        self.counts[spec.topic] = 0
        self.subs[spec.topic] = self.create_subscription(
            msg_class(spec.msgtype), spec.topic,
            lambda data, s=spec: self._on_message(s, data), qos, raw=True)

    def _on_message(self, spec: bag.TopicSpec, data: bytes) -> None:
        n = self.counts[spec.topic]
        self.counts[spec.topic] = n + 1
        if self.stopped:
            self.not_written += 1
            return
        if spec.image and n % self.config.image_every:
            return
        if spec.image and self._over_cap(len(data)):
            return
        try:
            self.writer.write(spec.topic, self.get_clock().now().nanoseconds, data)
        except OSError as exc:
            self._stop(f'writing {spec.topic} failed ({exc})')

    def _check_disk(self) -> None:
        """End the recording when the bag's file system has less than min_free_disk_mb free."""
        floor = self.config.min_free_disk_mb * 1e6
        if self.stopped or floor <= 0.0:
            return
        try:
            free = shutil.disk_usage(self.writer.path).free
        except OSError as exc:
            self._stop(f'the free disk space cannot be read ({exc})')
            return
        if free < floor:
            self._stop(f'{free / 1e6:.0f} MB free on the disk, below min_free_disk_mb '
                       f'({self.config.min_free_disk_mb:g})')

    def _stop(self, why: str) -> None:
        """End the recording for good: close the bag (if it still can), say why once."""
        self.stopped = why
        error = self._close_writer()
        if error:
            why += f'; {error}'
        self.get_logger().error(f'recorder: recording ended: {why}; the bag '
                                f'{self.config.bag_path} holds what came before')

    def _over_cap(self, size: int) -> bool:
        """Count an image of ``size`` bytes; True when it would pass ``max_image_mb``."""
        cap = self.config.max_image_mb * 1e6
        if cap > 0.0 and self.image_bytes + size > cap:
            if not self.images_over_cap:
                self.get_logger().warning(
                    f'recorder: {self.image_bytes / 1e6:.0f} MB of images written: '
                    f'max_image_mb ({self.config.max_image_mb:g}) reached, images are no '
                    'longer recorded (the other topics are)')
            self.images_over_cap += 1
            return True
        self.image_bytes += size
        return False

    def _close_writer(self) -> str:
        """Close the bag being written (its metadata.yaml); '' or why it could not be."""
        try:
            self.writer.close()
        except OSError as exc:
            return f'the bag could not be closed ({exc})'
        return ''

    def destroy_node(self) -> None:
        """Close the bag before the node goes."""
        error = self._close_writer()
        if error:
            self.get_logger().error(f'recorder: {error}')
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the recorder until Ctrl-C / SIGTERM; the bag is closed either way."""
    run_node(RecorderNode, 'recorder', args)
