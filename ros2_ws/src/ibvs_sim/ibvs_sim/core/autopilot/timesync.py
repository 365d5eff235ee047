"""TIMESYNC of the sim autopilot: requests answered as PX4 does, with the boot time in ns.

The boot clock is sim time: a request (tc1 = 0) gets tc1 = ``round(1e9 t)`` of the poll that
reads it (``time_boot_ms`` is the same clock) and ts1 echoed. In lockstep the sim reads MAVLink
only between frames, so a request is answered with the time of the frame being waited on.
"""
from __future__ import annotations

from typing import Any

from ibvs_sim.core.autopilot.config import AutopilotCounters, VehicleStateView
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_common.core.stamps import NS_PER_S


class TimesyncResponder:
    """Answer TIMESYNC requests on ``link``; this autopilot sends no requests of its own."""

    def __init__(self, counters: AutopilotCounters, link: AutopilotLink) -> None:
        """Answer on ``link``, counting in ``counters``."""
        self.counters = counters
        self._link = link

    def on_timesync(self, msg: Any, state: VehicleStateView) -> None:
        """Answer a TIMESYNC request as PX4 does: tc1 = boot time now (ns), ts1 echoed.

        The boot time is the sim time of this poll (time_boot_ms is the same clock). In
        lockstep the sim reads MAVLink only between frames, so a request is answered with the
        time of the frame being waited on. An answer (tc1 != 0: we send no requests) is
        ignored. At time 0 no answer: a real autopilot's boot time is never 0, and tc1 = 0
        would read as a request. pymavlink's common TIMESYNC has no target fields: the answer
        goes to the link's peer.
        """
        if int(msg.tc1) != 0:
            return
        t_ns = int(round(float(state.t) * NS_PER_S))
        if t_ns <= 0:
            self.counters.timesync_unanswered += 1
            return
        self._link.mav.timesync_send(t_ns, int(msg.ts1))
        self.counters.timesync_answered += 1
