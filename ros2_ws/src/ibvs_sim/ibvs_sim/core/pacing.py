"""How sim time advances against the wall clock: free-running or in lockstep with the graph.

- ``realtime`` (:class:`RealtimeClock`): sim time runs at ``real_time_factor`` x the wall
  clock; a camera frame the sim cannot render on time is dropped and counted, never delayed
  or bunched; a stall of the sim process itself longer than ``MAX_CATCH_UP_S`` of sim time
  re-phases the clock;
- ``lockstep`` (:class:`LockstepGate`): sim time moves on from a delivery of camera images
  only once the graph answered it and published its products, or after the wall-clock wait.

ROS-free; :class:`~ibvs_sim.core.sim_core.Simulation` steps the physics accordingly.
"""
from __future__ import annotations

import enum
import math

from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.graph_sync import GraphProducts

MAX_CATCH_UP_S = 0.5          # s of sim time: a longer stall of the sim process re-phases it


class Pacing(str, enum.Enum):
    """How sim time advances against the wall clock."""

    REALTIME = 'realtime'
    LOCKSTEP = 'lockstep'


class RealtimeClock:
    """Free-running pacing: the sim time a wall time stands for, the frames too late to render.

    :meth:`start` anchors sim time to the wall clock at frame 0; :meth:`target` is the sim time
    the physics must catch up with now; :meth:`late` drops (and counts) a frame whose exposure
    is a whole camera period behind it.
    """

    def __init__(self, real_time_factor: float) -> None:
        if not (math.isfinite(real_time_factor) and 0.0 < real_time_factor <= 10.0):
            raise ValueError(f'real_time_factor must be in (0, 10], got {real_time_factor}')
        self.real_time_factor = real_time_factor
        self.frames_dropped = 0               # frames not rendered on time
        self.stalls = 0                       # re-phased after a stall of the sim
        self._wall0 = 0.0                     # wall time at sim time _t0_ns
        self._t0_ns = 0

    def start(self, now: float, t_ns: int) -> None:
        """Anchor sim time ``t_ns`` (frame 0) to wall time ``now`` (s)."""
        self._wall0, self._t0_ns = now, t_ns

    def sim_ns_at(self, wall: float) -> int:
        """Return the sim time (ns) that the wall time ``wall`` (s) stands for."""
        return self._t0_ns + round((wall - self._wall0) * self.real_time_factor * NS_PER_S)

    def target(self, now: float, t_ns: int) -> int:
        """Return the sim time (ns) to step to at wall time ``now``; re-phase after a stall."""
        target = self.sim_ns_at(now)
        if target - t_ns > MAX_CATCH_UP_S * NS_PER_S:      # the sim itself stalled
            self.stalls += 1
            self._wall0, self._t0_ns = now, t_ns
            target = t_ns
        return target

    def late(self, target_ns: int, frame_ns: int, period_ns: int) -> bool:
        """Return True (and count it dropped) for a frame a whole period behind the target."""
        if target_ns - frame_ns >= period_ns:
            self.frames_dropped += 1
            return True
        return False


class LockstepGate:
    """Lockstep pacing: whether sim time may move on from the last delivery of images.

    It may once the graph answered the delivered frame (the caller says so: a setpoint of the
    frame's stamp, or no answer awaited) and published every product of it
    (:class:`~ibvs_sim.core.graph_sync.GraphProducts`), or after ``answer_wait_s`` of wall
    clock since the frame went out: a missing answer then counts in ``timeouts`` (only for a
    full ``timeout_s`` wait: a fault-injection frame's shorter wait expects none), missing
    products are given up (``given_up``) until they are published again.

    ``silent_after`` time-outs in a row make the answerer *silent* (``silences`` counts
    how often): answers are no longer waited for until a new one comes (the caller passes
    the latest answer it has seen; a different one ends the silence). A bridge that died
    leaves the autopilot flying on its own: its offboard-loss failsafe acts after ~1 s of
    its own (sim) time, which would otherwise take 50 frames x ``timeout_s`` of wall time.
    """

    def __init__(self, timeout_s: float, products: GraphProducts,
                 silent_after: int = 2) -> None:
        self.timeout_s = timeout_s
        self.products = products
        self.silent_after = int(silent_after)
        # wall wait for the answer to the last frame; shorter when fault injection withheld
        # some of its images (the graph may have nothing to answer)
        self.answer_wait_s = timeout_s
        self.timeouts = 0
        self.silences = 0
        self.given_up: list[str] = []         # products no longer waited for
        self._since: float | None = None
        self._in_a_row = 0                    # full time-outs since the last answer in time
        self._silent = False
        self._silent_answer: object = None    # the latest answer when the silence began

    def frame_out(self, now: float) -> None:
        """Note that a frame went out at wall time ``now`` (s): the wait for its answer starts."""
        self._since = now

    @property
    def silent(self) -> bool:
        """Whether answers are not waited for (the answerer timed out ``silent_after`` times)."""
        return self._silent

    def may_step(self, now: float, answered: bool, latest_answer: object = None) -> bool:
        """Return whether sim time may move on at wall time ``now`` (s).

        ``latest_answer``: the newest answer the caller has seen (any comparable token, e.g.
        its stamp); while silent, a different one ends the silence.
        """
        if self._silent:
            if latest_answer == self._silent_answer:
                answered = True
            else:
                self._silent = False
        if answered and not self.products.missing():
            if not self._silent:
                self._in_a_row = 0
            return True
        if now - self._since >= self.answer_wait_s:
            if not answered and self.answer_wait_s >= self.timeout_s:
                self.timeouts += 1
                self._in_a_row += 1
                if self._in_a_row >= self.silent_after:
                    self._silent, self._silent_answer = True, latest_answer
                    self.silences += 1
                    self._in_a_row = 0
            self.given_up += self.products.give_up()
            return True
        return False
