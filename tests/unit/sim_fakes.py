"""Stand-ins shared by the simulator's unit tests (imported by them, not collected)."""
import numpy as np

from ibvs_sim.core.autopilot import AttitudeReference


class HoverAutopilot:
    """An autopilot that holds the level attitude at the hover thrust and reads nothing."""

    last_setpoint_time_boot_ms = None
    awaits_setpoints = True

    def poll(self, state, receive=True, telemetry=True):
        pass

    def attitude_reference(self, state):
        return AttitudeReference(np.array([1.0, 0.0, 0.0, 0.0]), 0.5, 'offboard')

    def estimate_error(self, t):
        return np.eye(3)          # a perfect estimate
