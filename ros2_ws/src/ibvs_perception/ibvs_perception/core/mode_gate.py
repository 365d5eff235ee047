"""Mode gating: a perception product is computed only for the frames of a mode that uses it.

The pad detector and the floor flow are not used before the window is crossed, the window
detector and the wall flow not after (``ibvs_common.core.modes.MODE_INPUTS``): computing them
anyway costs an onboard computer a third of its CPU (docs/performance.md). The modes come from
the supervisor's ``ibvs/supervisor_status``, one per evaluated frame, stamped with it.

Rule (:class:`ModeGate`), with stamps on the ROS clock in integer nanoseconds:

- The mode in force at an image stamp t is that of the newest status with a stamp <= t
  among those received. Before any status, the supervisor's latched mode (``ibvs/mode``,
  :meth:`ModeGate.on_mode`) decides; without either every image is processed (a replay
  without a supervisor, a node started alone); so is every image when gating is disabled.
  On a slow computer the first status can come a second or more after the first images: the
  pad detector and the flows computed every IDLE image until then, starving the window
  detector that the start needs (a sixth of a core: the start refused, "the full window is
  not detected").
- An image whose mode does not use the product is kept (the newest ``depth``), unprocessed.
- A status at stamp t_s that turns the product on releases at once the newest kept image
  with a stamp >= t_s, to be processed and published, preceded by the kept image just before
  it, to be processed but not published: a tracker (the flow) needs its previous frame. The
  other kept images are dropped (counted in ``superseded``): latest only, as a node that is
  behind (:mod:`~ibvs_perception.core.latest_only`). Without a kept image >= t_s, the newest
  older one is processed as that predecessor.

So the images processed from a switch on are the same whether an image or the status of the
same stamp arrives first; in a lockstep simulation, where the status of frame k is published
before the sim renders frame k + 1, runs repeat. Onboard, the first frame after a switch is
answered when the status arrives (one supervisor latency, a few ms, later). When the status
comes later than the next image (an executor behind on a slow computer), the frames between
are not computed: releasing every kept image was a queue of up to ``depth`` frames computed
at once, at the moment the mode's work grows (the wall flow at WINDOW's start).

Clock steps (:mod:`ibvs_common.core.clock_step`): when the images' or the statuses' stamps go
back by more than ``MAX_BACKSTEP_S``, the gate forgets its switches and kept images, i.e. it
processes every image until the next status, as before any status. Otherwise a status after a
step back, older than the last switch, would be ignored until the clock caught up: a product
switched off in IDLE would stay off in WINDOW (and WINDOW would fail safe for want of it).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Iterable

from ibvs_common.core.clock_step import BackstepWatch

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
        self._image_stamps = BackstepWatch()
        self._status_stamps = BackstepWatch()
        self._initial = True         # the activity before any status (ibvs/mode, on_mode)
        self._status_seen = False    # a status came (since the start or a clock step)
        self.superseded = 0          # kept images >= a switch dropped for a newer one

    @property
    def clock_steps(self) -> int:
        """Times the gate started again because the image or status stamps went back."""
        return self._image_stamps.steps + self._status_stamps.steps

    def _watch(self, watch: BackstepWatch, stamp_ns: int) -> None:
        """Forget switches and kept images when the stamps of ``watch`` went back (a step).

        Both watches start again from there: the other stream's first stamp after the step is
        no second step.
        """
        if watch.observe(stamp_ns):
            self._changes.clear()
            self._kept.clear()
            self._initial = True
            self._status_seen = False
            self._image_stamps.forget()
            self._status_stamps.forget()
            watch.observe(stamp_ns)

    @property
    def active(self) -> bool:
        """Whether the newest known mode uses the product (before any status: on_mode's)."""
        return self._changes[-1][1] if self._changes else self._initial

    def on_mode(self, mode: int) -> None:
        """Take the supervisor's latched mode (``ibvs/mode``): it decides until a status comes.

        Once a status has come, the statuses alone decide (each is stamped with its frame):
        the ``ibvs/mode`` of a switch comes with the switch's status, in either order, and
        must not make the status look like no change (its image would never be computed).
        """
        if not self._status_seen:
            self._initial = int(mode) in self.active_modes

    def active_at(self, stamp_ns: int) -> bool:
        """Whether the mode in force at ``stamp_ns`` (newest status <= it) uses the product."""
        if not self.enabled:
            return True
        for t, active in reversed(self._changes):
            if t <= stamp_ns:
                return active
        # older than every change: the activity before the first one
        return self._initial if not self._changes else not self._changes[0][1]

    def on_image(self, stamp_ns: int, item: Any) -> list[GatedImage]:
        """Take one image: [it] to process now, or [] when kept for a possible switch."""
        self._watch(self._image_stamps, stamp_ns)
        if self.active_at(stamp_ns):
            return [GatedImage(stamp_ns, item, True)]
        self._kept.append((stamp_ns, item))
        return []

    def on_status(self, stamp_ns: int, mode: int) -> list[GatedImage]:
        """Take the mode of the frame at ``stamp_ns``; return the images a switch on releases."""
        if not self.enabled:
            return []
        self._watch(self._status_stamps, stamp_ns)
        self._status_seen = True
        active = int(mode) in self.active_modes
        if active == self.active:
            return []
        if self._changes and stamp_ns < self._changes[-1][0]:
            return []             # older than the last switch: the supervisor releases in order
        self._changes.append((stamp_ns, active))
        if not active:
            return []
        kept = list(self._kept)
        self._kept.clear()
        newer = [i for i, (t, _) in enumerate(kept) if t >= stamp_ns]
        if not newer:                    # the predecessor of the next image
            return [GatedImage(t, item, False) for t, item in kept[-1:]]
        newest = newer[-1]
        self.superseded += len(newer) - 1
        return [GatedImage(*kept[i], publish=(i == newest)) for i in (newest - 1, newest)
                if i >= 0]
