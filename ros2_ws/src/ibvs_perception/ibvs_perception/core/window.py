"""Window detection in the forward image: the four aperture corners as unit bearings.

Algorithm (paper section Experiments: "ArUco border detection", made sub-pixel):

1. Candidates. Adaptive threshold (dark = foreground) of a down-scaled image, then
   ``findContours`` with a two-level hierarchy, every boundary pixel kept
   (``CHAIN_APPROX_NONE``: with ``CHAIN_APPROX_SIMPLE`` an axis-aligned side, as in a level
   hover, shrinks to its two end points and no line can be fitted to it). The window is a
   dark *ring* (the frame band on the wall face): an outer contour (band/wall border) with
   one large hole (the aperture).
   Both are approximated by convex quadrilaterals (``approxPolyDP``); area, aspect-ratio and
   hole/outer area-ratio checks reject markers, door-like shapes and texture.
2. Sub-pixel refinement. A straight 3-D edge is straight only in *undistorted* coordinates,
   so each aperture side is parametrised in undistorted pixels (the ideal pinhole image
   ``K [x/z, y/z, 1]``), sampled, projected into the distorted image, and searched for the
   dark-to-light step along the local image normal (centroid of the intensity gradient).
   The step must lead into the band: its dark side reaches the band's level (the darkest of
   the profile) within ``_BAND_REACH_PX``. A texture step beside the band (a brick row, a
   mortar joint parallel to the side, as in a level view of a brick wall) is steeper than the
   band's blurred edge but does not, and is not taken for it.
   The edge points are undistorted again, a line is fitted to each side (Huber, then
   residual gating) and adjacent lines are intersected. Two passes.
3. Tracking. The same window is followed frame to frame: a corner displacement above
   ``max_corner_jump_px`` is reported as a loss (``JUMP``), not followed. After
   ``reacquire_after_frames`` frames without a consistent window the tracker searches again.

Outputs are in the camera optical frame (x right, y down, z along the optical axis); corners
are ordered top-left, top-right, bottom-right, bottom-left as seen in the image (clockwise in
the image); edge i joins corner i and i+1 and h_i = unit(p_i x p_(i+1)) (paper, Fig. window).
"""
from __future__ import annotations

from dataclasses import dataclass
import enum

import cv2
import numpy as np

from ibvs_common.core.camera import CameraModel
from ibvs_common.core.features import edge_normals

N_CORNERS = 4
#: binary value of "dark" pixels after the inverted adaptive threshold
_DARK = 255
#: the step of the intensity profiles along the edge normal, px
_PROFILE_STEP_PX = 0.5
#: half-width of the gradient window whose centroid gives the sub-pixel edge, in profile steps
_CENTROID_HALF_WIDTH = 3
#: small pixel offset used to map an undistorted normal into the distorted image, px
_NORMAL_PROBE_PX = 1.0
#: fraction of each side left out at both ends (near the corners the other band interferes)
_SIDE_MARGIN = 0.1
#: points per side checked to lie inside the image (edges are curved there)
_OUTLINE_SAMPLES = 9
#: where the band's dark level is read, inwards of the outer edge, px
_BAND_PROBE_PX = 1.5
#: polarity of a step along the inward normal
_RISING = 1
_FALLING = -1
#: |sin| of the angle between two edges below which their intersection is refused
_MIN_SIN_EDGE_ANGLE = 0.2
#: a band edge's dark side reaches the band's level within this distance of the step, px
#: (a blurred edge spans ~2 px; a texture step beside the band does not lead into it)
_BAND_REACH_PX = 2.0


class WindowStatus(enum.Enum):
    """Outcome of one frame."""

    DETECTED = 'detected'        # the tracked window, fully visible
    NOT_FOUND = 'not_found'      # no (fully visible) window in the image
    JUMP = 'jump'                # a window, but too far from the tracked one: reported as lost


