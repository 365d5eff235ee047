"""The one module that converts between frames (docs/spec.md section 1). No other file does.

Frames
------
- ``I``   : the paper's inertial frame. Origin at the pad centre on the floor, x along the
            window normal eta_w (direction of travel), z **down** (gravity is ``+g e3``),
            y = z x x. It is also the autopilot's local NED frame (north = x_I).
- ``map`` : ROS world frame, ENU (REP-103/105). x_ENU = y_I, y_ENU = x_I, z_ENU = -z_I.
- ``B``   : the paper's body frame, FRD (x forward, y right, z down): MAVLink's body frame.
- ``base_link`` : ROS body frame, FLU.
- ``C``   : a camera's optical frame (z along the optical axis, x right, y down in the image).
            Mounted by ``R_BC`` (optical -> body FRD), a parameter of each camera.

Rotation names read ``R_AB``: it maps coordinates in B to coordinates in A (``x_A = R_AB x_B``),
so the paper's ``R = ^I_B R`` is ``R_IB``.
Quaternions are Hamilton, scalar first ``(w, x, y, z)`` as MAVLink sends them; ROS messages
store ``(x, y, z, w)``: use :func:`quat_wxyz_to_xyzw` / :func:`quat_xyzw_to_wxyz` at the border.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

GRAVITY = 9.80665  # m/s^2, standard gravity
MAP_FRAME = 'map'  # frame_id of the ROS world frame (ENU), = {I} rotated by R_MAP_I
BASE_FRAME = 'base_link'  # frame_id of the ROS body frame (FLU), = {B} rotated by R_FLU_FRD
e1 = np.array([1.0, 0.0, 0.0])
e2 = np.array([0.0, 1.0, 0.0])
e3 = np.array([0.0, 0.0, 1.0])

# map (ENU) <- I (NED-type). Symmetric and its own inverse.
R_MAP_I = np.array([[0.0, 1.0, 0.0],
                    [1.0, 0.0, 0.0],
                    [0.0, 0.0, -1.0]])
R_I_MAP = R_MAP_I.T
# base_link (FLU) <- B (FRD). Symmetric and its own inverse.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])
R_FRD_FLU = R_FLU_FRD.T

# Default camera mounts of docs/spec.md section 1 (optical -> body FRD). Parameters, not
# assumptions.
R_BC_DOWN_DEFAULT = np.array([[0.0, -1.0, 0.0],
                              [1.0, 0.0, 0.0],
                              [0.0, 0.0, 1.0]])
R_BC_FRONT_DEFAULT = np.array([[0.0, 0.0, 1.0],
                               [1.0, 0.0, 0.0],
                               [0.0, 1.0, 0.0]])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return a x b of two 3-vectors (3,): np.cross's operations, so its result to the bit.

    For the per-sample and per-frame vector algebra: np.cross spends ~20 us (on a normal
    machine) handling the axes of its general case, for 6 products.
    """
    a0, a1, a2 = np.asarray(a, dtype=float).tolist()
    b0, b1, b2 = np.asarray(b, dtype=float).tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def skew(w: np.ndarray) -> np.ndarray:
    """Return S(w), the skew-symmetric matrix with ``S(w) x = w x x`` (paper: Omega_x)."""
    wx, wy, wz = np.asarray(w, dtype=float)
    return np.array([[0.0, -wz, wy],
                     [wz, 0.0, -wx],
                     [-wy, wx, 0.0]])


def proj_orth(y: np.ndarray) -> np.ndarray:
    """Return pi_y = I3 - y y^T (paper eq:pi): projector onto the plane orthogonal to unit y."""
    y = np.asarray(y, dtype=float)
    return np.eye(3) - np.outer(y, y)


def rot_x(a: float) -> np.ndarray:
    """Elementary rotation R_X(a) (right hand, radians)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Elementary rotation R_Y(a) (right hand, radians)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Elementary rotation R_Z(a) (right hand, radians)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix exp(S(w)) of a rotation vector w (axis * angle, rad), Rodrigues."""
    w = np.asarray(rotvec, dtype=float).reshape(3)
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3) + skew(w)
    K = skew(w / th)
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * K @ K


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad, angle in [0, pi]) of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    th = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    if th < 1e-9:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if th > np.pi - 1e-6:                 # near pi: (R + I) / 2 = axis axis^T
        B = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(B)))
        return th * B[:, i] / np.sqrt(B[i, i])
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * th / (2.0 * np.sin(th))


