"""Camera features as seen from the body origin: the cameras' lever arms ``t_BC`` (vehicle.yaml).

The paper's features are bearings and flows seen from the vehicle's centre. A real camera's
optical centre is a few centimetres away, at ``xi + R_IB t_BC`` ({I}); uncorrected, the
vehicle would fly the camera, not its centre, through the window and onto the pad (a down
camera 8 cm off centre lands 8 cm off). The points the features are made of lie on known
planes at distances the images measure (the window plane: its normal and, from the known
width, its distance; the floor: the pad's known marker spacing gives the height), so each
point is located from the camera and its bearing taken again from the body origin:

    X_i = d_C q_i / (eta^T q_i)      (from the camera; eta the plane's unit normal pointing
                                      from the camera towards it, d_C its distance)
    q_i' = unit(X_i + t_BC_I)        (from the body origin; t_BC_I = R_IB t_BC)

Flows v/d of a plane: the camera moves at v_C = v + omega x t_BC_I (omega the body rate in
{I}: a rotation about the body origin carries the camera along), its translational flow is
phi = v_C / d_C (the flow estimator removes the rotation of the view, not this), so the body
origin's is phi' = (phi d_C - omega x t_BC_I) / (d_C + eta^T t_BC_I). Without omega only the
distance is corrected (the rotation's part, at most |omega| |t_BC|: 2.5 cm/s at 0.5 rad/s and
5 cm, stays). All vectors in {I}; m, rad, rad/s; with t_BC = 0 everything is returned
unchanged. ROS-free.
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.features import (centroid_feature, distance_to_window_plane,
                                       edge_normals, pad_height_estimate, window_axes,
                                       window_normal)

E3 = np.array([0.0, 0.0, 1.0])      # the floor's normal in {I} (z down): from above, towards it


def has_lever_arm(t_BC: np.ndarray) -> bool:
    """Whether a camera's lever arm is not zero (then the features are corrected)."""
    return bool(np.any(np.asarray(t_BC, dtype=float) != 0.0))


def plane_bearings_from_body(bearings_I: np.ndarray, eta_I: np.ndarray, distance_C: float,
                             t_BC_I: np.ndarray) -> np.ndarray:
    """Return the bearings of points of a plane as seen from the body origin (module doc).

    ``bearings_I`` (N, 3) unit, from the camera; ``eta_I`` the plane's unit normal from the
    camera towards it; ``distance_C`` (m) the camera's distance to the plane along it.
    Raises ValueError for a bearing that does not point towards the plane or a distance <= 0.
    """
    q = np.asarray(bearings_I, dtype=float).reshape(-1, 3)
    depth = q @ np.asarray(eta_I, dtype=float)
    if not distance_C > 0.0 or np.any(depth <= 1e-9):
        raise ValueError('a point does not lie ahead on the plane (bearing or distance)')
    X = distance_C * q / depth[:, None] + np.asarray(t_BC_I, dtype=float)
    return X / np.linalg.norm(X, axis=1, keepdims=True)


def window_plane(corners_I: np.ndarray, r_w: float, eta_ref: np.ndarray | None = None
                 ) -> tuple[np.ndarray, float]:
    """Return the window plane seen from the camera: (eta_w, distance d_o in m).

    From the 4 corner bearings (TL, TR, BR, BL) and the known width ``r_w`` (features.py:
    eq:etaw and the width's scale). Raises ValueError for a degenerate view.
    """
    p = np.asarray(corners_I, dtype=float).reshape(4, 3)
    u_w, rho_w = window_axes(edge_normals(p), p)
    eta = window_normal(u_w, rho_w, centroid_feature(p), eta_ref)
    return eta, distance_to_window_plane(p, eta, r_w)


def window_corners_from_body(corners_I: np.ndarray, t_BC_I: np.ndarray, r_w: float,
                             eta_ref: np.ndarray | None = None) -> np.ndarray:
    """Return the window corners' bearings from the body origin (from the camera's)."""
    eta, d_o = window_plane(corners_I, r_w, eta_ref)
    return plane_bearings_from_body(corners_I, eta, d_o, t_BC_I)


def pad_height_from_groups(landmarks_I: np.ndarray, groups: list, half_sides: dict
                           ) -> float | None:
    """Return the camera's height above the pad from its smallest complete group, or None.

    ``landmarks_I``: 4 bearings per group, in the order of ``groups`` (names); ``half_sides``:
    name -> c (m), pad_layout.yaml.
    """
    sizes = [(half_sides[g], i) for i, g in enumerate(groups) if g in half_sides]
    if not sizes:
        return None
    c, i = min(sizes)
    p = np.asarray(landmarks_I, dtype=float).reshape(-1, 3)
    try:
        return pad_height_estimate(p[4 * i:4 * i + 4], c)
    except ValueError:
        return None


def pad_landmarks_from_body(landmarks_I: np.ndarray, groups: list, half_sides: dict,
                            t_BC_I: np.ndarray) -> np.ndarray | None:
    """Return the pad landmarks' bearings from the body origin, None if no height is known."""
    h_C = pad_height_from_groups(landmarks_I, groups, half_sides)
    if h_C is None or not h_C > 0.0:
        return None
    return plane_bearings_from_body(landmarks_I, E3, h_C, t_BC_I)


def flow_from_body(phi_C_I: np.ndarray, eta_I: np.ndarray, distance_C: float,
                   t_BC_I: np.ndarray, omega_I: np.ndarray | None = None) -> np.ndarray:
    """Return a plane's flow v/d at the body origin from the camera's (module doc).

    ``distance_C``: the camera's distance to the plane along ``eta_I`` (from camera to plane);
    ``omega_I``: the body rate (rad/s) in {I}, or None (then only the distance is corrected).
    """
    t = np.asarray(t_BC_I, dtype=float)
    d_body = distance_C + float(np.asarray(eta_I, dtype=float) @ t)
    if not (distance_C > 0.0 and d_body > 0.0):
        raise ValueError(f'plane distances must be > 0 (camera {distance_C}, body {d_body})')
    v_C = np.asarray(phi_C_I, dtype=float) * distance_C
    if omega_I is not None:
        v_C = v_C - np.cross(np.asarray(omega_I, dtype=float), t)
    return v_C / d_body


def camera_bearings_from_body(camera: str, bearings_I: np.ndarray, t_BC_I: np.ndarray,
                              r_w: float, half_sides: dict, groups: tuple = ()) -> np.ndarray:
    """Return a camera's product bearings from the body origin (the camera's if unknown).

    ``camera`` 'front': the window's corners (its plane from its known width ``r_w``);
    'down': the pad's landmarks of ``groups`` (the height from the group sizes
    ``half_sides``). A view too degenerate for its plane keeps the camera's bearings.
    """
    if not has_lever_arm(t_BC_I):
        return bearings_I
    try:
        if camera == 'front':
            return window_corners_from_body(bearings_I, t_BC_I, r_w)
        body = pad_landmarks_from_body(bearings_I, list(groups), half_sides, t_BC_I)
        return bearings_I if body is None else body
    except ValueError:
        return bearings_I
