"""The node side of mode gating (parameters, the supervisor-status subscription; no maths).

Every perception node hands its images to :meth:`GatedImages.on_image` instead of processing
them itself: :class:`~ibvs_perception.core.mode_gate.ModeGate` decides, from the modes on
``ibvs/supervisor_status``, which ones the node's ``process(msg, publish)`` gets (docs/
interfaces.md, "Mode gating"). The product's modes come from the one mode table,
``ibvs_common.core.modes.MODE_INPUTS``.
"""
from __future__ import annotations

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Image

from ibvs_common.core.modes import InputKind, modes_using
from ibvs_common.node_common import COMMAND_QOS, mode_from_status, stamp_to_ns
from ibvs_common.throttled_log import ThrottledLog
from ibvs_perception.core.mode_gate import ModeGate

THROTTLE_S = 2.0


class GatedImages:
    """Route a node's images through a :class:`ModeGate` for the product ``kind``."""

    def __init__(self, node: Node, kind: InputKind,
                 process: Callable[[Image, bool], None], log_prefix: str,
                 enabled: bool, depth: int) -> None:
        self.gate = ModeGate(modes_using(kind), depth, enabled)
        self.process = process
        self.prefix = log_prefix
        self.log = ThrottledLog(node.get_logger())
        if enabled:
            node.create_subscription(DiagnosticArray, 'ibvs/supervisor_status',
                                     self.on_status, COMMAND_QOS)

    def on_image(self, msg: Image) -> None:
        for gated in self.gate.on_image(stamp_to_ns(msg.header.stamp), msg):
            self.process(gated.item, gated.publish)

    def on_status(self, msg: DiagnosticArray) -> None:
        stamp_ns, mode, err = mode_from_status(msg)
        if err:
            self.log.error(f'{self.prefix}: ibvs/supervisor_status refused: {err}', THROTTLE_S)
            return
        for gated in self.gate.on_status(stamp_ns, mode):
            self.process(gated.item, gated.publish)
