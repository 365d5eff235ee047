"""Hold camera frames until the other inputs of their stamps have arrived (ROS-free).

A perception node that combines an image with inputs from other topics (the IMU attitude for
derotation, the window detection of the same image for the wall plane) gives a result that
depends on *which* of those inputs happened to be there when the image arrived, i.e. on thread
scheduling, unless it waits for them. :class:`FrameGate` keeps the latest few frames, in
arrival order, and releases the oldest

- as soon as ``ready(stamp)`` says its inputs are in (the node decides what that means),
- or when ``max_wait_s`` (a monotonic wall clock) has passed since it arrived (an input that
  never comes costs at most that latency, never the frame),
- or at once when more than ``max_held`` frames wait (the oldest leaves first, never dropped).

Frames leave in order, each at most once. Holding a few frames (not one) matters when an image
overtakes the IMU sample of the previous one, as at a lockstep start where frame 1 can follow
frame 0 within milliseconds: frame 0 still waits for its attitude instead of being processed
without it. With inputs that arrive within ``max_wait_s`` the output is a function of the
recorded data alone, so lockstep runs repeat and a bag replay reproduces them.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

DEFAULT_MAX_HELD = 3     # frames; 60 ms at 50 Hz, above any wait a real-time node should allow


@dataclass(frozen=True)
class GatedFrame:
    """A frame held by the gate: its stamp (s), arrival time (monotonic s) and payload."""

    stamp_s: float
    arrival_s: float
    payload: Any


class FrameGate:
    """Up to ``max_held`` held frames; see the module docstring for the release rules."""

    def __init__(self, max_wait_s: float, max_held: int = DEFAULT_MAX_HELD) -> None:
        if not max_wait_s >= 0.0 or int(max_held) < 1:
            raise ValueError(f'need max_wait_s >= 0 and max_held >= 1, got {max_wait_s}, '
                             f'{max_held}')
        self.max_wait_s = float(max_wait_s)
        self.max_held = int(max_held)
        self.held: deque[GatedFrame] = deque()
        self.released_without_inputs = 0      # frames released without their inputs (diagnostics)

    def push(self, stamp_s: float, payload: Any, now_s: float) -> GatedFrame | None:
        """Hold a new frame; return the oldest held one if the gate overflowed (process it now)."""
        self.held.append(GatedFrame(float(stamp_s), float(now_s), payload))
        if len(self.held) > self.max_held:
            self.released_without_inputs += 1
            return self.held.popleft()
        return None

    def release(self, ready: Callable[[float], bool], now_s: float) -> list[GatedFrame]:
        """Return, oldest first, the held frames that are ``ready(stamp)`` or waited enough.

        Only the head of the queue leaves: a frame never overtakes an older one.
        """
        out = []
        while self.held:
            frame = self.held[0]
            if not ready(frame.stamp_s):
                if now_s - frame.arrival_s < self.max_wait_s:
                    break
                self.released_without_inputs += 1
            out.append(self.held.popleft())
        return out
