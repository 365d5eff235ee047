"""Translational optical flow phi = v / d of a plane of known normal, from one camera.

Paper eq:p_t (floor) and its wall analogue: a static point of a plane with unit normal eta
(from the camera towards the plane, in {I}) at distance d has the derotated bearing rate

    p_dot = -(eta^T p) pi_p phi,       phi = v / d   (1/s, in {I}),

where p is the unit bearing in {I} (p = R_IB R_BC b_C, frames.bearings_C_to_I) and
pi_p = I - p p^T (eq:pi). Derotation uses the IMU attitude at each image stamp, so the rotation
between frames cancels exactly (up to the attitude error).

Two planes (the front camera sees the floor below the wall): with a second plane of known
normal eta_2 (the floor, e3) at distance d_2, the same v gives a point its nearer surface's
inverse range, so the model of every point becomes

    p_dot = -c(p) pi_p phi,    c(p) = max(eta^T p, s eta_2^T p),    s = d / d_2,

with one more unknown, the distance ratio s (>= 0; s = 0: the second plane is not in view).
The point is on the second plane exactly when s eta_2^T p > eta^T p: the assignment is
geometric, not a residual test. phi and s are fitted alternately (phi by least squares with
c fixed, s by least squares over the points that the first plane does not explain).

The IMU's attitude error between two images is not zero (a real gyro's noise: ~1 mrad over
20 ms about the front camera's axis on PX4 SIH). About an axis across the view it moves
every point alike, as a sideways translation does, and the fit absorbs it as a small phi
error; about the optical axis a it turns the image, which no translation explains, and
above ~0.5 px at the image corners it took most tracks out of the inlier gate. With
``fit_axis_rotation`` the model carries that rotation, a rate omega about a fitted with phi:

    p_dot = -c(p) pi_p phi + omega (a x p).

Pipeline per image (docs/perception.md "Translational optical flow" has it in full):
pyramidal Lucas-Kanade of the tracked features from the previous image, each started where the
IMU's rotation moves it (``lk_predict``), on as few pyramid levels as the motion left asks for
(:func:`pyramid_levels_for`); tracks derotated to {I}; a longer baseline over persisting
tracks when the motion is slow (``max_baseline_frames``); phi by Huber-weighted least squares
and an inlier gate; features replenished only in grid cells short of tracks.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math

import cv2
import numpy as np

from ibvs_common.core.params import param
from ibvs_common.core.camera import CameraModel
from ibvs_common.core.features import (centroid_feature, edge_normals, window_axes,
                                       window_normal)
from ibvs_common.core.frames import bearings_C_to_I, bearings_I_to_C

#: largest condition number of the normal equations accepted (a degenerate point spread)
_MAX_CONDITION = 1e8
#: the pyramid levels of a predicted track reach this many times the previous image's motion
#: left after the prediction (module doc)
LK_MOTION_MARGIN = 2.0


DEFAULT_FRAME_PERIOD_S = 0.02     # s, a 50 Hz camera computing every frame


@dataclass(frozen=True)
class FlowConfig:
    """Tuning of :class:`FlowEstimator` (pixels are distorted image pixels)."""

    grid_cols: int = param(8, 'columns of the feature replenishment grid', 1, 1000)
    grid_rows: int = param(6, 'rows of the feature replenishment grid', 1, 1000)
    min_tracks_per_cell: int = param(3, 'tracks: a grid cell with fewer gets new features', 0)
    features_per_cell: int = param(6, 'goodFeaturesToTrack budget per replenished cell', 1)
    replenish_every_n_frames: int = param(5, 'frames: replenishment period', 1)
    min_tracks: int = param(60, 'tracks: fewer, replenish at once', 0)
    quality_level: float = param(
        0.02, 'goodFeaturesToTrack quality, fraction of the best corner, (0, 1]', 0.0, 1.0)
    min_distance_px: float = param(10.0, 'px, least distance between features', 0.0)
    lk_window_px: int = param(15, 'px, side of the Lucas-Kanade window, >= 3', 3, 1001)
    lk_pyramid_levels: int = param(
        3,
        'Lucas-Kanade pyramid levels above the base image; with lk_predict the most used (fewer '
        'while the motion left after the prediction is small)', 0, 20)
    lk_predict: bool = param(
        True,
        'start each track where the IMU rotation between the two images moves it, and use only '
        'the pyramid levels that the motion left asks for')
    lk_capture_px: float = param(
        3.0, 'px: the motion a base-level Lucas-Kanade search converges from (each pyramid level '
        "doubles it); the levels used reach twice the previous image's 95th-percentile motion "
        'left after the prediction, > 0', 0.0)
    lk_retrack_lost_fraction: float = param(
        0.2,
        'a search with fewer pyramid levels that loses more than this fraction of the tracks is '
        'done again with all lk_pyramid_levels', 0.0, 1.0)
    lk_max_error: float = param(
        25.0, 'grey levels (of 255), largest LK mean absolute patch error', 0.0)
    border_px: float = param(8.0, 'px, tracks closer to the image border are dropped', 0.0)
    inlier_threshold_px: float = param(0.5, 'px over one frame, residual of an inlier track', 0.0)
    fit_axis_rotation: bool = param(
        True,
        'fit a rotation about the optical axis with phi: the attitude error between the two '
        'images about the camera axis (gyro noise), which no translation explains (module doc)')
    huber_iterations: int = param(4, 'IRLS (Huber) iterations before the inlier gate', 0, 1000)
    two_plane_iterations: int = param(
        2,
        'refits of the second plane distance ratio s and phi when a second plane may be in view '
        '(front camera: the floor)', 0, 100)
    min_inliers: int = param(20, 'inliers: fewer, no flow published (NaN)', 0)
    min_inlier_ratio: float = param(
        0.3, 'inliers / tracks below this: no flow published (NaN)', 0.0, 1.0)
    min_cos_plane: float = param(
        0.05, 'eta^T p below this: the point is not on the plane (dropped)', -1.0, 1.0)
    exclusion_margin_rad: float = param(0.02, 'rad, widening of the excluded window aperture', 0.0)
    min_frame_gap_s: float = param(
        1e-4, 's (image stamps, ROS clock), smallest accepted gap between consecutive images', 0.0)
    max_frame_gap_frames: float = param(
        5.0, 'computed frames (the camera period times the frame stride): largest accepted gap '
        'between consecutive images (frames lost on the way)', 0.0)
    slow_motion_px: float = param(
        2.0,
        'px per frame: when the derotated image motion is slower, phi is estimated over several '
        'frames (a longer baseline), up to max_baseline_frames', 0.0)
    max_baseline_frames: int = param(
        5, 'frames: the longest baseline of a slow-motion estimate (1: always frame to frame)', 1,
        50)

    def __post_init__(self) -> None:
        """Raise ValueError naming the parameter for what a range cannot check."""
        if not self.quality_level > 0.0:        # cv2.goodFeaturesToTrack asserts it
            raise ValueError(f'parameter quality_level must be > 0, got {self.quality_level}')
        if not (math.isfinite(self.lk_capture_px) and self.lk_capture_px > 0.0):
            raise ValueError(f'parameter lk_capture_px must be finite and > 0, '
                             f'got {self.lk_capture_px}')
        if not self.max_frame_gap_frames >= 1.0:
            raise ValueError('parameter max_frame_gap_frames must be >= 1, got '
                             f'{self.max_frame_gap_frames}')


@dataclass(frozen=True)
class FlowResult:
    """One flow estimate between two images."""

    phi_I: np.ndarray | None    # (3,) v/d in {I}, 1/s; None when not enough inliers
    inlier_ratio: float         # inliers / usable tracks, [0, 1]
    n_inliers: int
    n_tracks: int
    axis_rate: float = 0.0      # rad/s, the fitted rotation about the optical axis (module doc)


def wall_normal_from_corners(corner_bearings_C: np.ndarray, R_IB: np.ndarray,
                             R_BC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (eta_w, corner bearings in {I}) from the window corners (4, 3), optical frame.

    eta_w of eq:etaw with the paper's sign eta_w^T q_w < 0: from the camera towards the wall.
    """
    p_I = bearings_C_to_I(corner_bearings_C, R_IB, R_BC)
    u_w, rho_w = window_axes(edge_normals(p_I), p_I)
    return window_normal(u_w, rho_w, centroid_feature(p_I)), p_I