def rot_from_euler_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Return R_IB = R_Z(yaw) R_Y(pitch) R_X(roll) (aerospace ZYX, NED/FRD, radians)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def euler_zyx_from_rot(R_IB: np.ndarray) -> tuple[float, float, float]:
    """Return (roll, pitch, yaw) in radians of R_IB = R_Z(yaw) R_Y(pitch) R_X(roll)."""
    R = np.asarray(R_IB, dtype=float)
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def yaw_and_cos_tilt_from_quat(q_wxyz: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """(yaw in rad, cos of the tilt) of an R_IB quaternion (FRD in NED, w x y z).

    yaw as :func:`euler_zyx_from_rot` (``atan2(R[1, 0], R[0, 0])``), cos tilt = ``R[2, 2]`` =
    e3 . R e3 clipped to [-1, 1], from the quaternion's matrix entries without building it
    (tested equal): the bridge reads both from every ATTITUDE_QUATERNION. Normalises; raises
    ValueError as :func:`rot_from_quat`.
    """
    w, x, y, z = _unit_quat(q_wxyz)
    yaw = math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))
    return yaw, min(1.0, max(-1.0, 1 - 2 * (x * x + y * y)))


def quat_from_rot(R: np.ndarray) -> np.ndarray:
    """Return the unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0.0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s,
                      (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s,
                      (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s,
                      (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s,
                      (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0.0 else -q


_SQRT_HALF = float(np.sqrt(0.5))


def _unit_quat(q_wxyz) -> tuple[float, float, float, float]:
    """(w, x, y, z) as floats divided by their norm; ValueError if non-finite or zero."""
    w, x, y, z = (float(v) for v in q_wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError(f'invalid quaternion {(w, x, y, z)!r}')
    return w / n, x / n, y / n, z / n


def rot_from_quat(q_wxyz: np.ndarray) -> np.ndarray:
    """Return the rotation matrix of a quaternion (w, x, y, z); normalises it first.

    Raises ValueError for a non-finite or zero-norm quaternion.
    """
    q = np.asarray(q_wxyz, dtype=float)
    n = np.linalg.norm(q)
    if not np.all(np.isfinite(q)) or n < 1e-9:
        raise ValueError(f'invalid quaternion {q!r}')
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder a (w, x, y, z) quaternion to ROS message order (x, y, z, w)."""
    return np.array([q[1], q[2], q[3], q[0]], dtype=float)


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder a ROS (x, y, z, w) quaternion to (w, x, y, z)."""
    return np.array([q[3], q[0], q[1], q[2]], dtype=float)


# --- Vectors -----------------------------------------------------------------------------

def vec_I_to_map(v_I: np.ndarray) -> np.ndarray:
    """Express a vector (or rows of vectors) given in {I} (NED-type) in ``map`` (ENU)."""
    return np.asarray(v_I, dtype=float) @ R_MAP_I.T


def vec_map_to_I(v_map: np.ndarray) -> np.ndarray:
    """Express a vector (or rows of vectors) given in ``map`` (ENU) in {I} (NED-type)."""
    return np.asarray(v_map, dtype=float) @ R_I_MAP.T


def vec_frd_to_flu(v_B: np.ndarray) -> np.ndarray:
    """Express a body vector (rates, accelerations) given in FRD in ``base_link`` (FLU)."""
    return np.asarray(v_B, dtype=float) @ R_FLU_FRD.T


def vec_flu_to_frd(v_flu: np.ndarray) -> np.ndarray:
    """Express a body vector given in ``base_link`` (FLU) in FRD."""
    return np.asarray(v_flu, dtype=float) @ R_FRD_FLU.T


# --- Attitudes ---------------------------------------------------------------------------

def rot_map_base_from_R_IB(R_IB: np.ndarray) -> np.ndarray:
    """Attitude of ``base_link`` (FLU) in ``map`` (ENU) from the paper's R_IB (FRD in NED)."""
    return R_MAP_I @ np.asarray(R_IB, dtype=float) @ R_FRD_FLU


def R_IB_from_rot_map_base(R_map_base: np.ndarray) -> np.ndarray:
    """Paper's R_IB (FRD in NED) from the attitude of ``base_link`` in ``map``."""
    return R_I_MAP @ np.asarray(R_map_base, dtype=float) @ R_FLU_FRD


