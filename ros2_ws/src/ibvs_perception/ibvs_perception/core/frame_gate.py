"""Hold a camera frame until the other inputs of its stamp have arrived (ROS-free).

A perception node that combines an image with inputs from other topics (the IMU attitude for
derotation, the window detection of the same image for the wall plane) gives a result that
depends on *which* of those inputs happened to be there when the image arrived, i.e. on thread
scheduling, unless it waits for them. :class:`FrameGate` keeps the latest frame and releases it

- as soon as ``ready(stamp)`` says its inputs are in (the node decides what that means),
- or when ``max_wait_s`` (a monotonic wall clock) has passed since it arrived (an input that
  never comes costs at most that latency, never the frame),
- or at once when a newer frame arrives (the held frame is released first, never dropped).

With inputs that arrive within ``max_wait_s`` the output is a function of the recorded data
alone, so lockstep runs repeat and a bag replay reproduces them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class GatedFrame:
    """A frame held by the gate: its stamp (s), arrival time (monotonic s) and payload."""

    stamp_s: float
    arrival_s: float
    payload: Any


class FrameGate:
    """One held frame at a time; see the module docstring for the release rules."""

    def __init__(self, max_wait_s: float) -> None:
        if not max_wait_s >= 0.0:
            raise ValueError(f'max_wait_s must be >= 0, got {max_wait_s}')
        self.max_wait_s = float(max_wait_s)
        self.held: GatedFrame | None = None
        self.released_without_inputs = 0      # frames released without their inputs (diagnostics)

    def push(self, stamp_s: float, payload: Any, now_s: float) -> GatedFrame | None:
        """Hold a new frame; return the previously held one (to process now), if any."""
        previous, self.held = self.held, GatedFrame(float(stamp_s), float(now_s), payload)
        if previous is not None:
            self.released_without_inputs += 1
        return previous

    def release(self, ready: Callable[[float], bool], now_s: float) -> GatedFrame | None:
        """Return the held frame if ``ready(stamp)`` or it waited ``max_wait_s``; else None."""
        frame = self.held
        if frame is None:
            return None
        if ready(frame.stamp_s):
            self.held = None
            return frame
        if now_s - frame.arrival_s >= self.max_wait_s:
            self.held = None
            self.released_without_inputs += 1
            return frame
        return None