@dataclass(frozen=True)
class WindowDetectorConfig:
    """Tuning of :class:`WindowDetector` (pixels are full-resolution pixels unless noted)."""

    detection_scale: float = 0.5            # image scale of the contour search, (0, 1]
    threshold_block_px: int = 31            # adaptive threshold window at detection scale, odd
    threshold_offset: float = 30.0          # grey levels below the local mean counted as dark
    min_area_fraction: float = 0.01         # outer quad area / image area, lower bound
    max_area_fraction: float = 0.98         # outer quad area / image area, upper bound
    min_aspect_ratio: float = 0.35          # aperture width / height (image), lower bound
    max_aspect_ratio: float = 3.0           # aperture width / height (image), upper bound
    min_hole_area_ratio: float = 0.5        # aperture area / outer area (thin dark band)
    max_hole_area_ratio: float = 0.93
    min_holes_fraction: float = 0.25        # light area inside the ring / outer area (search)
    max_band_fraction: float = 0.25         # band width / shortest outer side, upper bound
    approx_tolerance: float = 0.04          # approxPolyDP tolerance / contour perimeter
    border_margin_px: float = 4.0           # the band must stay this far from the image border
    samples_per_side: int = 40              # edge points searched per aperture side
    search_half_width_px: float = 8.0       # first-pass search range along the edge normal
    refine_half_width_px: float = 3.0       # second-pass search range
    min_edge_contrast: float = 25.0         # grey-level step of a valid edge point
    min_edge_inlier_fraction: float = 0.5   # valid points per side, fraction of samples
    line_inlier_px: float = 1.0             # residual gate of the line fit, undistorted px
    max_corner_jump_px: float = 30.0        # largest corner displacement between frames
    reacquire_after_frames: int = 10        # frames without the tracked window before a search

    def __post_init__(self) -> None:
        """Raise ValueError naming the parameter for what a range cannot check."""
        block = self.threshold_block_px
        if block % 2 != 1 or block < 3:    # cv2.adaptiveThreshold: else cv2.error per image
            raise ValueError(f'parameter threshold_block_px must be odd and >= 3, got {block}')
        for low, high in (('min_area_fraction', 'max_area_fraction'),
                          ('min_aspect_ratio', 'max_aspect_ratio'),
                          ('min_hole_area_ratio', 'max_hole_area_ratio')):
            if not getattr(self, low) <= getattr(self, high):
                raise ValueError(f'parameter {low} ({getattr(self, low)}) must be <= {high} '
                                 f'({getattr(self, high)})')


#: spec of each WindowDetectorConfig field as a ROS parameter (description with unit, inclusive
#: range; ibvs_common.param_descriptors); pixels are full-resolution pixels unless noted
PARAMETER_SPECS = {
    'detection_scale': ('image scale of the contour search, (0, 1]', 0.01, 1.0),
    'threshold_block_px': ('px at detection scale, odd, >= 3: adaptive threshold window',
                           3, 1001),
    'threshold_offset': ('grey levels (of 255) below the local mean counted as dark',
                         0.0, 255.0),
    'min_area_fraction': ('outer band quad area / image area, lower bound', 0.0, 1.0),
    'max_area_fraction': ('outer band quad area / image area, upper bound', 0.0, 1.0),
    'min_aspect_ratio': ('width / height of the quad in the image, lower bound', 0.0, None),
    'max_aspect_ratio': ('width / height of the quad in the image, upper bound', 0.0, None),
    'min_hole_area_ratio': ('aperture area / outer band area, lower bound', 0.0, 1.0),
    'max_hole_area_ratio': ('aperture area / outer band area, upper bound', 0.0, 1.0),
    'min_holes_fraction': ('light area inside a dark ring / its area (search), lower bound',
                           0.0, 1.0),
    'max_band_fraction': ('band width / shortest outer side, upper bound', 0.0, 1.0),
    'approx_tolerance': ('approxPolyDP tolerance / contour perimeter', 0.0, 1.0),
    'border_margin_px': ('px: the whole band must be this far inside the image', 0.0, None),
    'samples_per_side': ('edge points searched per aperture side, >= 2', 2, 10000),
    'search_half_width_px': ('px: first-pass search range along the edge normal', 0.0, None),
    'refine_half_width_px': ('px: second-pass search range along the edge normal', 0.0, None),
    'min_edge_contrast': ('grey levels (of 255): step of a valid edge point', 0.0, 255.0),
    'min_edge_inlier_fraction': ('valid edge points per side / samples_per_side', 0.0, 1.0),
    'line_inlier_px': ('px (undistorted): residual gate of the line fit', 0.0, None),
    'max_corner_jump_px': ('px: a larger corner motion between frames is a loss', 0.0, None),
    'reacquire_after_frames': ('frames without the tracked window before a new search',
                               0, None),
}