def inside_spherical_polygon(p: np.ndarray, corners: np.ndarray, margin_rad: float) -> np.ndarray:
    """Tell which unit bearings p (N, 3) fall inside a convex spherical polygon.

    The polygon's corners (K, 3) are in the same frame; it is widened by ``margin_rad``.
    """
    h = np.cross(corners, np.roll(corners, -1, axis=0))
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    centre = corners.mean(axis=0)
    h *= np.sign(h @ centre)[:, None]     # inward normals of the great-circle edges
    return np.all(p @ h.T > -np.sin(margin_rad), axis=1)


def mid_bearings(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Return the unit mid bearings (N, 3) of tracks from p0 to p1 ({I}): the model's points."""
    p_mid = p0 + p1
    return p_mid / np.linalg.norm(p_mid, axis=1, keepdims=True)


def solve_flow_c(p_mid: np.ndarray, p_dot: np.ndarray, c: np.ndarray,
                 weights: np.ndarray) -> np.ndarray | None:
    """Weighted least squares phi of p_dot = -c_i pi_p phi (c_i = d / range_i, see above).

    Returns phi (3,) in 1/s or None for a degenerate set.
    """
    # A_i = -c_i pi_i: A_i^T A_i = c_i^2 pi_i, A_i^T y_i = -c_i pi_i y_i
    pi_y = p_dot - p_mid * np.sum(p_mid * p_dot, axis=1, keepdims=True)
    wc2 = weights * c * c
    M = wc2.sum() * np.eye(3) - (p_mid * wc2[:, None]).T @ p_mid
    b = -((weights * c)[:, None] * pi_y).sum(axis=0)
    if not np.all(np.isfinite(M)) or np.linalg.cond(M) > _MAX_CONDITION:
        return None
    return np.linalg.solve(M, b)


def solve_flow_axis(p_mid: np.ndarray, p_dot: np.ndarray, c: np.ndarray, weights: np.ndarray,
                    axis_I: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Weighted least squares (phi, omega) of p_dot = -c_i pi_p phi + omega (a x p) (module doc).

    ``axis_I``: the camera's optical axis a, unit, in {I}; omega in rad/s, positive turning the
    bearings anticlockwise about a (right-handed). Returns None for a degenerate set.
    """
    # A_i = [-c_i pi_i, t_i] with t_i = a x p_i (orthogonal to p_i, so pi_i t_i = t_i)
    t = np.cross(axis_I[None, :], p_mid)
    pi_y = p_dot - p_mid * np.sum(p_mid * p_dot, axis=1, keepdims=True)
    wc = weights * c
    M = np.zeros((4, 4))
    M[:3, :3] = (wc * c).sum() * np.eye(3) - (p_mid * (wc * c)[:, None]).T @ p_mid
    M[:3, 3] = M[3, :3] = -(wc[:, None] * t).sum(axis=0)
    M[3, 3] = float(np.sum(weights * np.sum(t * t, axis=1)))
    b = np.concatenate([-(wc[:, None] * pi_y).sum(axis=0),
                        [float(np.sum(weights * np.sum(t * p_dot, axis=1)))]])
    if not np.all(np.isfinite(M)) or np.linalg.cond(M) > _MAX_CONDITION:
        return None
    x = np.linalg.solve(M, b)
    return x[:3], float(x[3])


def axis_rotation_flow(p_mid: np.ndarray, axis_I: np.ndarray, omega: float) -> np.ndarray:
    """Return the bearing rates (N, 3) of a rotation at ``omega`` rad/s about ``axis_I``."""
    return omega * np.cross(axis_I[None, :], p_mid)


def residuals_c(p_mid: np.ndarray, p_dot: np.ndarray, c: np.ndarray, phi: np.ndarray,
                dt: float) -> np.ndarray:
    """|p1 - p0 - dt p_dot_model| per track (rad over one frame) for the model c, phi."""
    pi_phi = phi[None, :] - p_mid * (p_mid @ phi)[:, None]
    return dt * np.linalg.norm(p_dot + c[:, None] * pi_phi, axis=1)


def solve_translational_flow(p0: np.ndarray, p1: np.ndarray, dt: float, eta_I: np.ndarray,
                             weights: np.ndarray) -> np.ndarray | None:
    """Weighted least squares phi of p_dot = -(eta^T p) pi_p phi over tracks (eq:p_t).

    p0, p1: unit bearings (N, 3) in {I} at t0 and t0 + dt; the model is evaluated at the mid
    bearing. Returns phi (3,) in 1/s or None for a degenerate set.
    """
    p_mid = mid_bearings(p0, p1)
    return solve_flow_c(p_mid, (p1 - p0) / dt, p_mid @ eta_I, weights)


def flow_residuals(p0: np.ndarray, p1: np.ndarray, dt: float, eta_I: np.ndarray,
                   phi: np.ndarray) -> np.ndarray:
    """|p1 - p0 - dt p_dot_model| per track (rad over one frame)."""
    p_mid = mid_bearings(p0, p1)
    return residuals_c(p_mid, (p1 - p0) / dt, p_mid @ eta_I, phi, dt)


#: candidate distance ratios s = d / d_2 of the grid search (0: plane 2 not in view)
S_GRID = np.concatenate([[0.0], np.geomspace(0.05, 20.0, 40)])
#: least relative drop of the truncated cost for which a second plane is taken to be in view
TWO_PLANE_MIN_GAIN = 0.1


def second_plane_ratio(p_mid: np.ndarray, p_dot: np.ndarray, c1: np.ndarray, c2: np.ndarray,
                       phi: np.ndarray, dt: float, threshold: float) -> float:
    """Distance ratio s = d / d_2 of the two-plane model for a given phi (module doc).

    Grid search of the truncated squared residuals (``threshold``, rad over one frame) over
    :data:`S_GRID`, then least squares over the points the best s puts on plane 2 and
    explains. Returns s >= 0 (0: no point is better explained on plane 2).
    """
    pi_phi = phi[None, :] - p_mid * (p_mid @ phi)[:, None]
    # residual_i(s) / dt = |p_dot_i + C_i(s) pi_phi_i|, C_i(s) = max(c1_i, s c2_i)
    aa = np.sum(p_dot * p_dot, axis=1)[:, None]
    ab = np.sum(p_dot * pi_phi, axis=1)[:, None]
    bb = np.sum(pi_phi * pi_phi, axis=1)[:, None]
    C = np.maximum(c1[:, None], c2[:, None] * S_GRID[None, :])
    r2 = dt * dt * np.maximum(aa + 2.0 * C * ab + C * C * bb, 0.0)
    s = float(S_GRID[np.argmin(np.minimum(r2, threshold * threshold).sum(axis=0))])
    on2 = (s * c2 > c1) & (np.min(r2, axis=1) <= threshold * threshold)
    # refine: p_dot = -s c2 pi_phi on those points, linear in s
    a = -c2[on2, None] * pi_phi[on2]
    den = float(np.sum(a * a))
    if s > 0.0 and den > 0.0:
        s_ls = float(np.sum(a * p_dot[on2])) / den
        if np.isfinite(s_ls) and s_ls > 0.0:
            s = s_ls
    return s


def joint_grid_start(p_mid: np.ndarray, p_dot: np.ndarray, c1: np.ndarray, c2: np.ndarray,
                     dt: float, threshold: float) -> float:
    """Return the starting s of the two-plane fit, by a grid search over s and phi.

    For each s of :data:`S_GRID`, the least squares phi; the s whose (s, phi) has the least
    truncated squared residuals (``threshold``, rad over one frame) is returned, or 0 when it
    does not lower the cost by :data:`TWO_PLANE_MIN_GAIN`. Unlike a first fit on plane 1
    alone, it does not start from a phi biased by the points of plane 2 when these are many
    (the floor below the wall from a low height).
    """
    C = np.maximum(c1[:, None], c2[:, None] * S_GRID[None, :])            # (N, G)
    pi_y = p_dot - p_mid * np.sum(p_mid * p_dot, axis=1, keepdims=True)   # (N, 3)
    C2 = C * C
    # M_g = sum_i C_ig^2 (I - p_i p_i^T), b_g = -sum_i C_ig pi_i y_i
    ppT = (p_mid[:, :, None] * p_mid[:, None, :]).reshape(-1, 9)
    M = C2.sum(axis=0)[:, None, None] * np.eye(3) - (C2.T @ ppT).reshape(-1, 3, 3)
    b = -C.T @ pi_y                                                        # (G, 3)
    # well conditioned: det >= eps (trace / 3)^3 (a degenerate spread of points is refused)
    ok = np.linalg.det(M) > 1.0 / _MAX_CONDITION * (np.trace(M, axis1=1, axis2=2) / 3.0) ** 3
    if not np.any(ok):
        return 0.0
    phi = np.zeros((len(S_GRID), 3))
    phi[ok] = np.linalg.solve(M[ok], b[ok][..., None])[..., 0]
    # residual_ig / dt = |y_i + C_ig pi_i phi_g| with pi_i phi_g = phi_g - p_i (p_i . phi_g)
    p_phi = p_mid @ phi.T                                                  # (N, G)
    y_phi = p_dot @ phi.T                                                  # (N, G)
    yy = np.sum(p_dot * p_dot, axis=1)[:, None]
    yp = np.sum(p_dot * p_mid, axis=1)[:, None]
    phiphi = np.sum(phi * phi, axis=1)[None, :]
    # |y + C (phi - p (p.phi))|^2 = |y|^2 + 2C (y.phi - (y.p)(p.phi)) + C^2 (|phi|^2 - (p.phi)^2)
    r2 = dt * dt * np.maximum(yy + 2.0 * C * (y_phi - yp * p_phi)
                              + C2 * (phiphi - p_phi * p_phi), 0.0)
    cost = np.where(ok, np.minimum(r2, threshold * threshold).sum(axis=0), np.inf)
    best = int(np.argmin(cost))
    # a second plane must explain the data clearly better than none (S_GRID[0] = 0): a small
    # gain is noise fitted on plane 1's own points
    if np.isfinite(cost[0]) and cost[best] > (1.0 - TWO_PLANE_MIN_GAIN) * cost[0]:
        return 0.0
    return float(S_GRID[best])


def pyramid_levels_for(motion_px: float | None, capture_px: float, max_levels: int) -> int:
    """Fewest pyramid levels L <= max_levels with capture_px 2^L >= LK_MOTION_MARGIN motion_px.

    ``motion_px``: the previous image's motion left after the prediction (px, 95th
    percentile); None (unknown): ``max_levels``.
    """
    if motion_px is None or not math.isfinite(motion_px):
        return max_levels
    levels = 0
    while levels < max_levels and capture_px * 2 ** levels < LK_MOTION_MARGIN * motion_px:
        levels += 1
    return levels


def _p95_distance(a: np.ndarray, b: np.ndarray) -> float | None:
    """95th percentile of the distances between the rows of a and b (px), None for none."""
    return float(np.percentile(np.hypot(*(a - b).T), 95)) if len(a) else None


class FlowEstimator:
    """Feature tracker and translational-flow estimator of one camera (stateful)."""

    def __init__(self, config: FlowConfig, camera: CameraModel, R_BC: np.ndarray) -> None:
        self.config = config
        self.camera = camera
        self.R_BC = np.asarray(R_BC, dtype=float)
        self._win = (config.lk_window_px, config.lk_window_px)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.001)
        self.reset()

    def reset(self) -> None:
        """Drop the tracks and the previous image."""
        self._previous: np.ndarray | None = None
        self._points = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)          # one id per track, kept while tracked
        self._next_id = 0
        self._stamp: float | None = None
        # past frames with an attitude, newest last: (stamp, track ids, bearings in {I})
        self._history: deque = deque(maxlen=self.config.max_baseline_frames)
        self._frame_count = 0
        # the previous image's motion (px, 95th percentile) left after the prediction by
        # motion, and after the one by rotation alone: the pyramid levels of the next track
        self._motion_px: float | None = None
        self._rotation_motion_px: float | None = None
        self.last_baseline_frames = 0              # baseline of the last estimate (frames)
        self.last_pyramid_levels: int | None = None  # LK levels of the last track (None: none)
        self.retracks = 0                          # searches redone with every pyramid level
        # s between two computed frames: the camera period times the frame stride (the node
        # sets it from vehicle.yaml's rate and ibvs/frame_grid)
        self.frame_period_s = DEFAULT_FRAME_PERIOD_S

    @property
    def n_points(self) -> int:
        """Number of features currently tracked."""
        return len(self._points)

    def process(self, gray: np.ndarray, stamp_s: float, R_IB: np.ndarray | None,
                eta_I: np.ndarray | None, exclude_I: np.ndarray | None = None,
                eta2_I: np.ndarray | None = None) -> FlowResult | None:
        """Track into ``gray`` and estimate phi between the previous image and this one.

        R_IB: attitude at ``stamp_s`` (None: unknown, no estimate). eta_I: unit plane normal in
        {I} from the camera towards the plane (None: no estimate, tracking continues).
        exclude_I: corner bearings (K, 3) in {I} of a region whose points are not on the plane
        (the window aperture). eta2_I: unit normal of a second plane that may be in view (the
        floor for the front camera), at an unknown distance (module doc); phi stays the first
        plane's. Returns None when no estimate was attempted.
        """
        cfg = self.config
        result = None
        dt = None if self._stamp is None else stamp_s - self._stamp
        max_gap_s = cfg.max_frame_gap_frames * self.frame_period_s
        if dt is None or not cfg.min_frame_gap_s <= dt <= max_gap_s \
                or self._previous is None or gray.shape != self._previous.shape:
            self._points, self._ids = np.zeros((0, 2), np.float32), np.zeros(0, np.int64)
            self._history.clear()
            self._motion_px = self._rotation_motion_px = None
            self._frame_count = 0       # the replenishment cadence starts with the new tracks
        elif len(self._points):
            self._points, self._ids = self._track(gray, self._predicted(stamp_s, R_IB))
        p_I = None
        if R_IB is None:
            self._history.clear()                  # long baselines need every attitude
        else:
            p_I = self._bearings_I(self._points, R_IB)
            if eta_I is not None and self._history and len(self._points):
                axis_I = R_IB @ self.R_BC[:, 2] if cfg.fit_axis_rotation else None
                result = self._estimate_over_baseline(
                    stamp_s, p_I, np.asarray(eta_I, dtype=float), exclude_I,
                    None if eta2_I is None else np.asarray(eta2_I, dtype=float), axis_I)
        self._frame_count += 1
        if len(self._points) < cfg.min_tracks \
                or self._frame_count % cfg.replenish_every_n_frames == 0:
            n_old = len(self._points)
            self._replenish(gray)
            if p_I is not None and len(self._points) > n_old:
                p_I = np.vstack([p_I, self._bearings_I(self._points[n_old:], R_IB)])
        if p_I is not None:
            self._history.append((stamp_s, self._ids.copy(), p_I))
        self._previous, self._stamp = gray, stamp_s
        return result

    def _bearings_I(self, points_px: np.ndarray, R_IB: np.ndarray) -> np.ndarray:
        """Return the unit bearings (N, 3) in {I} of distorted pixels at the attitude R_IB."""
        if not len(points_px):
            return np.zeros((0, 3))
        return bearings_C_to_I(self.camera.pixels_to_bearings(points_px), R_IB, self.R_BC)

    def _estimate_over_baseline(self, stamp_s: float, p1_all: np.ndarray, eta_I: np.ndarray,
                                exclude_I: np.ndarray | None, eta2_I: np.ndarray | None,
                                axis_I: np.ndarray | None) -> FlowResult:
        """Estimate from the previous frame, or from further back when the motion is slow.

        ``axis_I``: the optical axis in {I} now, to fit a rotation about it (None: not fitted).
        """
        cfg = self.config
        baselines = []
        for back in range(1, len(self._history) + 1):       # previous frame first
            stamp0, ids0, p0_all = self._history[-back]
            common, i0, i1 = np.intersect1d(ids0, self._ids, assume_unique=True,
                                            return_indices=True)
            if len(common) < cfg.min_inliers:
                break
            baselines.append((stamp_s - stamp0, p0_all[i0], p1_all[i1]))
            if back == 1:
                motion_px = float(np.median(np.arccos(np.clip(
                    np.sum(p0_all[i0] * p1_all[i1], axis=1), -1.0, 1.0)))) \
                    * float(self.camera.K[0, 0])
                if motion_px >= cfg.slow_motion_px:
                    break
            elif back * motion_px >= cfg.slow_motion_px:
                break
        if not baselines:
            return FlowResult(None, 0.0, 0, 0)
        dt, p0, p1 = baselines[-1]
        self.last_baseline_frames = len(baselines)
        return self._estimate(p0, p1, dt, eta_I, exclude_I, eta2_I, axis_I)

    def _predicted(self, stamp_s: float, R_IB: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Where each track should be in this image: (by rotation, by motion, moving?), or None.

        A static direction keeps its bearing p in {I}: the previous image's p of each track
        (kept in the history) is seen at b = (R_IB R_BC)^T p now (by rotation, px). A track
        also seen in the image before moves on in {I} at its last rate, p + (p - p_before)
        dt / dt_before (the translational flow, constant over a frame): by motion (px), and
        ``moving`` says which tracks had that second image (the others: by rotation). None
        without the prediction, an attitude at either image, or the previous image's history.
        Tracks a prediction would take out of view keep their previous pixel.
        """
        if not self.config.lk_predict or R_IB is None or not self._history:
            return None
        stamp0, ids0, p0 = self._history[-1]
        if stamp0 != self._stamp or len(ids0) != len(self._ids):
            return None
        by_rotation = self._project(bearings_I_to_C(p0, R_IB, self.R_BC))
        moving = np.zeros(len(p0), dtype=bool)
        p = p0
        if len(self._history) >= 2:
            stamp1, ids1, p1 = self._history[-2]
            _, i0, i1 = np.intersect1d(ids0, ids1, assume_unique=True, return_indices=True)
            if len(i0) and stamp0 > stamp1:
                p = p0.copy()
                p[i0] += (p0[i0] - p1[i1]) * ((stamp_s - stamp0) / (stamp0 - stamp1))
                p[i0] /= np.linalg.norm(p[i0], axis=1, keepdims=True)
                moving[i0] = True
        by_motion = self._project(bearings_I_to_C(p, R_IB, self.R_BC)) if moving.any() \
            else by_rotation
        return by_rotation, by_motion, moving

    def _project(self, b_C: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) float32 of bearings; a track's previous one if out of view."""
        uv, valid = self.camera.bearings_to_pixels(b_C)
        return np.where(valid[:, None], uv, self._points).astype(np.float32)

    def _track(self, gray: np.ndarray, predicted: tuple | None
               ) -> tuple[np.ndarray, np.ndarray]:
        """LK-track the features from the previous image; returns (points, ids) of the good.

        ``predicted``: :meth:`_predicted`. The tracks start by motion when that prediction
        left less motion than the one by rotation in the previous image (an attitude estimate
        that jitters from frame to frame makes each track's last motion a worse guess than
        none), else by rotation; the pyramid levels follow what the chosen prediction left
        there (and what the one by rotation left, for tracks without a motion yet: module
        doc). None: from the previous pixels, with every level.
        """
        cfg = self.config
        if predicted is None:
            start, levels = None, cfg.lk_pyramid_levels
        else:
            by_rotation, by_motion, moving = predicted
            left_m, left_r = self._motion_px, self._rotation_motion_px
            use_motion = moving.any() and left_m is not None and left_r is not None \
                and left_m < left_r
            if use_motion:
                start = by_motion
                left = left_m if moving.all() else max(left_m, left_r)
            else:
                start, left = by_rotation, left_r
            levels = pyramid_levels_for(left, cfg.lk_capture_px, cfg.lk_pyramid_levels)
        cur, ok = self._lk(gray, start, levels)
        if levels < cfg.lk_pyramid_levels \
                and np.count_nonzero(~ok) > cfg.lk_retrack_lost_fraction * len(ok):
            self.retracks += 1
            levels = cfg.lk_pyramid_levels
            cur, ok = self._lk(gray, start, levels)
        self.last_pyramid_levels = levels
        if predicted is None:
            self._motion_px = self._rotation_motion_px = _p95_distance(cur[ok], self._points[ok])
        else:
            self._motion_px = _p95_distance(cur[ok & moving], by_motion[ok & moving]) \
                if (ok & moving).any() else self._motion_px
            self._rotation_motion_px = _p95_distance(cur[ok], by_rotation[ok])
        return cur[ok].astype(np.float32), self._ids[ok]

    def _lk(self, gray: np.ndarray, predicted: np.ndarray | None, levels: int
            ) -> tuple[np.ndarray, np.ndarray]:
        """One calcOpticalFlowPyrLK of the tracks: (points (N, 2), usable (N,))."""
        cfg = self.config
        start = None if predicted is None else predicted.reshape(-1, 1, 2).copy()
        cur, status, err = cv2.calcOpticalFlowPyrLK(
            self._previous, gray, self._points.reshape(-1, 1, 2), start, winSize=self._win,
            maxLevel=levels, criteria=self._criteria,
            flags=0 if start is None else cv2.OPTFLOW_USE_INITIAL_FLOW)
        cur = cur.reshape(-1, 2)
        h, w = gray.shape[:2]
        b = cfg.border_px
        ok = (status.reshape(-1) == 1) & (err.reshape(-1) < cfg.lk_max_error) \
            & np.all(np.isfinite(cur), axis=1) \
            & (cur[:, 0] >= b) & (cur[:, 0] <= w - 1 - b) \
            & (cur[:, 1] >= b) & (cur[:, 1] <= h - 1 - b)
        return cur, ok

    def _estimate(self, p0: np.ndarray, p1: np.ndarray, dt: float, eta_I: np.ndarray,
                  exclude_I: np.ndarray | None, eta2_I: np.ndarray | None,
                  axis_I: np.ndarray | None = None) -> FlowResult:
        """Phi from the tracks' bearings p0 -> p1 in {I}, dt apart (module doc).

        ``axis_I``: the optical axis in {I}; a rotation about it is fitted with phi (None: not).
        """
        cfg = self.config
        on_plane = (p0 @ eta_I > cfg.min_cos_plane) & (p1 @ eta_I > cfg.min_cos_plane)
        if eta2_I is not None:       # a point may lie on either plane
            on_plane |= (p0 @ eta2_I > cfg.min_cos_plane) & (p1 @ eta2_I > cfg.min_cos_plane)
        if exclude_I is not None:
            on_plane &= ~inside_spherical_polygon(p1, exclude_I, cfg.exclusion_margin_rad)
        p0, p1 = p0[on_plane], p1[on_plane]
        n = len(p0)
        if n < cfg.min_inliers:
            return FlowResult(None, 0.0, 0, n)
        p_mid, p_dot = mid_bearings(p0, p1), (p1 - p0) / dt
        c1 = np.maximum(p_mid @ eta_I, 0.0)
        c2 = None if eta2_I is None else np.maximum(p_mid @ eta2_I, 0.0)
        threshold = cfg.inlier_threshold_px / float(self.camera.K[0, 0])   # rad
        s = 0.0 if c2 is None else joint_grid_start(p_mid, p_dot, c1, c2, dt, threshold)
        c = c1 if c2 is None else np.maximum(c1, s * c2)
        for _ in range(1 + (cfg.two_plane_iterations if c2 is not None else 0)):
            phi, omega, weights = self._irls(p_mid, p_dot, c, dt, threshold, axis_I)
            if phi is None:
                return FlowResult(None, 0.0, 0, n)
            if c2 is None or s == 0.0:      # plane 2 not in view: the one-plane fit
                break
            s = second_plane_ratio(p_mid, self._derotated(p_mid, p_dot, axis_I, omega), c1, c2,
                                   phi, dt, threshold)
            c = np.maximum(c1, s * c2)
        inliers = residuals_c(p_mid, self._derotated(p_mid, p_dot, axis_I, omega), c, phi,
                              dt) <= threshold
        n_in = int(inliers.sum())
        ratio = n_in / n
        if n_in < cfg.min_inliers or ratio < cfg.min_inlier_ratio:
            return FlowResult(None, ratio, n_in, n, omega)
        # the final phi from plane 1's own inliers: it does not inherit an error of s
        on_1 = inliers if c2 is None else inliers & (c1 >= s * c2)
        if int(on_1.sum()) < cfg.min_inliers:
            return FlowResult(None, ratio, n_in, n, omega)
        phi, omega = self._solve(p_mid[on_1], p_dot[on_1], c1[on_1], np.ones(int(on_1.sum())),
                                 axis_I)
        if phi is None or not np.all(np.isfinite(phi)):
            return FlowResult(None, ratio, n_in, n, omega)
        return FlowResult(phi, ratio, n_in, n, omega)

    @staticmethod
    def _solve(p_mid: np.ndarray, p_dot: np.ndarray, c: np.ndarray, weights: np.ndarray,
               axis_I: np.ndarray | None) -> tuple[np.ndarray | None, float]:
        """(phi, omega) of the model c, with a rotation about ``axis_I`` when given (else 0)."""
        if axis_I is None:
            return solve_flow_c(p_mid, p_dot, c, weights), 0.0
        solved = solve_flow_axis(p_mid, p_dot, c, weights, axis_I)
        return (None, 0.0) if solved is None else solved

    @staticmethod
    def _derotated(p_mid: np.ndarray, p_dot: np.ndarray, axis_I: np.ndarray | None,
                   omega: float) -> np.ndarray:
        """Return the bearing rates without the fitted rotation about the optical axis."""
        return p_dot if axis_I is None else p_dot - axis_rotation_flow(p_mid, axis_I, omega)

    def _irls(self, p_mid: np.ndarray, p_dot: np.ndarray, c: np.ndarray, dt: float,
              threshold: float, axis_I: np.ndarray | None = None
              ) -> tuple[np.ndarray | None, float, np.ndarray]:
        """Huber-reweighted least squares: (phi or None, omega, last weights) for the model c."""
        weights = np.ones(len(p_mid))
        phi, omega = None, 0.0
        for _ in range(self.config.huber_iterations):
            phi, omega = self._solve(p_mid, p_dot, c, weights, axis_I)
            if phi is None:
                return None, 0.0, weights
            r = residuals_c(p_mid, self._derotated(p_mid, p_dot, axis_I, omega), c, phi, dt)
            weights = np.minimum(1.0, threshold / np.maximum(r, 1e-15))
        return phi, omega, weights

    def _replenish(self, gray: np.ndarray) -> None:
        """Add features (goodFeaturesToTrack) only in grid cells that hold too few tracks."""
        cfg = self.config
        h, w = gray.shape[:2]
        cell_w, cell_h = w / cfg.grid_cols, h / cfg.grid_rows
        pts = self._points
        col = np.clip((pts[:, 0] / cell_w).astype(int), 0, cfg.grid_cols - 1)
        row = np.clip((pts[:, 1] / cell_h).astype(int), 0, cfg.grid_rows - 1)
        counts = np.bincount(row * cfg.grid_cols + col, minlength=cfg.grid_cols * cfg.grid_rows)
        new = []
        for cell in np.flatnonzero(counts < cfg.min_tracks_per_cell):
            r, c = divmod(int(cell), cfg.grid_cols)
            x0, y0 = int(c * cell_w), int(r * cell_h)
            x1, y1 = int((c + 1) * cell_w), int((r + 1) * cell_h)
            corners = cv2.goodFeaturesToTrack(gray[y0:y1, x0:x1], cfg.features_per_cell,
                                              cfg.quality_level, cfg.min_distance_px)
            if corners is not None:
                new.append(corners.reshape(-1, 2) + np.array([x0, y0], np.float32))
        if not new:
            return
        cand = np.concatenate(new).astype(np.float32)
        b = cfg.border_px
        cand = cand[(cand[:, 0] >= b) & (cand[:, 0] <= w - 1 - b)
                    & (cand[:, 1] >= b) & (cand[:, 1] <= h - 1 - b)]
        if len(pts) and len(cand):
            d2 = ((cand[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
            cand = cand[d2.min(axis=1) >= cfg.min_distance_px ** 2]
        self._points = np.concatenate([pts, cand]).astype(np.float32)
        self._ids = np.concatenate([self._ids, self._next_id + np.arange(len(cand))])
        self._next_id += len(cand)
