"""Mode gating: a perception product is computed only for the frames of a mode that uses it.

The pad detector and the floor flow are not used before the window is crossed, the window
detector and the wall flow not after (``ibvs_common.core.modes.MODE_INPUTS``): computing them
anyway costs an onboard computer a third of its CPU (docs/performance.md). The modes come from
the supervisor's ``ibvs/supervisor_status``, one per evaluated frame, stamped with it.

Rule (:class:`ModeGate`), with stamps on the ROS clock in integer nanoseconds:

- The mode in force at an image stamp t is that of the newest status with a stamp <= t
  among those received. Before any status every image is processed (a replay without a
  supervisor, a node started alone); so is every image when gating is disabled.
- An image whose mode does not use the product is kept (the newest ``depth``), unprocessed.
- A status at stamp t_s that turns the product on releases at once the kept images with a
  stamp >= t_s, in stamp order, each to be processed and published, preceded by the newest
  kept image older than t_s, to be processed but not published: a tracker (the flow) needs
  its previous frame. The other kept images are dropped.

So the images processed from a switch on are the same whether an image or the status of the
same stamp arrives first; in a lockstep simulation, where the status of frame k is published
before the sim renders frame k + 1, runs repeat. Onboard, the first frames after a switch are
answered when the status arrives (one supervisor latency, a few ms, later).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Iterable

#: activity changes remembered, to find the mode in force at a late image's stamp
CHANGE_HISTORY = 8


@dataclass(frozen=True)
class GatedImage:
    """An image released by the gate: process it; publish the result only if ``publish``."""

    stamp_ns: int
    item: Any
    publish: bool


class ModeGate:
    """Which images of one camera a perception node processes, from the supervisor's modes."""

    def __init__(self, active_modes: Iterable[int], depth: int = 4,
                 enabled: bool = True) -> None:
        """Gate for a product used in ``active_modes`` (mode numbers); keep ``depth`` images."""
        if int(depth) < 2:
            raise ValueError(f'depth must be >= 2 (an image and its predecessor), got {depth}')
        self.active_modes = frozenset(int(m) for m in active_modes)
        self.enabled = bool(enabled)
        self._kept: deque = deque(maxlen=int(depth))      # (stamp_ns, item), oldest first
        self._changes: deque = deque(maxlen=CHANGE_HISTORY)   # (stamp_ns, active)

    @property
    def active(self) -> bool:
        """Whether the newest known mode uses the product (True before any status)."""
        return not self._changes or self._changes[-1][1]

    def active_at(self, stamp_ns: int) -> bool:
        """Whether the mode in force at ``stamp_ns`` (newest status <= it) uses the product."""
        if not self.enabled:
            return True
        for t, active in reversed(self._changes):
            if t <= stamp_ns:
                return active
        # older than every change: the activity before the first one (on, before any status)
        return not self._changes or not self._changes[0][1]

    def on_image(self, stamp_ns: int, item: Any) -> list[GatedImage]:
        """Take one image: [it] to process now, or [] when kept for a possible switch."""
        if self.active_at(stamp_ns):
            return [GatedImage(stamp_ns, item, True)]
        self._kept.append((stamp_ns, item))
        return []

    def on_status(self, stamp_ns: int, mode: int) -> list[GatedImage]:
        """Take the mode of the frame at ``stamp_ns``; return the images a switch on releases."""
        if not self.enabled:
            return []
        active = int(mode) in self.active_modes
        if active == self.active:
            return []
        if self._changes and stamp_ns < self._changes[-1][0]:
            return []             # older than the last switch: the supervisor releases in order
        self._changes.append((stamp_ns, active))
        if not active:
            return []
        older = [(t, item) for t, item in self._kept if t < stamp_ns]
        out = [GatedImage(t, item, False) for t, item in older[-1:]]
        out += [GatedImage(t, item, True) for t, item in self._kept if t >= stamp_ns]
        self._kept.clear()
        return out
