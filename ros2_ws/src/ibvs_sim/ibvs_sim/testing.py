"""Stand-ins for tests of the simulator and of what it drives (installed, never collected)."""
import math

import numpy as np

from ibvs_common.core.frames import GRAVITY, rot_from_euler_zyx
from ibvs_sim.core.autopilot import AttitudeReference, VehicleStateView

INITIAL_XI = (-2.0, 0.1, -1.82)    # the reference initial condition, {I} NED, m


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


def hover_state(t: float, xi=INITIAL_XI, v=(0.0, 0.0, 0.0), roll: float = 0.0,
                pitch: float = 0.0, yaw: float = 0.0,
                omega=(0.0, 0.0, 0.0)) -> VehicleStateView:
    """Ground truth of a vehicle at ``xi`` ({I} NED) with the given attitude; IMU at rest."""
    R = rot_from_euler_zyx(roll, pitch, yaw)
    return VehicleStateView(t=t, xi_I=np.array(xi, dtype=float), v_I=np.array(v, dtype=float),
                            R_IB=R, Omega_B=np.array(omega, dtype=float),
                            accel_B_specific=R.T @ np.array([0.0, 0.0, -GRAVITY]))


def second_order_step(t: np.ndarray | float, wn: float, zeta: float) -> np.ndarray:
    """Return the unit step response of theta'' + 2 zeta wn theta' + wn^2 theta = wn^2.

    Textbook closed form, 0 < zeta < 1; 0 for t < 0.
    """
    t = np.maximum(np.asarray(t, float), 0.0)
    wd = wn * math.sqrt(1.0 - zeta ** 2)
    return 1.0 - np.exp(-zeta * wn * t) * (np.cos(wd * t)
                                           + zeta / math.sqrt(1.0 - zeta ** 2) * np.sin(wd * t))
