"""Which camera frames the graph computes: every ``stride``-th one, the same in every node.

When the onboard computer cannot hold the camera rate, the graph computes every second (or
fourth...) frame instead of a random subset: the supervisor chooses the stride (its rate
governor, ibvs_control/core/rate_governor.py) and sends it with each frame status; each
perception node then processes only the frames on the grid, so that the products of one
frame come from the same image in every node. A frame is on the grid when its stamp is a
whole multiple of ``stride`` camera periods from a reference frame of that camera (the last
frame the supervisor evaluated). The index is rounded: a camera's stamps may jitter by up to
half a period. Every node computes the same answer from the same stamp, whatever its clock.
Stamps are integer nanoseconds on the ROS clock. ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass

MAX_STRIDE = 8


@dataclass(frozen=True)
class FrameGrid:
    """Every ``stride``-th frame of one camera, counted from the frame stamped ``ref_ns``.

    ``period_ns``: the camera's frame period (its configured rate). ``stride`` 1 (the
    default): every frame.
    """

    period_ns: int
    stride: int = 1
    ref_ns: int = 0

    def __post_init__(self) -> None:
        """Raise ValueError for a period <= 0 or a stride outside 1 ... MAX_STRIDE."""
        if self.period_ns <= 0:
            raise ValueError(f'frame period must be > 0 ns, got {self.period_ns}')
        if not 1 <= self.stride <= MAX_STRIDE:
            raise ValueError(f'frame stride must be in 1 ... {MAX_STRIDE}, got {self.stride}')

    def index(self, stamp_ns: int) -> int:
        """Return the frame's index from the reference frame (rounded to the nearest period)."""
        d = int(stamp_ns) - self.ref_ns
        return (d + self.period_ns // 2) // self.period_ns

    def on_grid(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` is one the graph computes."""
        return self.stride == 1 or self.index(stamp_ns) % self.stride == 0

    def with_stride(self, stride: int, ref_ns: int) -> FrameGrid:
        """Return this camera's grid with another stride, counted from frame ``ref_ns``."""
        return FrameGrid(self.period_ns, int(stride), int(ref_ns))


def period_ns(rate_hz: float) -> int:
    """Return the frame period (ns) of a camera rate (Hz > 0)."""
    if not rate_hz > 0.0:
        raise ValueError(f'camera rate must be > 0 Hz, got {rate_hz}')
    return int(round(1e9 / rate_hz))


class GridFollower:
    """A camera's grid as the supervisor announces it (``ibvs/frame_grid``), for its users.

    A smaller stride applies from its reference frame on and the old grid before it, as the
    supervisor expects the frames (ibvs_control's ``SupervisorGrids``: a try of a smaller
    stride starts a little after its decision); a larger one applies at once. The perception
    nodes compute only the frames on it; the lockstep sim owes no wait to a frame off it.
    """

    def __init__(self, period_ns: int) -> None:
        self.grid = FrameGrid(int(period_ns))
        self._before: tuple[FrameGrid, int] | None = None   # the grid before a smaller stride

    def update(self, stride: int, ref_ns: int) -> None:
        """Take a new (stride, reference frame) of this camera."""
        if stride < self.grid.stride:
            self._before = (self.grid, int(ref_ns))
        elif stride > self.grid.stride:
            self._before = None
        self.grid = self.grid.with_stride(stride, ref_ns)

    def on_grid_at(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` is on the grid (the old one before a smaller one)."""
        if self._before is not None and stamp_ns < self._before[1]:
            return self._before[0].on_grid(stamp_ns)
        return self.grid.on_grid(stamp_ns)
