"""HoverStandIn: the sim's autopilot served on the wall clock for a vehicle at rest, in a thread.

For benchmarks and tests that need a PX4-like MAVLink peer without the sim's physics: the
vehicle is level and still (R_IB = I, specific force -g e3), the autopilot polled every
``POLL_S`` of the steady clock, its sim time the steady time since the start.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from ibvs_sim.core.autopilot.config import AutopilotConfig, VehicleStateView
from ibvs_sim.core.autopilot.facade import Autopilot

POLL_S = 0.002                  # s (steady) between polls
AT_REST = (np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3), np.array([0.0, 0.0, -9.81]))


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
        while not self._stop.is_set():
            time.sleep(POLL_S)
            self.autopilot.poll(VehicleStateView(time.monotonic() - t0, *AT_REST))

    def close(self) -> None:
        """Stop the thread and close the autopilot's link."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.autopilot.close()