@dataclass(frozen=True)
class WindowDetection:
    """One detected window in the optical frame of the camera."""

    corners_px: np.ndarray      # (4, 2) distorted pixels, TL, TR, BR, BL
    bearings_C: np.ndarray      # (4, 3) undistorted unit bearings, same order
    edge_normals_C: np.ndarray  # (4, 3) h_i = unit(p_i x p_(i+1)), edge i joins i and i+1


@dataclass(frozen=True)
class WindowResult:
    """What one frame gives: a status and, when DETECTED, the detection."""

    status: WindowStatus
    detection: WindowDetection | None = None


def order_corners_clockwise(quad_px: np.ndarray) -> np.ndarray:
    """Order 4 image points TL, TR, BR, BL (clockwise in the image, y down).

    The start is the corner whose direction from the centroid is closest to the image's
    up-left diagonal, which holds for camera rolls below 45 degrees.
    """
    quad = np.asarray(quad_px, dtype=float).reshape(N_CORNERS, 2)
    d = quad - quad.mean(axis=0)
    angle = np.arctan2(d[:, 1], d[:, 0])          # clockwise on screen with y down
    quad = quad[np.argsort(angle)]
    d = quad - quad.mean(axis=0)
    start = int(np.argmax(-(d[:, 0] + d[:, 1])))  # farthest along (-1, -1)
    return np.roll(quad, -start, axis=0)


