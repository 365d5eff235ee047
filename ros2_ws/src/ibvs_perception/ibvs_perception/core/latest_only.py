"""Latest only: a node that is behind skips an image once the next one has surely come.

A perception node takes its camera's images in order from a short queue. When it falls behind
(a busy core, a long frame of another camera before), the image it takes may be so old that
the next image it would compute (``period`` later: the camera period times the frame stride)
is already queued behind it. Computing the old one costs a whole processing time for a product
that reaches the supervisor late, and makes the newer one later still. :class:`LatestOnly`
says when to skip it instead, from each image's age when the node takes it (ROS clock now
minus stamp, ns; the camera's delivery latency included):

- the camera's delivery latency is the smallest age of any image of the camera taken since
  the floor was last learnt (computed or not: what delivery costs at best; a node that is
  always behind would never see it again if old ages were forgotten);
- an image older than that by more than ``period`` plus ``superseded_margin_s`` is
  superseded: the next one, delivered as fast, has come;
- a queue that drains: each grid image taken after a skipped one must be younger than it by
  at least half a period (the node is going through images that were waiting). One that is
  not shows that the newer image did not come as fast as the floor says (the delivery got
  slower, frames were dropped, the clock jumped or runs at another rate than the stamps): it
  is computed, and the floor is learnt again from the images that follow.

In a lockstep simulation the ROS clock waits for the graph, so no image ages there and none is
skipped, however slow the machine.
"""
from __future__ import annotations

from dataclasses import dataclass

from ibvs_common.core.params import param
from ibvs_common.core.stamps import NS_PER_S

MIN_IMAGES = 10        # images seen since the floor was (re)learnt before it is trusted


@dataclass(frozen=True)
class LatestOnlyConfig:
    """When a node that is behind skips an image for the newer one behind it."""

    latest_only: bool = param(
        True, 'skip a grid image when the next one has surely come behind it (a node behind '
        'computes the newest, docs/design.md "Latest only"); false: compute every grid image '
        'taken')
    superseded_margin_s: float = param(
        0.005, "s (ROS clock): the delivery jitter allowed: an image is skipped when it is "
        "older, when taken, than the camera's fastest delivery plus one computed-frame period "
        'plus this', 0.0)


class LatestOnly:
    """Decide, per grid image taken, whether the next one has made it superseded."""

    def __init__(self, config: LatestOnlyConfig) -> None:
        self.config = config
        self.margin_ns = int(round(config.superseded_margin_s * NS_PER_S))
        self._floor_ns: int | None = None        # smallest age since (re)learning
        self._seen = 0                           # images since (re)learning
        self._skipped_age: int | None = None     # age of the last grid image, if skipped
        self.relearnt = 0             # times the floor was learnt again (module doc)

    @property
    def delivery_ns(self) -> int | None:
        """Return the camera's delivery latency (ns, the smallest age), None if unknown."""
        return self._floor_ns if self._seen >= MIN_IMAGES else None

    def observe(self, age_ns: int) -> None:
        """Take the age (ns) of any image of the camera when the node takes it."""
        age_ns = int(age_ns)
        self._floor_ns = age_ns if self._floor_ns is None else min(self._floor_ns, age_ns)
        self._seen += 1

    def superseded(self, age_ns: int, period_ns: int) -> bool:
        """Whether a grid image ``age_ns`` old is skipped for the next one, ``period_ns`` later.

        ``period_ns``: the camera period times the frame stride (ns, ROS clock).
        """
        floor = self.delivery_ns
        if not self.config.latest_only or floor is None:
            return False
        age_ns, period_ns = int(age_ns), int(period_ns)
        skip = age_ns > floor + period_ns + self.margin_ns
        if skip and self._skipped_age is not None and \
                age_ns > self._skipped_age - period_ns // 2:
            self._floor_ns, self._seen = None, 0     # not draining: learn the delivery again
            self.relearnt += 1
            skip = False
        self._skipped_age = age_ns if skip else None
        return skip
