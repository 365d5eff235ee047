"""Spherical image features of the paper, section 3 (landing plane and window plane).

All bearings are unit vectors from the camera centre (= body origin) to a scene point. Unless a
name says otherwise they are expressed in the paper's inertial frame {I} (derotated with the IMU
attitude: ``p = R_IB R_BC b_C``, see frames.bearings_C_to_I). Distances are metres, flows 1/s.

Window corners come in a fixed order: top-left, top-right, bottom-right, bottom-left as seen
from the approach side; edge i joins corner i and corner i+1 (top, right, bottom, left).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ibvs_common.core.frames import cross3

_EPS = 1e-9


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x)
    if n < _EPS:
        raise ValueError(f'cannot normalise a (near) zero vector {x!r}')
    return x / n


def centroid_feature(bearings_I: np.ndarray) -> np.ndarray:
    """Return q = -(1/n) sum p_i, the centroid feature of eq:q_t (landing) and q_w (window).

    Sign: q points from the observed points towards the camera (for a landmark set centred on
    the origin of {I}, q is parallel to xi / |xi| at long range).
    """
    p = np.asarray(bearings_I, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError('no bearings')
    return -p.mean(axis=0)


def edge_normals(corner_bearings: np.ndarray) -> np.ndarray:
    """Return the edge normals h_i = unit(p_i x p_{i+1}), shape (4, 3), in the bearings' frame.

    h_i is the normal of the plane through the camera centre and edge i (binormalised Plucker
    coordinates, paper section 3.2).
    """
    p = np.asarray(corner_bearings, dtype=float).reshape(4, 3)
    return np.array([_unit(cross3(p[i], p[(i + 1) % 4])) for i in range(4)])


def window_axes(h: np.ndarray, corner_bearings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (u_w, rho_w), the window's edge directions from parallel edge pairs.

    The direction of a 3-D line lies in its interpretation plane, so the common direction of
    the two parallel edges i and i+2 is h_i x h_{i+2}. u_w is the direction of the vertical
    edges (right, left), oriented from the top corners to the bottom corners; rho_w that of the
    horizontal edges (top, bottom), oriented from left to right corners. Then
    (eta_w, rho_w, u_w) is right-handed with rho_w = u_w x eta_w (paper's axes).
    """
    p = np.asarray(corner_bearings, dtype=float).reshape(4, 3)
    rho_w = _unit(cross3(h[0], h[2]))
    u_w = _unit(cross3(h[1], h[3]))
    if rho_w @ ((p[1] + p[2]) - (p[0] + p[3])) < 0.0:
        rho_w = -rho_w
    if u_w @ ((p[2] + p[3]) - (p[0] + p[1])) < 0.0:
        u_w = -u_w
    return u_w, rho_w


def window_normal(u_w: np.ndarray, rho_w: np.ndarray, q_w: np.ndarray,
                  eta_ref: np.ndarray | None = None) -> np.ndarray:
    """Return eta_w = +-unit(u_w x rho_w) (eq:etaw).

    Sign rule of the paper: eta_w^T q_w < 0 (eta_w points from the vehicle's side through the
    window, the direction of travel). When eta_ref (the previous estimate) is given, continuity
    with it decides instead, so that the sign cannot flip near the window plane.
    """
    eta = _unit(cross3(u_w, rho_w))
    if eta_ref is not None:
        return eta if eta @ eta_ref >= 0.0 else -eta
    return eta if eta @ q_w < 0.0 else -eta


def closest_edge_direction(h: np.ndarray, u_w: np.ndarray, rho_w: np.ndarray,
                           eta_w: np.ndarray, corner_bearings: np.ndarray) -> np.ndarray:
    """Return l^e, the unit direction from the camera to the closest point of the closest edge.

    For edge i the direction to its nearest point lies in its plane (normal h_i) and is
    orthogonal to the edge: l_i = +-(h_i x d_i) with d_i = rho_w (top, bottom) or u_w (right,
    left), oriented towards the edge (positive dot product with its corner bearings). Every
    edge lies in the wall plane at distance d_o, so eta_w^T l_i = d_o / |L_i| and the closest
    edge is the one with the largest |eta_w^T l_i| (paper, after eq:region).
    """
    p = np.asarray(corner_bearings, dtype=float).reshape(4, 3)
    best, best_score = None, -1.0
    for i in range(4):
        d = rho_w if i % 2 == 0 else u_w
        l_i = _unit(cross3(h[i], d))
        if l_i @ (p[i] + p[(i + 1) % 4]) < 0.0:
            l_i = -l_i
        score = abs(float(eta_w @ l_i))
        if score > best_score:
            best, best_score = l_i, score
    return best


