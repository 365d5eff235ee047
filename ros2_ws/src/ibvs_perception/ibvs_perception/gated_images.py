"""Which images a perception node computes: the frame grid and the modes that use them.

Every perception node hands its images to :meth:`GatedImages.on_images` instead of
processing them itself. From ``ibvs/frame_grid``: only every stride-th frame of this camera is
computed, the same in every node (ibvs_common.core.frame_grid; an optical-flow node follows
its camera's flow grid, sparser while the rate governor sheds the flows); from
``ibvs/supervisor_status``: the modes (:class:`~ibvs_perception.core.mode_gate.ModeGate`: a
product is computed only for the images of a mode that uses it, docs/interfaces.md "Mode
gating"); and latest only: a node that is behind computes the newest grid image it has taken
and skips the older ones taken with it (:class:`~ibvs_perception.camera_input.CameraInput`
takes those already waiting behind the one delivered), or one that
:class:`~ibvs_perception.core.latest_only.LatestOnly` says the next one has surely arrived
behind. Counts the frames it leaves out by the grid, those superseded and the grid frames that
never came (dropped on the way), and says so on ``/diagnostics``
(:mod:`ibvs_perception.image_diagnostics`); each grid image superseded is also published on
``ibvs/frames_superseded``, for the supervisor's rate governor.
"""
from __future__ import annotations

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Header, UInt8

from ibvs_common.core.frame_grid import FrameGrid, GridFollower
from ibvs_common.core.modes import InputKind, modes_using
from ibvs_common.node_common import (COMMAND_QOS, FRAME_QOS, grid_from_msg, MODE_QOS,
                                     mode_from_status, stamp_to_ns, superseded_msg,
                                     SUPERSEDED_TOPIC)
from ibvs_common.throttled_log import ThrottledLog
from ibvs_common.waiting_messages import take_waiting
from ibvs_perception.config import ImageInputConfig
from ibvs_perception.core.latest_only import LatestOnly
from ibvs_perception.core.mode_gate import ModeGate
from ibvs_perception.image_diagnostics import ImageCounts, ImageDiagnostics, ProcessingTimer

THROTTLE_S = 2.0


