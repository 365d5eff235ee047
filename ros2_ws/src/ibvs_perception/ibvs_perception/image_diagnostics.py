"""A perception node's images on ``/diagnostics``: what it computed, left out and lost.

Once a second (ROS clock) a node publishes one DiagnosticStatus named ``<node>: images`` with
its counters since start (:class:`ImageCounts`): images computed, left out by the frame grid,
grid frames that never came (dropped on the way, or overwritten in the subscription's queue
while the node was behind), grid images superseded (skipped by a node behind for the newer one
behind them, :mod:`ibvs_perception.core.latest_only`), images computed without an IMU
attitude, and the median
processing time over the last second (steady clock). WARN while grid frames are lost or
attitudes are missing. Not on the flight path: the counts only report.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rclpy.node import Node

from ibvs_common.node_common import COMMAND_QOS

DIAGNOSTICS_PERIOD_S = 1.0          # s (ROS clock) between two /diagnostics
TIMES_KEPT = 200                    # processing times kept for the median
STATUS_SUFFIX = ': images'          # a node's status is named '<node>: images'


def image_status_name(node_name: str) -> str:
    """Return the name of ``node_name``'s image status on /diagnostics."""
    return node_name + STATUS_SUFFIX


@dataclass
class ImageCounts:
    """A node's image counters since start."""

    computed: int = 0          # images handed to the node's processing
    off_grid: int = 0          # left out: not on the frame grid
    missed: int = 0            # grid frames that never came
    superseded: int = 0        # grid images skipped: the next one had come (a node behind)
    no_attitude: int = 0       # computed without an IMU attitude at the image stamp


class ProcessingTimer:
    """Steady-clock duration of each processing call; the median of the recent ones."""

    def __init__(self) -> None:
        self._ms: deque = deque(maxlen=TIMES_KEPT)

    def run(self, process: Callable[..., None], *args) -> None:
        """Call ``process(*args)`` and keep its duration."""
        t0 = time.perf_counter()
        try:
            process(*args)
        finally:
            self._ms.append(1e3 * (time.perf_counter() - t0))

    def median_ms(self) -> float | None:
        """Return the median of the kept durations (ms), None before the first call."""
        return float(np.median(self._ms)) if self._ms else None


def image_status(name: str, counts: ImageCounts, previous: ImageCounts,
                 median_ms: float | None) -> DiagnosticStatus:
    """Build the ``<name>: images`` status from the counts and those of the last status."""
    lost = counts.missed - previous.missed
    blind = counts.no_attitude - previous.no_attitude
    values = {'images_computed': counts.computed, 'images_off_grid': counts.off_grid,
              'grid_frames_missed': counts.missed, 'images_superseded': counts.superseded,
              'images_without_attitude': counts.no_attitude,
              'processing_median_ms': 'unknown' if median_ms is None else f'{median_ms:.1f}'}
    degraded = lost > 0 or blind > 0
    return DiagnosticStatus(
        level=DiagnosticStatus.WARN if degraded else DiagnosticStatus.OK,
        name=image_status_name(name), hardware_id='companion computer',
        message=(f'{lost} grid frame(s) lost, {blind} image(s) without attitude in the last '
                 'period' if degraded else 'every grid frame computed'),
        values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])


class ImageDiagnostics:
    """Publish a node's :class:`ImageCounts` on ``/diagnostics`` once a second (ROS clock)."""

    def __init__(self, node: Node, name: str, counts: ImageCounts,
                 timer: ProcessingTimer) -> None:
        self.node, self.name, self.counts, self.timer = node, name, counts, timer
        self._previous = ImageCounts()
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', COMMAND_QOS)
        node.create_timer(DIAGNOSTICS_PERIOD_S, self.publish)

    def publish(self) -> None:
        """Publish the counts, and keep them for the next period's differences."""
        msg = DiagnosticArray(status=[image_status(self.name, self.counts, self._previous,
                                                   self.timer.median_ms())])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)
        self._previous = replace(self.counts)