def alpha_w(q_w_norm: float, eps: float, delta: float) -> float:
    """Return the weight alpha_w of eq:alphaw: 0 inside W (|q_w| <= eps), 1 beyond eps+delta."""
    if q_w_norm <= eps:
        return 0.0
    if q_w_norm >= eps + delta:
        return 1.0
    return float((q_w_norm - eps) / delta)


def window_feature_bar(p_w: np.ndarray, eta_w: np.ndarray, l_e: np.ndarray,
                       alpha: float) -> np.ndarray:
    """Return q_bar_w of eq:qw.

    q_bar_w = -(1/n) sum p_i [alpha / (eta^T p_i) + (1 - alpha) (eta^T l_e) / (eta^T p_i)],
    which equals alpha xi_w / d_o + (1 - alpha) xi_w / d_e (eq d_w), xi_w being the vehicle
    position relative to the window centre, d_o the distance to the wall plane and d_e that to
    the closest edge.
    """
    p = np.asarray(p_w, dtype=float).reshape(-1, 3)
    cos_i = p @ eta_w
    if np.any(cos_i <= _EPS):
        raise ValueError('a window corner is not in front of the vehicle along eta_w')
    weight = alpha + (1.0 - alpha) * float(eta_w @ l_e)
    return -(p / cos_i[:, None]).mean(axis=0) * weight


def window_flow(phi_wall: np.ndarray, eta_w: np.ndarray, l_e: np.ndarray,
                alpha: float) -> np.ndarray:
    """Return phi_w of eq:phi_w = alpha v/d_o + (1 - alpha) v/d_e.

    Both terms come from the wall's translational flow phi_wall = v/d_o, since
    v/d_e = (d_o/d_e) v/d_o and d_o/d_e = eta_w^T l^e.
    """
    return np.asarray(phi_wall, dtype=float) * (alpha + (1.0 - alpha) * float(eta_w @ l_e))


def distance_to_window_plane(corner_bearings_I: np.ndarray, eta_w: np.ndarray,
                             r_w: float) -> float:
    """Return d_o (m) from the corner bearings and the known window width r_w.

    Corner i is at P_i = d_o p_i / (eta^T p_i); the top and bottom edges have length r_w, so
    d_o = r_w / |p_TR/(eta^T p_TR) - p_TL/(eta^T p_TL)| (averaged over both edges). Used by
    the mode supervisor (blind-crossing length) and by the disturbance observer's velocity
    channel (v = d_o times the wall flow v / d_o), never by the force laws themselves.
    """
    p = np.asarray(corner_bearings_I, dtype=float).reshape(4, 3)
    s = p / (p @ eta_w)[:, None]
    width = 0.5 * (np.linalg.norm(s[1] - s[0]) + np.linalg.norm(s[2] - s[3]))
    return float(r_w / width)


def window_centre_offset(corner_bearings_I: np.ndarray, eta_w: np.ndarray,
                         r_w: float) -> np.ndarray:
    """Return the window centre's offset (m, {I}) from the camera, in the window plane.

    With the corners at P_i = d_o s_i, s_i = p_i / (eta^T p_i) and d_o from
    :func:`distance_to_window_plane`, the centre (the mean of a rectangle's corners) is
    d_o mean(s_i), and its part orthogonal to eta is d_o (mean(s_i) - eta) (eta^T s_i = 1):
    how far off the window's axis the camera is, as the image tells (no position estimate).
    """
    p = np.asarray(corner_bearings_I, dtype=float).reshape(4, 3)
    eta = np.asarray(eta_w, dtype=float).reshape(3)
    s = p / (p @ eta)[:, None]
    return distance_to_window_plane(p, eta, r_w) * (s.mean(axis=0) - eta)


@dataclass(frozen=True)
class WindowFeatures:
    """The window features of section 3.2, all in {I}."""

    q_w: np.ndarray
    eta_w: np.ndarray
    u_w: np.ndarray
    rho_w: np.ndarray
    l_e: np.ndarray
    alpha_w: float
    q_w_bar: np.ndarray


def compute_window_features(corner_bearings_I: np.ndarray, eps: float, delta: float,
                            eta_ref: np.ndarray | None = None) -> WindowFeatures:
    """All window features from the 4 corner bearings in {I} (order TL, TR, BR, BL).

    Raises ValueError for a degenerate view (corners aligned, window edge-on).
    """
    p = np.asarray(corner_bearings_I, dtype=float).reshape(4, 3)
    if not np.all(np.isfinite(p)):
        raise ValueError('non-finite corner bearing')
    q_w = centroid_feature(p)
    h = edge_normals(p)
    u_w, rho_w = window_axes(h, p)
    eta_w = window_normal(u_w, rho_w, q_w, eta_ref)
    l_e = closest_edge_direction(h, u_w, rho_w, eta_w, p)
    a = alpha_w(float(np.linalg.norm(q_w)), eps, delta)
    q_w_bar = window_feature_bar(p, eta_w, l_e, a)
    return WindowFeatures(q_w, eta_w, u_w, rho_w, l_e, a, q_w_bar)


