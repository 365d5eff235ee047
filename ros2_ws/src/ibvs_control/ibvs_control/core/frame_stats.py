"""What the supervisor reports of the frames on /diagnostics: rate held, skipped, late (ROS-free).

Counted per frame of the mode's camera: complete frames (evaluated and flown), skipped ones
(a product the mode needs did not come by the deadline) by the product that was missing,
grid frames no product came for at all (missed: a node behind took a newer image; of them
undelivered: no node reported skipping the image, the camera never delivered it),
products dropped because their frame had been skipped (late), and products of frames off the
frame grid. The control rate held is the complete frames per second of stamps over the last
second; the delivery latency is the ROS time at a frame's first product minus its stamp
(capture to arrival plus the fastest node's computing). Times in ns of the ROS clock.
"""
from __future__ import annotations

from collections import Counter, deque

import numpy as np

RATE_WINDOW_NS = 1_000_000_000        # the control rate is counted over this much of stamps
LATENCY_SAMPLES = 50


class FrameStats:
    """Counters and recent samples of the frames of the mode's camera."""

    def __init__(self) -> None:
        self.complete = 0
        self.skipped = 0
        self.skipped_without: Counter = Counter()      # missing product name -> frames
        self.late_dropped = 0
        self.off_grid_dropped = 0
        self.missed = 0               # grid frames no product came for (a node behind)
        self.undelivered = 0          # ... of which no node reported skipping the image
        self._complete_stamps: deque[int] = deque()
        self._skipped_stamps: deque[int] = deque()
        self._delivery_ns: dict[str, deque] = {}

    def frame(self, stamp_ns: int, missing: tuple[str, ...] = ()) -> None:
        """Count one released frame; ``missing``: the products it lacked (empty: complete)."""
        if missing:
            self.skipped += 1
            self.skipped_without.update(missing)
            self._skipped_stamps.append(int(stamp_ns))
        else:
            self.complete += 1
            self._complete_stamps.append(int(stamp_ns))

    def opened(self, camera: str, stamp_ns: int, now_ns: int) -> None:
        """Note a frame's first product arriving at ``now_ns`` (delivery latency)."""
        samples = self._delivery_ns.setdefault(camera, deque(maxlen=LATENCY_SAMPLES))
        samples.append(int(now_ns) - int(stamp_ns))

    def rate_hz(self, newest_ns: int) -> float:
        """Return the complete frames per second over the second of stamps up to ``newest_ns``."""
        self._trim(newest_ns)
        return len(self._complete_stamps) * 1e9 / RATE_WINDOW_NS

    def skipped_recently(self, newest_ns: int) -> int:
        """Return the frames skipped over the second of stamps up to ``newest_ns``."""
        self._trim(newest_ns)
        return len(self._skipped_stamps)

    def delivery_ms(self, camera: str) -> float | None:
        """Return the median delivery latency of the camera's recent frames (ms), or None."""
        samples = self._delivery_ns.get(camera)
        return float(np.median(samples)) / 1e6 if samples else None

    def _trim(self, newest_ns: int) -> None:
        for stamps in (self._complete_stamps, self._skipped_stamps):
            while stamps and stamps[0] <= newest_ns - RATE_WINDOW_NS:
                stamps.popleft()

    def values(self, newest_ns: int, stride: int, camera: str,
               flow_stride: int = 1) -> dict[str, str]:
        """Return what /diagnostics shows, as key -> string.

        ``flow_stride``: the mode camera's flow is computed on every ``flow_stride``-th frame
        of the grid and held between (the rate governor sheds it).
        """
        delivery = {c: self.delivery_ms(c) for c in sorted(self._delivery_ns)}
        out = {'camera': camera, 'frame_stride': str(stride), 'flow_stride': str(flow_stride),
               'control_rate_hz': f'{self.rate_hz(newest_ns):.1f}',
               'frames_skipped_last_s': str(self.skipped_recently(newest_ns)),
               'frames_complete': str(self.complete), 'frames_skipped': str(self.skipped),
               'late_products_dropped': str(self.late_dropped),
               'off_grid_products_dropped': str(self.off_grid_dropped),
               'frames_missed': str(self.missed),
               'frames_undelivered': str(self.undelivered)}
        for name, n in sorted(self.skipped_without.items()):
            out[f'frames_skipped_without_{name}'] = str(n)
        for cam, ms in delivery.items():
            out[f'{cam}_delivery_latency_ms'] = 'unknown' if ms is None else f'{ms:.1f}'
        return out