class GatedImages:
    """Route a node's images through a :class:`ModeGate` for the product ``kind``."""

    def __init__(self, node: Node, kind: InputKind,
                 process: Callable[[Image, bool], None], log_prefix: str,
                 config: ImageInputConfig, camera: str, period_ns: int,
                 flow: bool = False) -> None:
        self.gate = ModeGate(modes_using(kind), config.mode_gate_depth, config.mode_gating)
        self.latest = LatestOnly(config.latest)
        self.clock = node.get_clock()
        self.process = process
        self.prefix = log_prefix
        self.camera = camera
        self.flow = bool(flow)          # follow the camera's flow grid (an optical-flow node)
        self.follower = GridFollower(int(period_ns))
        self.counts = ImageCounts()
        self.timer = ProcessingTimer()
        self._last_index: int | None = None
        self.log = ThrottledLog(node.get_logger())
        self.diagnostics = ImageDiagnostics(node, log_prefix, self.counts, self.timer)
        # each grid image skipped for a newer one, told to the supervisor: its gap is the
        # computer's, not the camera's (ibvs_control's SupersededFrames)
        self._superseded_pub = node.create_publisher(Header, SUPERSEDED_TOPIC, COMMAND_QOS)
        # the grid, the latched mode and the statuses, in the order taken before an image
        self._control_subs = [(node.create_subscription(DiagnosticArray, 'ibvs/frame_grid',
                                                        self.on_grid, MODE_QOS), self.on_grid)]
        if config.mode_gating:
            # the supervisor's latched mode: the gate's state until its first status
            self._control_subs.append((node.create_subscription(
                UInt8, 'ibvs/mode', self.on_mode, MODE_QOS), self.on_mode))
            # the newest statuses only: behind a busy executor a deeper queue hands the gate
            # statuses 10 frames old, and a product switched on waits for them (a third of a
            # core: the wall flow started 0.5 s after WINDOW, which failed safe)
            self._control_subs.append((node.create_subscription(
                DiagnosticArray, 'ibvs/supervisor_status', self.on_status, FRAME_QOS),
                self.on_status))

    @property
    def grid(self) -> FrameGrid:
        """Return this camera's current frame grid: its stride and reference frame."""
        return self.follower.grid

    @property
    def frame_period_s(self) -> float:
        """Return the time between two frames this node computes: period times stride (s)."""
        return self.grid.period_ns * self.grid.stride / 1e9

    def on_images(self, images: list[Image], taken_ns: int | None = None) -> None:
        """Take the images taken at once (oldest first), each through :meth:`on_image`.

        A grid image with a newer grid image behind it in ``images`` is superseded.
        ``taken_ns``: when they were taken (ns, ROS clock; None: now). The frame grid, mode
        and statuses already waiting in their readers are taken first
        (:meth:`take_control_messages`).
        """
        self.take_control_messages()
        on_grid = [self.on_grid_at(stamp_to_ns(m.header.stamp)) for m in images]
        newest = max((i for i, ok in enumerate(on_grid) if ok), default=-1)
        for i, msg in enumerate(images):
            self.on_image(msg, newer_waiting=i < newest, taken_ns=taken_ns)

    def on_image(self, msg: Image, newer_waiting: bool = False,
                 taken_ns: int | None = None) -> None:
        """Take one image; ``newer_waiting``: a newer grid image has been taken behind it.

        Its age is judged at ``taken_ns`` (ns, ROS clock; None: now), the time the camera
        input took it: in a process whose camera feeds two nodes
        (:class:`~ibvs_perception.camera_input.SharedCameraInputs`), the second one's turn
        comes a processing time later, and judged then it would skip every frame the first
        one computes on a slow computer.
        """
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if taken_ns is None:
            taken_ns = self.clock.now().nanoseconds
        age_ns = int(taken_ns) - stamp_ns
        self.latest.observe(age_ns)
        if not self.on_grid_at(stamp_ns):
            self.counts.off_grid += 1
            return
        self._count_missed(stamp_ns)
        if self.gate.active_at(stamp_ns) and (newer_waiting or self.latest.superseded(
                age_ns, self.grid.period_ns * self.grid.stride)):
            self.counts.superseded += 1
            self._superseded_pub.publish(superseded_msg(self.camera, stamp_ns))
            return
        self._process_all(self.gate.on_image(stamp_ns, msg))

    def take_control_messages(self) -> None:
        """Apply the grid, mode and statuses waiting in their readers, before an image.

        Their events wait in the executor's queue behind the images that arrived before them:
        a node behind judged its images on a grid the supervisor had left (a sixth of a core:
        a stride-2 grid 80 ms late, frames computed that the supervisor dropped as off-grid).
        """
        for subscription, handler in self._control_subs:
            for msg in take_waiting(subscription):
                handler(msg)

    def _process_all(self, gated_items) -> None:
        for gated in gated_items:
            self.counts.computed += 1
            self.timer.run(self.process, gated.item, gated.publish)

    def _count_missed(self, stamp_ns: int) -> None:
        """Count the grid frames between this image and the last one (none came for them)."""
        period = self.grid.period_ns
        index = (stamp_ns + period // 2) // period            # frames since the clock's epoch
        if self._last_index is not None and index > self._last_index:
            self.counts.missed += max((index - self._last_index) // self.grid.stride - 1, 0)
        self._last_index = index

    def on_grid_at(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` is on the grid (the old one before a smaller one)."""
        return self.follower.on_grid_at(stamp_ns)

    def on_grid(self, msg: DiagnosticArray) -> None:
        """Take this camera's frame grid (ibvs/frame_grid: stride, reference frame).

        A smaller stride applies from its reference frame on, the old grid before it, as the
        supervisor expects them (ibvs_control's ``SupervisorGrids``).
        """
        grid = grid_from_msg(msg, self.camera, self.flow)
        if grid is None:
            self.log.error(f'{self.prefix}: ibvs/frame_grid without this camera: ignored',
                           THROTTLE_S)
            return
        self.follower.update(*grid)

    def on_mode(self, msg: UInt8) -> None:
        """Take the supervisor's latched mode (the gate's state until its first status)."""
        self.gate.on_mode(msg.data)

    def on_status(self, msg: DiagnosticArray) -> None:
        stamp_ns, mode, err = mode_from_status(msg)
        if err:
            self.log.error(f'{self.prefix}: ibvs/supervisor_status refused: {err}', THROTTLE_S)
            return
        dropped = self.gate.superseded
        released = self.gate.on_status(stamp_ns, mode)
        self.counts.superseded += self.gate.superseded - dropped
        self._process_all(released)