#: marker pairs of a group (layout id order: (+c,+c), (+c,-c), (-c,-c), (-c,+c)) and their
#: distance in units of c: the four sides 2 c, the two diagonals 2 sqrt(2) c
_GROUP_PAIRS = ((0, 1, 2.0), (1, 2, 2.0), (2, 3, 2.0), (3, 0, 2.0),
                (0, 2, 2.0 * np.sqrt(2.0)), (1, 3, 2.0 * np.sqrt(2.0)))


def pad_height_estimate(group_bearings_I: np.ndarray, c: float,
                        eta_t: np.ndarray | None = None) -> float:
    """Height (m) above the landing plane from one complete marker group (mode 3 -> 4 cue).

    The markers lie on the plane of normal eta_t (down, {I}) at the camera's height h below
    it, so marker i is at h p_i / (eta_t^T p_i) from the camera: their distances scale with h.
    With the group's known geometry (centres at (+-c, +-c): sides 2 c, diagonals 2 sqrt(2) c)
    h is the least-squares scale over the 6 pairs, h = sum L_k l_k / sum l_k^2, l_k the
    distance at unit height. Exact from any lateral offset and attitude (given the attitude
    used to express the bearings in {I}). The earlier estimate from the centroid's vertical
    component alone, h = sqrt(2) c cos(theta) / sin(theta), read the lateral offset x as the
    group's size: h sqrt(2) c / x, a third of the height for group D 0.17 m off the pad
    (measured on PX4 SIH: SHUTDOWN at a read 0.107 m, then a 2.1 m/s touchdown).
    Bearings (4, 3) in layout id order; raises ValueError when a bearing does not point
    towards the plane.
    """
    eta = np.array([0.0, 0.0, 1.0]) if eta_t is None else np.asarray(eta_t, dtype=float)
    p = np.asarray(group_bearings_I, dtype=float).reshape(4, 3)
    depth = p @ eta
    if np.any(depth <= _EPS):
        raise ValueError('a marker bearing does not point towards the landing plane')
    X = p / depth[:, None]                       # the markers at unit height
    lengths = np.array([np.linalg.norm(X[i] - X[j]) for i, j, _ in _GROUP_PAIRS])
    known = c * np.array([k for _, _, k in _GROUP_PAIRS])
    return float(lengths @ known / (lengths @ lengths))


#: a group's 4 marker centres on the pad in units of its half-side c, layout id order
_GROUP_UNIT_SQUARE = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0]])
#: smallest accepted scale of a marker bearing in the plane map (degenerate group view)
_MIN_PLANE_MAP_SCALE = 1e-9


def pad_plane_map(group_bearings: np.ndarray, c: float) -> np.ndarray:
    """Return the map M (3, 3) of the pad plane to the camera's rays, from one complete group.

    The vector from the camera to the pad point (x, y) (metres, pad axes of pad_layout.yaml,
    origin at the pad centre) is linear in (x, y, 1): ``R [e1, e2, -xi] (x, y, 1)`` for a
    camera at xi in {I} and any rotation R of the bearings' frame. Its 4 marker centres
    (+-c, +-c) seen as unit bearings fix that map up to one positive scale:
    ``M (x, y, 1) = s (point - camera)``, s > 0, in the bearings' frame (any frame: {I},
    optical). M is the homography of the group's 4 centres, so M (0, 0, 1) is the
    intersection of the image diagonals: the pad centre is where every group's centre is.
    Bearings (4, 3) in layout id order ((+c,+c), (+c,-c), (-c,-c), (-c,+c)); raises
    ValueError for a degenerate view (3 centres on one great circle, or a marker behind the
    others: a sign the 4 bearings are not a square's image).
    """
    p = np.asarray(group_bearings, dtype=float).reshape(4, 3)
    if not (np.all(np.isfinite(p)) and c > 0.0):
        raise ValueError('non-finite bearing or non-positive group size')
    P = p[:3].T
    try:
        b = np.linalg.solve(P, p[3])
    except np.linalg.LinAlgError as exc:
        raise ValueError('degenerate pad group view') from exc
    # u3 = u0 - u1 + u2 for the square's homogeneous points, so lambda_k a_k = b_k with
    # a = (1, -1, 1) (M u_k = lambda_k p_k, lambda_3 = 1)
    lam = b * np.array([1.0, -1.0, 1.0])
    if np.any(lam < _MIN_PLANE_MAP_SCALE):
        raise ValueError('pad group bearings are not the view of a square')
    U = np.vstack([c * _GROUP_UNIT_SQUARE[:3].T, np.ones(3)])
    return (P * lam) @ np.linalg.inv(U)


