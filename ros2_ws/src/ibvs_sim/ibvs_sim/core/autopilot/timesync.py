"""TIMESYNC of the sim autopilot, both ways, as PX4 does; its boot clock in ns.

The boot clock is sim time: a request (tc1 = 0) gets tc1 = ``round(1e9 t)`` of the poll that
reads it (``time_boot_ms`` is the same clock) and ts1 echoed (:class:`TimesyncResponder`). In
lockstep the sim reads MAVLink only between frames, so a request is answered with the time of
the frame being waited on.

PX4 also asks its peers, at ~10 Hz (docs/mavlink.md, measured on v1.16 SITL), and the bridge
answers as MAVROS does: :class:`TimesyncRequester` sends those requests at
``timesync_request_hz`` of sim time and checks the answers (ts1 one of its own requests, tc1 a
time: the companion's ROS time, which is sim time here too). So every sim run exercises the
bridge's answering path, as real PX4 does. The answers are counted, not used: PX4 uses them for
its own estimate of the companion's clock, which the sim has no use for.
"""
from __future__ import annotations

import collections
from typing import Any

from ibvs_sim.core.autopilot.config import AutopilotCounters, VehicleStateView
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_common.core.stamps import NS_PER_S


class TimesyncResponder:
    """Answer TIMESYNC requests (tc1 = 0) on ``link``."""

    def __init__(self, counters: AutopilotCounters, link: AutopilotLink) -> None:
        """Answer on ``link``, counting in ``counters``."""
        self.counters = counters
        self._link = link

    def on_timesync(self, msg: Any, state: VehicleStateView) -> None:
        """Answer a TIMESYNC request as PX4 does: tc1 = boot time now (ns), ts1 echoed.

        The boot time is the sim time of this poll (time_boot_ms is the same clock). In
        lockstep the sim reads MAVLink only between frames, so a request is answered with the
        time of the frame being waited on. An answer (tc1 != 0) is the requester's. At time
        0 no answer: a real autopilot's boot time is never 0, and tc1 = 0
        would read as a request. pymavlink's common TIMESYNC has no target fields: the answer
        goes to the link's peer.
        """
        if int(msg.tc1) != 0:
            return                              # an answer: TimesyncRequester.on_answer
        t_ns = int(round(float(state.t) * NS_PER_S))
        if t_ns <= 0:
            self.counters.timesync_unanswered += 1
            return
        self._link.mav.timesync_send(t_ns, int(msg.ts1))
        self.counters.timesync_answered += 1


#: own requests whose ts1 an answer may echo (10 Hz: 0.8 s of them)
PENDING_REQUESTS_KEPT = 8


class TimesyncRequester:
    """Send TIMESYNC requests at ``timesync_request_hz`` (sim time) and check the answers."""

    def __init__(self, request_hz: float, counters: AutopilotCounters,
                 link: AutopilotLink) -> None:
        """Request at ``request_hz`` (0: never) on ``link``, counting in ``counters``."""
        if not request_hz >= 0.0:
            raise ValueError(f'timesync_request_hz must be >= 0, got {request_hz}')
        self.counters = counters
        self._link = link
        self._period_s = 1.0 / request_hz if request_hz > 0.0 else None
        self._next_t: float | None = None
        self._pending: collections.deque = collections.deque(maxlen=PENDING_REQUESTS_KEPT)

    def send_if_due(self, state: VehicleStateView) -> None:
        """Send a request (tc1 = 0, ts1 = boot time ns) when one is due at sim time state.t.

        Not at time 0 (ts1 = 0 is no time) and not before a peer is known. Paced as the
        telemetry streams: no burst after a stall, the phase moves instead.
        """
        t = float(state.t)
        t_ns = int(round(t * NS_PER_S))
        if self._period_s is None or t_ns <= 0 or not self._link.peer_known():
            return
        if self._next_t is not None and t + 1e-9 < self._next_t:
            return
        self._next_t = t + self._period_s
        self._link.mav.timesync_send(0, t_ns)
        self._pending.append(t_ns)
        self.counters.timesync_requests_sent += 1

    def on_answer(self, msg: Any, state: VehicleStateView) -> None:
        """Check an answer (tc1 != 0; a request is the responder's): ts1 ours, tc1 > 0."""
        ts1, tc1 = int(msg.ts1), int(msg.tc1)
        if tc1 == 0:
            return
        if ts1 not in self._pending or tc1 < 0:
            self.counters.timesync_answers_foreign += 1
            return
        self._pending.remove(ts1)
        self.counters.timesync_answers_received += 1
