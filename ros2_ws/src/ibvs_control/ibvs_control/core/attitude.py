"""Outer-loop force -> attitude and collective-thrust setpoint (paper section 2, eq:F).

The paper's force obeys ``m v_dot = -F + m g e3`` (eq:system) with ``F = F_T R e3`` (eq:F): F is
expressed in {I} (NED-type, z down) and points along the body z axis (FRD, down), so hover is
``F = m g e3`` with a level attitude. The desired attitude R_d has ``R_d e3 = F / |F|`` and the
desired yaw; the collective thrust is ``F_T = |F|``, normalised for the autopilot with a linear
hover-thrust model ``thrust_norm = F_T / (m g) * hover_thrust``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ibvs_common.core.frames import cross3, GRAVITY, e3, quat_from_rot

MIN_FORCE_N = 1e-3          # below this |F| carries no direction: keep the body z axis vertical
DEFAULT_MAX_TILT_RAD = 0.6  # ~34 deg: tilt limit of the thrust direction (vertical part kept)


@dataclass(frozen=True)
class AttitudeSetpoint:
    """Desired attitude (body FRD in {I}) and collective thrust."""

    R_IB_des: np.ndarray     # 3x3 rotation, body FRD -> {I}
    q_IB_wxyz: np.ndarray    # the same as a unit quaternion (w, x, y, z)
    thrust_N: float          # F_T, newtons
    thrust_norm: float       # autopilot's normalised collective thrust in [0, 1]


def limit_tilt(F_I: np.ndarray, max_tilt_rad: float = DEFAULT_MAX_TILT_RAD) -> np.ndarray:
    """Limit the angle between F and e3 to max_tilt_rad, keeping F's vertical component.

    A force with no downward (e3) component (which would need an inverted vehicle) is
    replaced by its horizontal part scaled onto the tilt cone at a minimum vertical force.
    """
    F = np.asarray(F_I, dtype=float)
    Fz = max(F[2], MIN_FORCE_N)
    F_h = F[:2]
    max_h = Fz * np.tan(max_tilt_rad)
    n_h = np.linalg.norm(F_h)
    if n_h > max_h:
        F_h = F_h * (max_h / n_h)
    return np.array([F_h[0], F_h[1], Fz])


def rotation_from_thrust_direction(z_B_I: np.ndarray, yaw: float) -> np.ndarray:
    """Return R_IB whose third column is the unit vector z_B_I and whose ZYX yaw is ``yaw``.

    ``yaw`` is the NED yaw (rad, about +z down, 0 = body x along x_I). Construction (as PX4's
    attitude setpoint generation): y_c = (-sin yaw, cos yaw, 0); x_B = unit(y_c x z_B);
    y_B = z_B x x_B. x_B is orthogonal to y_c, so its horizontal heading is exactly ``yaw``.
    """
    z_B = np.asarray(z_B_I, dtype=float)
    z_B = z_B / np.linalg.norm(z_B)
    y_c = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    x_B = cross3(y_c, z_B)
    n = np.linalg.norm(x_B)
    if n < 1e-6:  # thrust axis horizontal along y_c: degenerate, keep the heading axis
        x_B = cross3(cross3(z_B, np.array([np.cos(yaw), np.sin(yaw), 0.0])), z_B)
        n = np.linalg.norm(x_B)
    x_B /= n
    y_B = cross3(z_B, x_B)
    return np.column_stack([x_B, y_B, z_B])


def attitude_from_force(F_I: np.ndarray, yaw_des: float, mass: float, hover_thrust: float,
                        max_thrust_factor: float = 2.0,
                        max_tilt_rad: float = DEFAULT_MAX_TILT_RAD) -> AttitudeSetpoint:
    """Turn the paper's force F (N, in {I}) and a yaw into an attitude + thrust setpoint.

    R_d e3 = F/|F| (eq:F), heading = yaw_des; thrust_N = |F| after the tilt limit;
    thrust_norm = thrust_N / (m g) * hover_thrust, clipped to [0, 1] (and to the vehicle's
    maximum, max_thrust_factor * m g).
    Raises ValueError for a non-finite F or yaw.
    """
    F = np.asarray(F_I, dtype=float)
    if F.shape != (3,) or not np.all(np.isfinite(F)) or not np.isfinite(yaw_des):
        raise ValueError(f'non-finite force {F!r} or yaw {yaw_des!r}')
    F = limit_tilt(F, max_tilt_rad)
    thrust_N = float(min(np.linalg.norm(F), max_thrust_factor * mass * GRAVITY))
    z_B = F / np.linalg.norm(F) if np.linalg.norm(F) > MIN_FORCE_N else e3
    R_d = rotation_from_thrust_direction(z_B, yaw_des)
    thrust_norm = float(np.clip(thrust_N / (mass * GRAVITY) * hover_thrust, 0.0, 1.0))
    return AttitudeSetpoint(R_d, quat_from_rot(R_d), thrust_N, thrust_norm)


def yaw_facing(eta_w_I: np.ndarray, R_BC_front: np.ndarray) -> float:
    """Return the NED yaw that points the forward camera's optical axis along eta_w.

    The optical axis in body FRD is ``R_BC[:, 2]``; its heading in the body is
    beta = atan2(a_y, a_x). The yaw psi puts it on the heading of eta_w's horizontal part:
    psi = atan2(eta_y, eta_x) - beta. Valid for any mount whose optical axis is not vertical.
    """
    a = np.asarray(R_BC_front, dtype=float)[:, 2]
    beta = np.arctan2(a[1], a[0])
    eta = np.asarray(eta_w_I, dtype=float)
    psi = np.arctan2(eta[1], eta[0]) - beta
    return float(np.arctan2(np.sin(psi), np.cos(psi)))


def shutdown_thrust_scale(t_since_shutdown_s: float, ramp_time_s: float) -> float:
    """Mode 4 thrust ramp: 1 at the switch, falling linearly to 0 after ramp_time_s."""
    if ramp_time_s <= 0.0:
        return 0.0
    return float(np.clip(1.0 - t_since_shutdown_s / ramp_time_s, 0.0, 1.0))