class WindowDetector:
    """Detect and track the window aperture (stateful: one instance per camera stream)."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config
        self._last_px: np.ndarray | None = None
        self._last_bearings: np.ndarray | None = None
        self._last_outer_u: np.ndarray | None = None
        self._rotation_since = np.eye(3)      # camera rotation not yet applied to the track
        self._frames_since_seen = 0

    def reset(self) -> None:
        """Forget the tracked window."""
        self._last_px = None
        self._last_bearings = None
        self._last_outer_u = None
        self._rotation_since = np.eye(3)
        self._frames_since_seen = 0

    # --- public ---------------------------------------------------------------------------

    def process(self, gray: np.ndarray, camera: CameraModel,
                rotation_C: np.ndarray | None = None) -> WindowResult:
        """Detect the window in a grey image (uint8, camera.height x camera.width).

        ``rotation_C``: the camera's rotation since the previous image, as the matrix M that
        maps a fixed direction's bearing in the previous optical frame to the current one,
        ``b_now = M b_prev`` (from the IMU: ``M = R_IC(now)^T R_IC(prev)``,
        ``R_IC = R_IB R_BC``). The tracked window (the outline the fast path starts from and
        the corners the jump gate compares with) is moved by it first: exact for a pure
        rotation, so the search and the ``max_corner_jump_px`` gate are left with the motion
        that translation causes. None: no prediction (the window is assumed still).
        """
        if rotation_C is not None and self._last_bearings is not None:
            self._predict(camera, np.asarray(rotation_C, dtype=float))
        if self._last_outer_u is not None:
            # fast path: refine the tracked window from its last outline, no contour search
            refined = self._refine(gray, camera, self._last_outer_u)
            if refined is not None:
                return self._track([refined])
        refined = [r for r in (self._refine(gray, camera, quad)
                               for quad in self.find_candidates(gray, camera))
                   if r is not None]
        return self._track(refined)

    def find_candidates(self, gray: np.ndarray, camera: CameraModel) -> list[np.ndarray]:
        """Outer quads (4, 2) of dark rings in undistorted pixels, TL, TR, BR, BL.

        A candidate is the outer boundary of a dark connected component that is a convex
        quadrilateral of plausible size and aspect ratio, and
        whose holes (the aperture, possibly cut by dark texture seen through it) cover at
        least ``min_holes_fraction`` of it: a filled dark square is not a ring.
        """
        cfg = self.config
        scale = cfg.detection_scale
        small = gray if scale >= 1.0 else cv2.resize(gray, None, fx=scale, fy=scale,
                                                     interpolation=cv2.INTER_AREA)
        binary = cv2.adaptiveThreshold(small, _DARK, cv2.ADAPTIVE_THRESH_MEAN_C,
                                       cv2.THRESH_BINARY_INV, cfg.threshold_block_px,
                                       cfg.threshold_offset)
        contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        if hierarchy is None:
            return []
        hierarchy = hierarchy[0]
        image_area = float(small.shape[0] * small.shape[1])
        quads = []
        for i, (_, _, child, parent) in enumerate(hierarchy):
            if parent != -1 or child == -1:
                continue
            outer = contours[i]
            outer_area = cv2.contourArea(outer)
            if not cfg.min_area_fraction * image_area <= outer_area \
                    <= cfg.max_area_fraction * image_area:
                continue
            if _children_area(contours, hierarchy, child) < cfg.min_holes_fraction * outer_area:
                continue
            quad = self._outer_quad_u(outer, camera, scale)
            if quad is None:
                continue
            width = 0.5 * (np.linalg.norm(quad[1] - quad[0]) + np.linalg.norm(quad[2] - quad[3]))
            height = 0.5 * (np.linalg.norm(quad[3] - quad[0]) + np.linalg.norm(quad[2] - quad[1]))
            if height <= 0 or not cfg.min_aspect_ratio <= width / height <= cfg.max_aspect_ratio:
                continue
            quads.append(quad)
        return quads

    # --- helpers --------------------------------------------------------------------------

    def _track(self, refined: list[tuple[WindowDetection, np.ndarray]]) -> WindowResult:
        """Follow the same window; a jump above max_corner_jump_px is a loss, not followed.

        ``refined``: (detection, outer band quad in undistorted px) of each candidate.
        """
        cfg = self.config
        if self._last_px is not None and self._frames_since_seen >= cfg.reacquire_after_frames:
            self.reset()
        if not refined:
            self._frames_since_seen += 1
            self._last_outer_u = None       # search the whole image next time
            return WindowResult(WindowStatus.NOT_FOUND)
        if self._last_px is None:
            best, outer_u = max(refined, key=lambda r: _quad_area(r[1]))
        else:
            jumps = [float(np.max(np.linalg.norm(d.corners_px - self._last_px, axis=1)))
                     for d, _ in refined]
            best, outer_u = refined[int(np.argmin(jumps))]
            if min(jumps) > cfg.max_corner_jump_px:
                self._frames_since_seen += 1
                self._last_outer_u = None
                return WindowResult(WindowStatus.JUMP)
        self._last_px, self._last_outer_u = best.corners_px, outer_u
        self._last_bearings = best.bearings_C
        self._rotation_since = np.eye(3)
        self._frames_since_seen = 0
        return WindowResult(WindowStatus.DETECTED, best)

    def _predict(self, camera: CameraModel, M: np.ndarray) -> None:
        """Move the tracked corners and outline by the camera rotation M (see process).

        Only when the rotation moves a corner by more than half the first-pass search range
        (``search_half_width_px``): below that the search finds the edges from the unmoved
        outline, and the result, whose sub-pixel noise depends on where the search starts,
        stays what it was without the IMU (a replayed bag then reproduces it whatever the
        order in which an IMU sample and the image of the same stamp arrived).
        """
        M = M @ self._rotation_since             # with the rotations not applied yet
        b = self._last_bearings @ M.T
        uv, valid = camera.bearings_to_pixels(b)
        if not np.all(valid):                    # rotated out of view: search the image
            self.reset()
            return
        if np.max(np.linalg.norm(uv - self._last_px, axis=1)) \
                <= 0.5 * self.config.search_half_width_px:
            self._rotation_since = M             # kept for when it adds up
            return
        self._rotation_since = np.eye(3)
        self._last_bearings, self._last_px = b, uv
        if self._last_outer_u is not None:
            K = camera.K
            rays = np.column_stack([(self._last_outer_u - K[:2, 2]) / np.diag(K)[:2],
                                    np.ones(N_CORNERS)]) @ M.T
            if np.all(rays[:, 2] > 0.0):
                self._last_outer_u = rays[:, :2] / rays[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
            else:
                self._last_outer_u = None

    def _outer_quad_u(self, contour: np.ndarray, camera: CameraModel,
                      scale: float) -> np.ndarray | None:
        """Return the initial outer quad in undistorted px from robust lines along 4 sides.

        approxPolyDP splits the contour into 4 convex sides; each side's points (ends left
        out) are undistorted and fitted with a Huber line, so that texture blobs touching the
        band do not drag the corners. Returns the 4 intersections, TL, TR, BR, BL, or None.
        """
        perimeter = cv2.arcLength(contour, True)
        approx = cv2.approxPolyDP(contour, self.config.approx_tolerance * perimeter, True)
        if len(approx) != N_CORNERS or not cv2.isContourConvex(approx):
            return None
        points = contour.reshape(-1, 2)
        vertex_idx = sorted(int(np.flatnonzero(np.all(points == v, axis=1))[0])
                            for v in approx.reshape(N_CORNERS, 2))
        points_u = _undistorted_px(camera, (points + 0.5) / scale - 0.5)
        lines = []
        for k in range(N_CORNERS):
            a, b = vertex_idx[k], vertex_idx[(k + 1) % N_CORNERS]
            seg = np.arange(a, b if b > a else b + len(points)) % len(points)
            cut = int(_SIDE_MARGIN * len(seg))
            seg = seg[cut:len(seg) - cut]
            if len(seg) < 2:
                return None
            vx, vy, x0, y0 = cv2.fitLine(points_u[seg].astype(np.float32), cv2.DIST_HUBER,
                                         0, 0.01, 0.01).reshape(-1)
            lines.append(np.array([-vy, vx, vy * x0 - vx * y0], dtype=float))
        corners = _intersect_consecutive(lines)
        if corners is None or not cv2.isContourConvex(corners.astype(np.float32)):
            return None
        return order_corners_clockwise(corners)

    def _refine(self, gray: np.ndarray, camera: CameraModel,
                outer_u: np.ndarray) -> tuple[WindowDetection, np.ndarray] | None:
        """Sub-pixel aperture corners of a candidate ring and its refined outer quad, or None.

        Outer edges (light wall -> dark band, inwards) are fitted first; the aperture edges
        are the first dark -> light step inwards of them, then fitted again in a narrow band.
        All fits are straight lines in undistorted pixels.
        """
        cfg = self.config
        for half_width in (cfg.search_half_width_px, cfg.refine_half_width_px):
            outer_u = self._fit_quad(gray, camera, outer_u, half_width, _FALLING)
            if outer_u is None:
                return None
        if not self._inside_image(camera, outer_u):
            return None
        inner_u = self._find_inner_quad(gray, camera, outer_u)
        if inner_u is None:
            return None
        inner_u = self._fit_quad(gray, camera, inner_u, cfg.refine_half_width_px, _RISING)
        if inner_u is None or not cv2.isContourConvex(inner_u.astype(np.float32)):
            return None
        ratio = _quad_area(inner_u) / _quad_area(outer_u)
        if not cfg.min_hole_area_ratio <= ratio <= cfg.max_hole_area_ratio:
            return None
        K = camera.K
        normalized = (inner_u - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        bearings = np.column_stack([normalized, np.ones(N_CORNERS)])
        bearings /= np.linalg.norm(bearings, axis=1, keepdims=True)
        corners_px = _distort_px(camera, inner_u)
        return WindowDetection(corners_px, bearings, edge_normals(bearings)), outer_u

    def _inside_image(self, camera: CameraModel, quad_u: np.ndarray) -> bool:
        """Whether the whole (curved) outline of a quad lies border_margin_px inside."""
        t = np.linspace(0.0, 1.0, _OUTLINE_SAMPLES)[:, None]
        outline = np.concatenate([a + t * (b - a)
                                  for a, b in zip(quad_u, np.roll(quad_u, -1, axis=0))])
        uv = _distort_px(camera, outline)
        m = self.config.border_margin_px
        return bool(np.all(np.isfinite(uv)) and np.all(uv >= m)
                    and np.all(uv <= np.array([camera.width, camera.height]) - 1 - m))

    def _quad_samples(self, corners_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return sample points (4 n, 2) along the 4 sides and their inward unit normals.

        Sides follow each other (n samples each); undistorted px.
        """
        n = self.config.samples_per_side
        t = np.linspace(_SIDE_MARGIN, 1.0 - _SIDE_MARGIN, n)[:, None]
        centre = corners_u.mean(axis=0)
        samples, normals = [], []
        for side in range(N_CORNERS):
            a, b = corners_u[side], corners_u[(side + 1) % N_CORNERS]
            direction = (b - a) / np.linalg.norm(b - a)
            inward = np.array([-direction[1], direction[0]])
            if np.dot(inward, centre - a) < 0.0:
                inward = -inward
            samples.append(a + t * (b - a))
            normals.append(np.repeat(inward[None, :], n, axis=0))
        return np.concatenate(samples), np.concatenate(normals)

    def _fit_sides(self, camera: CameraModel, base: np.ndarray, normal_d: np.ndarray,
                   pos: np.ndarray, ok: np.ndarray, inward: np.ndarray) -> np.ndarray | None:
        """Fit the 4 sides' lines to their edge points and intersect them (undistorted px)."""
        cfg = self.config
        n = cfg.samples_per_side
        if np.any(ok.reshape(N_CORNERS, n).sum(axis=1) < cfg.min_edge_inlier_fraction * n):
            return None
        edge_u = np.full((len(ok), 2), np.nan)
        edge_u[ok] = _undistorted_px(camera, base[ok] + pos[ok, None] * normal_d[ok])
        lines = []
        for side in range(N_CORNERS):
            sel = slice(side * n, (side + 1) * n)
            line = self._fit_side(edge_u[sel][ok[sel]], inward[side * n])
            if line is None:
                return None
            lines.append(line)
        return _intersect_consecutive(lines)

    def _fit_quad(self, gray: np.ndarray, camera: CameraModel, corners_u: np.ndarray,
                  half_width: float, polarity: int) -> np.ndarray | None:
        """Refit the 4 sides of a quad (undistorted px) to the strongest step of ``polarity``.

        polarity +1: intensity rises inwards (band -> aperture); -1: falls (wall -> band).
        """
        offsets = np.arange(-half_width, half_width + 1e-9, _PROFILE_STEP_PX)
        samples_u, inward = self._quad_samples(corners_u)
        profile, base, normal_d = _profiles(gray, camera, samples_u, inward, offsets)
        grad = polarity * np.diff(profile, axis=1)
        into_band = _steps_into_band(profile, polarity, 0.5 * self.config.min_edge_contrast)
        peak = np.argmax(np.where(into_band, grad, -np.inf), axis=1)
        pos, ok = self._step_positions(grad, offsets, peak)
        ok &= into_band.any(axis=1)
        return self._fit_sides(camera, base, normal_d, pos, ok, inward)

    def _find_inner_quad(self, gray: np.ndarray, camera: CameraModel,
                         outer_u: np.ndarray) -> np.ndarray | None:
        """Aperture quad: per side, the first dark -> light step inwards of the outer edge."""
        cfg = self.config
        sides = np.linalg.norm(outer_u - np.roll(outer_u, -1, axis=0), axis=1)
        depth = cfg.max_band_fraction * float(sides.min())
        offsets = np.arange(0.0, depth + 1e-9, _PROFILE_STEP_PX)
        first = int(round(_BAND_PROBE_PX / _PROFILE_STEP_PX))
        if len(offsets) < first + 2 * _CENTROID_HALF_WIDTH:
            return None
        samples_u, inward = self._quad_samples(outer_u)
        profile, base, normal_d = _profiles(gray, camera, samples_u, inward, offsets)
        dark = profile[:, first:first + _CENTROID_HALF_WIDTH].mean(axis=1)
        above = profile > (dark + 0.5 * cfg.min_edge_contrast)[:, None]
        above[:, :first] = False
        crossing = np.argmax(above, axis=1) - 1
        grad = np.diff(profile, axis=1)
        pos, ok = self._step_positions(grad, offsets, crossing)
        ok &= above.any(axis=1)
        return self._fit_sides(camera, base, normal_d, pos, ok, inward)

    def _step_positions(self, grad: np.ndarray, offsets: np.ndarray,
                        peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel step offsets: centroid of the positive gradient around ``peak``.

        Gradient sample j sits between profile samples j and j+1. Returns (offset, valid).
        """
        window = np.arange(-_CENTROID_HALF_WIDTH, _CENTROID_HALF_WIDTH + 1)
        idx = np.clip(peak[:, None] + window[None, :], 0, grad.shape[1] - 1)
        g = np.clip(np.take_along_axis(grad, idx, axis=1), 0.0, None)
        step = g.sum(axis=1)
        pos = (g * (offsets[idx] + 0.5 * _PROFILE_STEP_PX)).sum(axis=1) / np.maximum(step, 1e-9)
        ok = (step >= self.config.min_edge_contrast) & (peak > 0) \
            & (peak < grad.shape[1] - 1)
        return pos, ok

    def _fit_side(self, edge_u: np.ndarray, inward: np.ndarray) -> np.ndarray | None:
        """Line (nx, ny, c), n.x + c = 0, n inward, through edge points (undistorted px)."""
        cfg = self.config
        line = _fit_line(edge_u, cfg.line_inlier_px,
                         int(np.ceil(cfg.min_edge_inlier_fraction * cfg.samples_per_side)))
        if line is None:
            return None
        return line if np.dot(line[:2], inward) >= 0.0 else -line


def _steps_into_band(profile: np.ndarray, polarity: int, margin: float) -> np.ndarray:
    """Mask (n, m - 1) of the steps between profile samples j, j+1 that lead into the band.

    The dark side of a step is inwards (samples j+1 ...) for a falling step, outwards
    (... j) for a rising one. It leads into the band when the darkest sample within
    ``_BAND_REACH_PX`` on that side is within ``margin`` grey levels of the profile's darkest.
    """
    reach = max(1, int(round(_BAND_REACH_PX / _PROFILE_STEP_PX)))
    n, m = profile.shape
    padded = np.pad(profile, ((0, 0), (reach, reach)), mode='edge')
    windows = np.lib.stride_tricks.sliding_window_view(padded, reach, axis=1)
    # windows[:, i] covers profile samples i - reach ... i - 1
    if polarity == _FALLING:
        side_min = windows[:, reach + 1:reach + m].min(axis=2)     # samples j+1 ... j+reach
    else:
        side_min = windows[:, 1:m].min(axis=2)                      # samples j-reach+1 ... j
    return side_min <= profile.min(axis=1, keepdims=True) + margin


def _children_area(contours, hierarchy, child: int) -> float:
    """Total area of a contour's holes (its children in a RETR_CCOMP hierarchy)."""
    total = 0.0
    while child != -1:
        total += cv2.contourArea(contours[child])
        child = hierarchy[child][0]
    return total


def _quad_area(quad: np.ndarray) -> float:
    """Area of a simple polygon (shoelace)."""
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _profiles(gray: np.ndarray, camera: CameraModel, samples_u: np.ndarray,
              inward_u: np.ndarray, offsets: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intensity profiles along the image normal of a straight undistorted edge.

    The samples and the normal are mapped into the distorted image (where the edge is
    curved); returns (profiles (n, m) bilinear, base points (n, 2) and unit normals (n, 2)
    in distorted pixels).
    """
    base = _distort_px(camera, samples_u)
    probe = _distort_px(camera, samples_u + _NORMAL_PROBE_PX * inward_u)
    normal_d = probe - base
    normal_d /= np.linalg.norm(normal_d, axis=1, keepdims=True)
    grid = base[:, None, :] + offsets[None, :, None] * normal_d[:, None, :]
    profile = cv2.remap(gray, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return profile.astype(float), base, normal_d


def _undistorted_px(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels -> ideal pinhole pixels K [x/z, y/z, 1] (same K, no distortion)."""
    xy = camera.pixels_to_normalized(uv)
    return xy * np.array([camera.K[0, 0], camera.K[1, 1]]) + camera.K[:2, 2]


def _distort_px(camera: CameraModel, uv_u: np.ndarray) -> np.ndarray:
    """Ideal pinhole pixels -> distorted pixels."""
    focal = np.array([camera.K[0, 0], camera.K[1, 1]])
    xy = (np.asarray(uv_u, dtype=float) - camera.K[:2, 2]) / focal
    uv, _ = camera.bearings_to_pixels(np.column_stack([xy, np.ones(len(xy))]))
    return uv


def _fit_line(points: np.ndarray, inlier_px: float, min_inliers: int) -> np.ndarray | None:
    """Robust total-least-squares line (nx, ny, c) with n.x + c = 0, |n| = 1, or None.

    Huber fit (cv2.fitLine), then points farther than ``inlier_px`` are dropped and the line
    is refitted by orthogonal least squares (SVD).
    """
    if len(points) < max(2, min_inliers):
        return None
    pts = points.astype(np.float32).reshape(-1, 1, 2)
    vx, vy, x0, y0 = cv2.fitLine(pts, cv2.DIST_HUBER, 0, 0.01, 0.01).reshape(-1)
    n = np.array([-vy, vx], dtype=float)
    c = -float(n @ np.array([x0, y0]))
    inliers = np.abs(points @ n + c) <= inlier_px
    if inliers.sum() < max(2, min_inliers):
        return None
    sel = points[inliers]
    centre = sel.mean(axis=0)
    _, _, vt = np.linalg.svd(sel - centre)
    n = vt[-1]
    return np.array([n[0], n[1], -float(n @ centre)])


def _intersect_consecutive(lines: list[np.ndarray]) -> np.ndarray | None:
    """Corner i = intersection of line i-1 and line i (homogeneous cross product)."""
    corners = []
    for i in range(N_CORNERS):
        l1, l2 = lines[i - 1], lines[i]
        if abs(l1[0] * l2[1] - l1[1] * l2[0]) < _MIN_SIN_EDGE_ANGLE:
            return None
        x = np.cross(l1, l2)
        corners.append(x[:2] / x[2])
    return np.array(corners)
