"""Clock steps: a clock, or a stream of stamps, that goes back (docs/design.md, "Time").

Every stamp and deadline of the flight path is on the ROS clock: system time on a vehicle. A
step of the system clock (chrony's ``makestep``, an RTC ahead of the first time fix, a time
source set late) moves every stamp taken after it:

- forward: every input is older than its timeout at once, and the supervisor's staleness
  rules end a flight (FAILSAFE); nothing else is needed;
- back: inputs taken before the step look younger than they are, and time-indexed state (the
  IMU history, frames waiting for their products) would hold samples of two moments under the
  same stamps, or refuse every new stamp as older than one already done, for the length of
  the step.

rcl and rclpy report jumps of sim time only (their jump callbacks), not steps of system time,
so the flight path detects a step back itself, wherever it sees time go by: the readings of a
node's own clock, or a stream of stamps that must increase (one IMU, one kind of perception
product: each comes from one publisher, in order). :class:`BackstepWatch` does it for one such
sequence. A go-back of at most ``max_backstep_s`` is not a step: readings of two threads taken
out of order, an IMU stamp corrected by the clock sync. What a node does on a step is its
policy, in its own docs: drop its time-indexed state and start again from the next input (as
tf2 clears its buffer on a jump back), and in the supervisor also FAILSAFE in a flying mode.
"""
from __future__ import annotations

import math

from ibvs_common.core.stamps import NS_PER_S

#: s, a go-back of a clock or stamp stream beyond this is a clock step (5 frames at 50 Hz)
MAX_BACKSTEP_S = 0.1


class BackstepWatch:
    """One sequence of times (integer ns) that must not go back: detect when it does."""

    def __init__(self, max_backstep_s: float = MAX_BACKSTEP_S) -> None:
        """Watch for go-backs longer than ``max_backstep_s`` (s, > 0)."""
        if not (math.isfinite(max_backstep_s) and max_backstep_s > 0.0):
            raise ValueError(f'max_backstep_s must be finite and > 0, got {max_backstep_s}')
        self.max_backstep_ns = int(round(max_backstep_s * NS_PER_S))
        self.newest_ns: int | None = None     # the latest time of the sequence since a step
        self.steps = 0                        # steps back seen

    def observe(self, t_ns: int) -> int:
        """Take the next time; return how far (ns) it went back if that is a step, else 0.

        A step restarts the watch from ``t_ns``: the times after it are compared with it.
        """
        t_ns = int(t_ns)
        newest = self.newest_ns
        if newest is None or t_ns >= newest:
            self.newest_ns = t_ns
            return 0
        back = newest - t_ns
        if back <= self.max_backstep_ns:
            return 0
        self.newest_ns = t_ns
        self.steps += 1
        return back

    def forget(self) -> None:
        """Start again: the next time is taken as it comes (a step detected elsewhere)."""
        self.newest_ns = None
