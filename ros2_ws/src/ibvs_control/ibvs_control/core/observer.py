"""Disturbance observer of the force laws: Delta / m from the IMU, aided by the flow's velocity.

Dynamics (docs/spec.md, {I} NED-type, z down): ``m v' = -F_app + m g e3 + Delta``, with ``F_app``
the force the vehicle applied (the commanded magnitude along the measured thrust axis
``R_IB e3``; controller.py).

**IMU channel** (ObserverGains ``tau_s``, ``d_max``): the IMU's specific force
``f_I = v' - g e3`` (m/s^2, put into {I} with the autopilot's attitude estimate, mean over a
frame) gives ``Delta / m = f_I + F_app / m``, low-passed with time constant tau_s:
``d_imu' = (f_I + F_app / m - d_imu) / tau_s``. It takes a wind as it changes, but it is blind
to what tilts the estimate: an autopilot holds its *estimate* at the setpoint, so an estimate
tilted by delta flies the truth tilted by -delta and the thrust pushes the vehicle at
``g sin(delta)`` (0.17 m/s^2 per degree), while ``f_I``, put into {I} with the same estimate,
reads the commanded direction (tilt and accelerometer bias cannot be told apart in hover).
The same holds for an accelerometer bias the autopilot has levelled on.

**Velocity channel** (``bias_tau_s`` > 0 in WINDOW, ``landing_bias_tau_s`` > 0 in LANDING;
0.2 and 0.1 s by default): where the graph measures the metric velocity (in
WINDOW, the wall's translational flow v / d_o times the window plane's distance d_o from the
corner bearings and the known width r_w; in LANDING, the floor's flow v / d_t times the
pad-image height, controller.py), a momentum observer sees every push the vehicle
feels: ``z' = g e3 - F_app / m + d_vel``, ``d_vel = (v - z) / tau_s`` (a first-order
low-pass of the true Delta / m with time constant tau_s, no differentiation of v). The
difference's horizontal part, ``b = (I - e3 e3^T)(d_vel - d_imu)``, is what the IMU cannot
see (a tilt error pushes sideways; a vertical push, the thrust model's error, the IMU does
see); it is low-passed with the mode's time constant, clamped at ``bias_max``, and *held*
where no velocity is measured (the blind crossing). An estimate error wanders (PX4 SIH's:
0.7 deg in 2 s, docs/sim_autopilot.md), so LANDING learns it again from its own velocity.
Horizontal only also keeps the flow's vertical errors (the derotation's, a distance error
coupling the vertical acceleration) out of the thrust, as a PX4 SIH flight with all three
axes suggested (docs/px4_sih.md). The estimate
is always ``d_imu + b``: the IMU channel keeps its bandwidth for the wind, the velocity
channel (noisier: flow noise times the distance, divided by tau_s) only sets the slow part.
docs/design.md "Attitude-estimate error".
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.frames import e3, GRAVITY
from ibvs_control.core.control_laws import clamp_norm, ObserverGains


class DisturbanceObserver:
    """Delta / m (m/s^2, {I}): the IMU channel plus the held velocity-channel correction."""

    def __init__(self, gains: ObserverGains, mass: float) -> None:
        self.gains = gains
        self.mass = float(mass)
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new flight)."""
        self.d_imu = np.zeros(3)          # the IMU channel's Delta / m
        self.bias = np.zeros(3)           # b: what the IMU cannot see (held between updates)
        self._z: np.ndarray | None = None   # the velocity channel's predicted velocity
        self._d_vel = np.zeros(3)

    @property
    def estimate(self) -> np.ndarray:
        """Delta / m (m/s^2, {I}) = d_imu + b, |.| <= d_max."""
        return clamp_norm(self.d_imu + self.bias, self.gains.d_max)

    @property
    def velocity_aided(self) -> bool:
        """Whether the velocity channel is on (bias_tau_s > 0)."""
        return self.gains.bias_tau_s > 0.0

    def update(self, dt: float, f_I: np.ndarray | None, F_app: np.ndarray,
               v_I: np.ndarray | None = None, bias_tau_s: float | None = None) -> None:
        """One step over ``dt`` (s): specific force f_I, applied force F_app (N), velocity v_I.

        f_I None or non-finite: the IMU channel holds. v_I (m/s, {I}) None, non-finite or the
        velocity channel off: the correction b holds and the velocity channel restarts at
        its next measurement (bumpless: it starts from the current estimate). ``bias_tau_s``:
        the correction's time constant for this step (None: the gains' ``bias_tau_s``; <= 0:
        the channel off), as the source of v_I decides (controller.py: WINDOW or LANDING).
        """
        if dt <= 0.0:
            return
        g = self.gains
        F_app = np.asarray(F_app, dtype=float)
        if f_I is not None and np.all(np.isfinite(f_I)):
            d_meas = np.asarray(f_I, dtype=float) + F_app / self.mass
            self.d_imu = clamp_norm(self.d_imu + min(dt / g.tau_s, 1.0) * (d_meas - self.d_imu),
                                    g.d_max)
        tau_b = g.bias_tau_s if bias_tau_s is None else float(bias_tau_s)
        if not tau_b > 0.0 or v_I is None or not np.all(np.isfinite(v_I)):
            self._z = None
            return
        v_I = np.asarray(v_I, dtype=float)
        if self._z is None:                     # start: d_vel = the current estimate
            self._d_vel = self.estimate
            self._z = v_I - g.tau_s * self._d_vel
            return
        self._z = self._z + dt * (GRAVITY * e3 - F_app / self.mass + self._d_vel)
        self._d_vel = clamp_norm((v_I - self._z) / g.tau_s, g.d_max)
        unseen = self._d_vel - self.d_imu
        unseen[2] = 0.0                         # horizontal: the IMU sees vertical pushes
        self.bias = clamp_norm(self.bias + min(dt / tau_b, 1.0) * (unseen - self.bias),
                               g.bias_max)
