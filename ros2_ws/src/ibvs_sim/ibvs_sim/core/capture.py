"""Frames in the making: exposures rendered as physics passes them, held until their delivery.

:class:`FrameCapture` follows every :class:`~ibvs_sim.core.camera_model.FrameClock`: each
render instant of a frame's exposure is rendered once physics has passed it (the pose
interpolated between the two physics steps around it), the renders of an exposure are
averaged (motion blur), the read noise of the frame is added, and the frame waits for its
delivery time. ROS-free; docs/sim.md "Camera model".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ibvs_common.core.frames import exp_so3, log_so3
from ibvs_sim.core.camera_model import FrameClock, PlannedFrame
from ibvs_sim.core.cameras import CameraRig


@dataclass(frozen=True)
class Pose:
    """The body's pose at sim time ``t_ns``."""

    t_ns: int
    R_IB: np.ndarray
    xi_I: np.ndarray


def interpolate(a: Pose, b: Pose, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Return (R_IB, xi_I) at ``t_ns`` between poses a and b: linear, geodesic on SO(3).

    At (or outside) either end, that pose itself, bit for bit.
    """
    if t_ns >= b.t_ns or a.t_ns >= b.t_ns:
        return b.R_IB, b.xi_I
    if t_ns <= a.t_ns:
        return a.R_IB, a.xi_I
    s = (t_ns - a.t_ns) / (b.t_ns - a.t_ns)
    return (a.R_IB @ exp_so3(s * log_so3(a.R_IB.T @ b.R_IB)),
            a.xi_I + s * (b.xi_I - a.xi_I))


@dataclass
class CapturedFrame:
    """A frame whose exposure is rendered: its plan and its images (camera -> mono8)."""

    plan: PlannedFrame
    images: dict


class FrameCapture:
    """Render every clock's exposures as physics passes them; give out the frames due.

    ``late(frame, period_ns)`` (free-running pacing) says whether a frame is already a whole
    period behind the wall clock when its exposure starts: it is then not rendered (the pacing
    counts it).
    """

    def __init__(self, clocks: list[FrameClock], rig: CameraRig) -> None:
        self.clocks = clocks
        self.rig = rig
        self.pending: list[CapturedFrame] = []        # captured, not delivered yet
        self._current = [clock.next() for clock in clocks]   # each clock's frame in exposure
        self._rendered = [0] * len(clocks)             # its samples rendered so far
        self._sums: list[dict] = [{} for _ in clocks]  # its renders summed (blur), per camera

    def next_delivery_ns(self) -> int | None:
        """Return the earliest delivery of a frame captured or in exposure (None: none)."""
        due = [f.plan.delivery_ns for f in self.pending]
        due += [f.delivery_ns for f in self._current if f.cameras]
        return min(due) if due else None

    def expose(self, before: Pose, now: Pose,
               late: Callable[[PlannedFrame, int], bool] | None = None) -> None:
        """Render every exposure instant up to ``now`` (physics just stepped from ``before``).

        A frame whose exposure is complete is captured: it waits for its delivery.
        """
        for i, clock in enumerate(self.clocks):
            while True:
                frame = self._current[i]
                if not frame.cameras or (self._rendered[i] == 0 and late is not None
                                         and late(frame, clock.period_ns)):
                    self._start(i)
                    continue
                todo = frame.samples_ns[self._rendered[i]:]
                for t_ns in todo:
                    if t_ns > now.t_ns:
                        break
                    self._render(i, *interpolate(before, now, t_ns))
                if self._rendered[i] < len(frame.samples_ns):
                    break
                self.pending.append(CapturedFrame(frame, self._finish(i)))
                self._start(i)

    def has_due(self, t_ns: int) -> bool:
        """Whether a captured frame is delivered at or before ``t_ns``."""
        return any(f.plan.delivery_ns <= t_ns for f in self.pending)

    def take_due(self, t_ns: int) -> list[CapturedFrame]:
        """Return (and forget) the captured frames delivered at or before ``t_ns``."""
        due = [f for f in self.pending if f.plan.delivery_ns <= t_ns]
        self.pending = [f for f in self.pending if f.plan.delivery_ns > t_ns]
        return due

    def _start(self, i: int) -> None:
        self._current[i] = self.clocks[i].next()
        self._rendered[i] = 0
        self._sums[i] = {}

    def _render(self, i: int, R_IB: np.ndarray, xi_I: np.ndarray) -> None:
        images = self.rig.render_clean(self._current[i].cameras, R_IB, xi_I)
        n = len(self._current[i].samples_ns)
        sums = self._sums[i]
        for name, img in images.items():
            if n == 1:
                sums[name] = img
            elif name in sums:
                sums[name] += img
            else:
                sums[name] = img.astype(np.float32)
        self._rendered[i] += 1

    def _finish(self, i: int) -> dict:
        """Return the frame's images: the exposure's mean render with the frame's read noise."""
        frame, n = self._current[i], len(self._current[i].samples_ns)
        out = {}
        for name, img in self._sums[i].items():
            if n > 1:
                img = np.rint(img / n).astype(np.uint8)
            out[name] = self.rig.add_noise(name, img, frame.index)
        return out
