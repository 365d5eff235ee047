"""The inner-loop references of the sim autopilot: offboard setpoint, hold, land / failsafe.

An :class:`~ibvs_sim.core.autopilot.config.AttitudeReference` is the attitude of FRD in NED
(w, x, y, z) and the normalised collective thrust ``T / T_max`` (hover = ``hover_thrust``) that
the sim's attitude controller tracks. Hold and land close their loops on ground truth (no
estimator); NED dynamics ``dv/dt = g e3 - (T/m) R e3``.

- OFFBOARD: the latest SET_ATTITUDE_TARGET (attitude level with the current yaw and hover
  thrust until one has given them);
- POSCTL / AUTO_LOITER (hold): ``a* = Kp (xi_hold - xi) - Kd v`` towards the point where the
  mode was entered, yaw held, tilt limited to ``max_tilt``;
- AUTO_LAND (and the offboard-loss failsafe): level, current yaw, thrust from a descent-rate
  loop to ``land_descent_rate``;
- disarmed: level, zero thrust. A non-finite ground truth gets level hover (counted).
"""
from __future__ import annotations

import math

import numpy as np

from ibvs_common.core.frames import (GRAVITY, euler_zyx_from_rot, quat_from_rot,
                                     rot_from_euler_zyx, rot_z)
from ibvs_sim.core.autopilot.config import (AttitudeReference, AutopilotConfig,
                                            AutopilotCounters, finite, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.protocol import FlightMode, ReferenceSource

MIN_LIFT_FRACTION = 0.1          # hold / land never command less than 0.1 g of lift


class AttitudeReferences:
    """The reference of each mode, and the hold point (position {I} in m, yaw in rad)."""

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 warn: RateLimitedLog) -> None:
        """Start without a hold point: the first finite ground truth sets it."""
        self.config = config
        self.counters = counters
        self._warn = warn
        self.hold_xi: np.ndarray | None = None    # hold position {I}, m
        self.hold_yaw: float | None = None        # rad

    def ensure_hold_target(self, state: VehicleStateView) -> None:
        """Hold where the vehicle is, unless a hold point is set (or the state is not finite)."""
        if self.hold_xi is None and finite(state.xi_I, state.R_IB):
            self.set_hold_target(state)

    def set_hold_target(self, state: VehicleStateView) -> None:
        """Hold the position and yaw of ``state`` from now on."""
        self.hold_xi = np.array(state.xi_I, dtype=float)
        self.hold_yaw = euler_zyx_from_rot(state.R_IB)[2]

    def reference(self, state: VehicleStateView, armed: bool, mode: FlightMode,
                  setpoint_q: np.ndarray | None,
                  setpoint_thrust: float | None) -> AttitudeReference:
        """Return the reference of ``mode`` (``setpoint_*``: the latest offboard fields or None).

        Sets the hold point first if there is none (see :meth:`ensure_hold_target`).
        """
        self.ensure_hold_target(state)
        if not finite(state.xi_I, state.v_I, state.R_IB):
            self.counters.state_invalid += 1
            self._warn.warning('state', 'non-finite ground truth at t=%.3f: level, hover', state.t)
            return AttitudeReference(np.array([1.0, 0.0, 0.0, 0.0]),
                                     self.config.hover_thrust if armed else 0.0,
                                     ReferenceSource.FAILSAFE.value
                                     if armed else ReferenceSource.DISARMED.value)
        if not armed:
            return AttitudeReference(self.level_quat(state), 0.0, ReferenceSource.DISARMED.value)
        if mode is FlightMode.OFFBOARD:
            q = setpoint_q if setpoint_q is not None else self.level_quat(state)
            thrust = setpoint_thrust if setpoint_thrust is not None else self.config.hover_thrust
            return AttitudeReference(np.array(q, dtype=float), float(thrust),
                                     ReferenceSource.OFFBOARD.value)
        if mode is FlightMode.AUTO_LAND:
            return self.land_reference(state)
        return self.hold_reference(state)

    @staticmethod
    def level_quat(state: VehicleStateView) -> np.ndarray:
        """Return the level attitude (w, x, y, z) keeping the current yaw."""
        yaw = euler_zyx_from_rot(state.R_IB)[2]
        return quat_from_rot(rot_from_euler_zyx(0.0, 0.0, yaw))

    def thrust_attitude(self, acc_cmd_I: np.ndarray, yaw: float) -> tuple[np.ndarray, float]:
        """Return the attitude (w, x, y, z) and normalised thrust realising ``acc_cmd_I`` (m/s²).

        NED dynamics ``dv/dt = g e3 - (T/m) R e3``: the body z axis must point along
        ``g e3 - a`` and ``T/m = ‖g e3 - a‖``. The horizontal part is limited to ``max_tilt``;
        ``yaw`` in rad.
        """
        acc = np.array(acc_cmd_I, dtype=float)
        lift = GRAVITY - acc[2]                        # up-acceleration the thrust must provide
        lift = max(lift, MIN_LIFT_FRACTION * GRAVITY)
        horiz = acc[:2]
        horiz_max = lift * math.tan(self.config.max_tilt)
        n = float(np.linalg.norm(horiz))
        if n > horiz_max:
            horiz = horiz * (horiz_max / n)
        b3_I = np.array([-horiz[0], -horiz[1], lift])  # g e3 - a, body z (down) in {I}
        thrust_acc = float(np.linalg.norm(b3_I))
        # Express b3 in the yaw-aligned frame, then read roll/pitch of R = Rz(yaw) Ry Rx.
        b = rot_z(yaw).T @ (b3_I / thrust_acc)
        pitch = math.atan2(b[0], b[2])
        roll = math.atan2(-b[1], math.hypot(b[0], b[2]))
        q = quat_from_rot(rot_from_euler_zyx(roll, pitch, yaw))
        thrust = self.config.hover_thrust * thrust_acc / GRAVITY
        return q, float(np.clip(thrust, 0.0, 1.0))

    def hold_reference(self, state: VehicleStateView) -> AttitudeReference:
        """POSCTL / AUTO_LOITER: PD on ground-truth position towards the hold point, hold yaw."""
        c = self.config
        err = self.hold_xi - np.asarray(state.xi_I, dtype=float)
        v = np.asarray(state.v_I, dtype=float)
        kp = np.array([c.hold_kp_xy, c.hold_kp_xy, c.hold_kp_z])
        kd = np.array([c.hold_kd_xy, c.hold_kd_xy, c.hold_kd_z])
        q, thrust = self.thrust_attitude(kp * err - kd * v, self.hold_yaw)
        return AttitudeReference(q, thrust, ReferenceSource.HOLD.value)

    def land_reference(self, state: VehicleStateView) -> AttitudeReference:
        """AUTO_LAND / failsafe: level, current yaw, descent-rate loop on ground truth."""
        c = self.config
        v_down = float(np.asarray(state.v_I, dtype=float)[2])
        acc_down = c.land_speed_gain * (c.land_descent_rate - v_down)
        thrust = c.hover_thrust * (GRAVITY - acc_down) / GRAVITY
        return AttitudeReference(self.level_quat(state), float(np.clip(thrust, 0.0, 1.0)),
                                 ReferenceSource.FAILSAFE.value)
