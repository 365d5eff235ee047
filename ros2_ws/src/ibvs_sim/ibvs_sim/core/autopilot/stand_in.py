"""HoverStandIn: the sim's autopilot served on the wall clock for a vehicle at rest, in a thread.

For benchmarks and tests that need a PX4-like MAVLink peer without the sim's physics: the
vehicle is level and still (R_IB = I, specific force -g e3), its sim time the steady time
since the start. The thread wakes on a datagram or when a telemetry stream is due, at least
every ``MAX_WAIT_S`` (heartbeat, offboard-loss checks): not a 2 ms poll, whose 500 wake-ups
a second loaded the 2-core machine under the very benchmarks that use it.
"""
from __future__ import annotations

import select
import threading
import time

import numpy as np

from ibvs_sim.core.autopilot.config import AutopilotConfig, VehicleStateView
from ibvs_sim.core.autopilot.facade import Autopilot

MAX_WAIT_S = 0.01               # s (steady), the longest wait between two cycles
AT_REST = (np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3), np.array([0.0, 0.0, -9.81]))


def wait_s(autopilot: Autopilot, t: float) -> float:
    """Seconds a wall-clock server of ``autopilot`` at sim time ``t`` may wait for a datagram."""
    due = autopilot.next_telemetry_t()
    return MAX_WAIT_S if due is None else min(MAX_WAIT_S, max(0.0, due - t))


class HoverStandIn:
    """Serve an :class:`Autopilot` of ``config`` in a daemon thread until :meth:`close`."""

    def __init__(self, config: AutopilotConfig) -> None:
        self.autopilot = Autopilot(config)
        self.local_port = self.autopilot.local_port
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='hover_stand_in', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        fd = self.autopilot.fileno()
        while not self._stop.is_set():
            select.select([fd], [], [], wait_s(self.autopilot, time.monotonic() - t0))
            self.autopilot.poll(VehicleStateView(time.monotonic() - t0, *AT_REST))

    def close(self) -> None:
        """Stop the thread and close the autopilot's link."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.autopilot.close()