def pad_reference_bearings(group_bearings: np.ndarray, c: float,
                           reference_xy: np.ndarray) -> np.ndarray:
    """Return the unit bearings (m, 3) of pad points ``reference_xy`` (m, 2; metres).

    The points are seen through one complete group's plane map (pad_plane_map), in the frame
    of its bearings. Exact in geometry: any complete group gives the same bearings of the
    same pad points.
    """
    M = pad_plane_map(group_bearings, c)
    xy = np.asarray(reference_xy, dtype=float).reshape(-1, 2)
    r = np.column_stack([xy, np.ones(len(xy))]) @ M.T
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def pad_reference_points(reference_half_side: float) -> np.ndarray:
    """Return the pad points (m, 2; metres) q_t is defined on: the centre or a square around it.

    ``reference_half_side`` 0: the pad centre alone; r > 0: the 4 points (+-r, +-r).
    """
    r = float(reference_half_side)
    if r < 0.0:
        raise ValueError(f'reference half-side must be >= 0, got {r}')
    return np.zeros((1, 2)) if r == 0.0 else r * _GROUP_UNIT_SQUARE


def pad_feature(landmark_bearings: np.ndarray, half_sides: list[float] | None = None,
                reference_half_side: float = 0.0,
                weights: list[float] | None = None) -> np.ndarray:
    """Return q_t = -(1/n) sum p_j over a fixed set of pad points, from any complete groups.

    eq:q_t on a landmark set that does not depend on which groups are complete: the pad
    points of pad_reference_points(reference_half_side) (default: the pad centre alone,
    q_t = -p_centre = xi / |xi|), each seen through every complete group's plane map
    (pad_reference_bearings) and averaged over the groups. In geometry every group gives
    the same q_t, so a group appearing or disappearing changes it only by the groups'
    measurement noise. The centroid of the groups' own marker centres (centroid_feature)
    is a different vector for each set of groups (rings of other radii: another magnitude
    and, off the pad's axis or tilted, another direction).

    ``landmark_bearings`` (4 k, 3): the 4 marker-centre bearings of each of k complete
    groups, groups one after the other, each in layout id order (pad/landmarks); the frame
    of q_t is theirs. ``half_sides``: each group's c (m); needed only when
    ``reference_half_side`` > 0 (the pad centre is the same point in every group's units).
    A group whose view is degenerate (pad_plane_map) is left out. ``weights`` (one per group,
    >= 0, not all 0; None: equal): a weighted mean over the groups instead, so that a group can
    come and go with a weight near 0 (the pad detector's group weights: small near the image
    border and for markers near the size ArUco can read) and a bias of its own (a calibration
    error, its markers' blur) moves q_t gradually instead of by a step. Raises ValueError for
    no group, a count that is not 4 k, weights that are not one per group, or when every group
    is degenerate.
    """
    p = np.asarray(landmark_bearings, dtype=float).reshape(-1, 3)
    k = len(p) // 4
    if k == 0 or len(p) != 4 * k:
        raise ValueError(f'need 4 bearings per complete group, got {len(p)}')
    ref = pad_reference_points(reference_half_side)
    if reference_half_side > 0.0:
        if half_sides is None or len(half_sides) != k:
            raise ValueError('half_sides (one per group) are needed for a reference square')
        cs = [float(c) for c in half_sides]
    else:
        cs = [1.0] * k
    if weights is not None:
        w_all = np.asarray(weights, dtype=float).reshape(-1)
        if len(w_all) != k or not np.all(np.isfinite(w_all)) or np.any(w_all < 0.0) \
                or not np.any(w_all > 0.0):
            raise ValueError(f'weights: one finite weight >= 0 per group ({k}), not all 0, '
                             f'got {list(w_all)}')
    rays, w = [], []
    for g in range(k):
        try:
            rays.append(pad_reference_bearings(p[4 * g:4 * g + 4], cs[g], ref))
        except ValueError:
            continue
        w.append(1.0 if weights is None else float(w_all[g]))
    if not rays or not sum(w) > 0.0:
        raise ValueError('no pad group gives a non-degenerate view')
    if weights is None:
        return -np.mean(np.concatenate(rays), axis=0)
    return -np.average(np.concatenate(rays), axis=0, weights=np.repeat(w, len(ref)))