def R_IB_from_quat_map_base(q_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """Paper's R_IB (FRD in NED) from a ROS attitude quaternion (FLU in ENU, w x y z).

    ``R_IB_from_rot_map_base(rot_from_quat(q))`` (tested equal) with the two fixed axis swaps
    done as row and column moves of the quaternion's matrix: row 0 of R_IB is row 1 of
    R_map_base, row 1 is row 0, row 2 is negated; columns 1 and 2 are negated. Scalar
    arithmetic: every node converts every imu/data sample (100 Hz). Normalises the
    quaternion; raises ValueError as :func:`rot_from_quat`.
    """
    w, x, y, z = _unit_quat(q_wxyz)
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return np.array([[r10, -r11, -r12],
                     [r00, -r01, -r02],
                     [-r20, r21, r22]])


def quat_ned_frd_to_enu_flu(q_wxyz: np.ndarray) -> np.ndarray:
    """Convert an autopilot attitude (FRD in NED, w x y z) to ROS (FLU in ENU, w x y z).

    The same conversion MAVROS applies to ATTITUDE_QUATERNION: ``q_MAP_I * q * q_FRD_FLU``
    with ``q_MAP_I = (0, 1, 1, 0) / sqrt 2`` (pi about the x = y axis, R_MAP_I) and
    ``q_FRD_FLU = (0, 1, 0, 0)`` (pi about x), in closed form; returned normalised with
    w >= 0, as :func:`quat_from_rot` (the matrix route, tested equal). Scalar arithmetic: the
    bridge converts every ATTITUDE_QUATERNION (100 Hz). Raises ValueError as
    :func:`rot_from_quat`.
    """
    w, x, y, z = _unit_quat(q_wxyz)
    out = np.array([w + z, x + y, x - y, w - z]) * _SQRT_HALF
    return out if out[0] >= 0.0 else -out


def quat_enu_flu_to_ned_frd(q_wxyz: np.ndarray) -> np.ndarray:
    """ROS attitude (FLU in ENU, w x y z) -> MAVLink attitude (FRD in NED, w x y z)."""
    return quat_from_rot(R_IB_from_rot_map_base(rot_from_quat(q_wxyz)))


# --- Cameras -----------------------------------------------------------------------------

def bearings_C_to_I(bearings_C: np.ndarray, R_IB: np.ndarray, R_BC: np.ndarray) -> np.ndarray:
    """Rotate unit bearings (rows) from a camera optical frame to {I}: p = R_IB R_BC b_C.

    This is the derotation of the paper's eq:pwi (and eq:barpi with R_BC = I for the
    down camera of the paper's mount).
    """
    return np.asarray(bearings_C, dtype=float) @ (np.asarray(R_IB) @ np.asarray(R_BC)).T


def bearings_I_to_C(bearings_I: np.ndarray, R_IB: np.ndarray, R_BC: np.ndarray) -> np.ndarray:
    """Inverse of :func:`bearings_C_to_I`: b_C = R_BC^T R_IB^T p."""
    return np.asarray(bearings_I, dtype=float) @ (np.asarray(R_IB) @ np.asarray(R_BC))


def camera_mount_in_base_link(R_BC: np.ndarray, t_BC: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Return a camera's mount as the ROS transform ``base_link`` -> its optical frame.

    From the mount of vehicle.yaml: ``R_BC`` maps optical-frame coordinates to body FRD and
    ``t_BC`` is the optical centre in body FRD (m). Returned as tf2 (REP-103) states a
    transform parent -> child: ``(translation, q_xyzw)`` with ``translation`` (3,) the optical
    centre expressed in ``base_link`` (FLU, m) and ``q_xyzw`` (4,) the unit quaternion, ROS
    message order (x, y, z, w), w >= 0, of ``R_FLU_C = R_FLU_FRD R_BC``, which maps
    optical-frame coordinates into ``base_link``: ``x_FLU = R_FLU_C x_C + translation``.
    """
    translation = R_FLU_FRD @ np.asarray(t_BC, dtype=float).reshape(3)
    q_wxyz = quat_from_rot(R_FLU_FRD @ np.asarray(R_BC, dtype=float))
    return translation, quat_wxyz_to_xyzw(q_wxyz)


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> bool:
    """Tell whether R is a proper rotation matrix (orthonormal, det +1) within tol.

    Orthonormal: every element of ``R R^T - I`` within tol; det by the rule of Sarrus.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        return False
    if float(np.abs(R @ R.T - _EYE3).max()) > tol:
        return False
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    return abs(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) - 1.0) < tol


_EYE3 = np.eye(3)
