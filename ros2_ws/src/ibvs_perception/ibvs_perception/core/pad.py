"""Landing-pad detection: ArUco markers grouped by the pad layout, marker centres as bearings.

The landmarks of the paper's eq:q_t are the marker *centres* of every complete group (4 of 4
markers seen). A marker centre is the intersection of its diagonals in undistorted
coordinates (the image of the 3-D centre under a perspective map, unlike the corner mean),
then turned into a unit bearing in the optical frame (x right, y down, z forward).
The centroid of the marker centres is *not* the same vector for every set of complete groups
(rings of other radii around the pad centre: another magnitude and, off the pad's axis or
tilted, another direction; up to ~0.8 deg and 0.045 in |q_t| at one switch on sim renders).
The controller's q_t is therefore ``ibvs_common.core.features.pad_feature``: the pad centre
seen through each complete group's plane map (its 4 centres against the layout), the same
vector from every group up to the detection noise.

Small markers: a group whose markers are too small for ArUco in the full-resolution search
(below ~12-15 px) is searched again in an upscaled crop around where a complete group
predicts it (``_small_pass``; ``small_marker_px``).

Speed: once a group is complete, the next frame is searched only in a region of interest, the
bounding box of the pad markers seen last grown by a margin (the smaller groups lie inside the
larger ones, so groups that appear during the descent are inside it). The whole image is
searched when no group is complete in the region (loss, same frame), every
``full_search_every_n_frames`` frames, and when nothing is tracked. The minimum marker
perimeter stays the same number of pixels in the region as in the whole image, and the region
keeps markers away from its border, so the region finds what the whole image would. Only the
corners of the markers of complete groups (the ones the centres need) are refined.

OpenCV settings: ``process`` runs OpenCV with its Intel IPP paths off and one thread by default
(``use_ipp``, ``opencv_threads``; both restored afterwards): faster on a VM and deterministic
(docs/perception.md, "OpenCV settings").
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

from ibvs_common.core.params import param
from ibvs_common.core.camera import CameraModel
from ibvs_common.core.config import MarkerGroup, PadLayout
from ibvs_common.core.cv_compat import aruco_parameters, ArucoMarkerDetector

MARKER_CORNERS = 4
#: smallest |cross| of the two diagonals (normalised coordinates) accepted as a centre
_MIN_DIAGONAL_CROSS = 1e-12
#: the 8 corner orders of a square: the 4 cyclic shifts, in either direction
_CORNER_ORDERS = np.array([[(j - k) % MARKER_CORNERS for j in range(MARKER_CORNERS)]
                           for k in range(MARKER_CORNERS)]
                          + [[MARKER_CORNERS - 1 - (j - k) % MARKER_CORNERS
                              for j in range(MARKER_CORNERS)] for k in range(MARKER_CORNERS)])


class PadConfigError(ValueError):
    """The pad layout names an ArUco dictionary that OpenCV does not know."""


MODULES_PER_SIDE = 6     # DICT_4X4: 4 data bits + 2 border modules per side


DEFAULT_FRAME_PERIOD_S = 0.02     # s, a 50 Hz camera computing every frame


@dataclass(frozen=True)
class PadDetectorConfig:
    """Tuning of the ArUco detector (OpenCV DetectorParameters names, pixels)."""

    adaptive_thresh_win_size_min: int = param(
        21, 'px: smallest ArUco adaptive threshold window, >= 3 (min = max: one pass, fastest)', 3,
        1001)
    adaptive_thresh_win_size_max: int = param(
        21, 'px: largest ArUco adaptive threshold window, >= min', 3, 1001)
    adaptive_thresh_win_size_step: int = param(
        10, 'px: step between adaptive threshold windows, > 0', 1, 1000)
    adaptive_thresh_constant: float = param(
        30.0, 'grey levels (of 255) below the local mean counted as black', 0.0, 255.0)
    min_marker_perimeter_rate: float = param(
        0.04,
        'marker perimeter / largest side of the whole image, lower bound (the same px in the '
        'tracked region)', 0.0, 4.0)
    min_corner_distance_rate: float = param(
        0.1, "candidate's min corner distance / its perimeter", 0.0, 1.0)
    corner_refinement_win_size: int = param(5, 'px: sub-pixel corner refinement window', 1, 100)
    corner_refinement_max_iterations: int = param(
        30, 'iterations of the sub-pixel corner refinement', 1, 10000)
    corner_refinement_min_accuracy: float = param(
        0.01, 'px: the corner refinement stops below this change', 0.0)
    relative_corner_refinement_win_size: float = param(
        0.3, 'corner refinement window / marker module size', 0.0)
    roi_margin_fraction: float = param(
        0.1, "tracking: the next frame's search region is the last markers' bounding box grown by "
        'this fraction of its larger side', 0.0)
    roi_margin_px: int = param(12, 'px added to the tracking region margin', 0)
    full_search_every_n_frames: int = param(
        50, 'frames: whole-image search at least this often (0: only on a loss)', 0)
    roi_max_age_frames: float = param(
        1.5, 'computed frames (the camera period times the frame stride): a tracking region '
        'older than this (a frame lost on the way) is not used', 0.0)
    max_layout_error: float = param(
        0.1,
        "a complete group whose marker corners miss the group's layout (the homography of its 4 "
        "marker centres) by more than this fraction of a marker's side in the image plus "
        'max_layout_error_px is rejected (a foreign marker carrying a pad id)', 0.0)
    max_layout_error_px: float = param(
        3.0,
        'px (undistorted): added to the allowed corner error of the layout check (corner noise '
        'of small markers)', 0.0)
    small_marker_px: float = param(
        20.0,
        'px: small-marker pass: an incomplete group whose smallest marker, predicted through a '
        'complete group, is below this is searched again in an upscaled crop around it (0: off)',
        0.0)
    small_marker_min_px: float = param(
        8.0,
        'px: the small-marker pass skips a group predicted smaller than this (too few pixels per'
        ' module to decode)', 0.0)
    small_marker_target_px: float = param(
        24.0,
        'px: the small-marker crop is upscaled by an integer factor (2-4) bringing the predicted'
        ' smallest marker near this', 1.0)
    use_ipp: bool = param(
        False,
        "OpenCV's Intel IPP inside the detector (off: its CPU dispatch traps to the hypervisor "
        'on VMs)')
    opencv_threads: int = param(
        1, "OpenCV threads inside the detector (0: leave OpenCV's setting)", 0, 1024)
    group_weight_border_px: float = param(
        20.0,
        "px: a group's weight in the pad feature (pad/groups) grows from 0 to 1 as its "
        "markers' corners get this far from the image border: a group that enters or leaves "
        'the image moves q_t gradually, not by a step (0: off)', 0.0)
    group_weight_min_side_px: float = param(
        8.0, "px: a group's weight is 0 when its smallest marker side is this small ...", 0.0)
    group_weight_full_side_px: float = param(
        24.0, '... and 1 from this side on (markers near the size ArUco can read come and go)',
        0.0)

    def __post_init__(self) -> None:
        """Raise ValueError naming the parameter for what a range cannot check (OpenCV)."""
        if not 3 <= self.adaptive_thresh_win_size_min <= self.adaptive_thresh_win_size_max:
            raise ValueError(
                'parameters adaptive_thresh_win_size_min '
                f'({self.adaptive_thresh_win_size_min}) and adaptive_thresh_win_size_max '
                f'({self.adaptive_thresh_win_size_max}): need 3 <= min <= max')
        if not self.adaptive_thresh_win_size_step > 0:
            raise ValueError('parameter adaptive_thresh_win_size_step must be > 0, got '
                             f'{self.adaptive_thresh_win_size_step}')
        if not self.group_weight_min_side_px <= self.group_weight_full_side_px:
            raise ValueError('parameters group_weight_min_side_px '
                             f'({self.group_weight_min_side_px}) and group_weight_full_side_px '
                             f'({self.group_weight_full_side_px}): need min <= full')


@dataclass(frozen=True)
class PadDetection:
    """Landmarks of all complete groups: ordered group by group (largest first), ids order."""

    bearings_C: np.ndarray          # (N, 3) unit bearings of the marker centres, N = 4 k
    group_names: tuple[str, ...]    # the complete groups used, same order
    centres_px: np.ndarray          # (N, 2) distorted pixels of the centres (debug)
    rejected_groups: tuple[str, ...] = ()   # complete groups that failed the layout check
    group_weights: tuple[float, ...] = ()   # per group in group_names: group_weight()


def aruco_dictionary(name: str) -> 'cv2.aruco.Dictionary':
    """Return the predefined OpenCV dictionary of a layout name such as 'DICT_4X4_50'."""
    code = getattr(cv2.aruco, name, None) if name.startswith('DICT_') else None
    if not isinstance(code, int):
        raise PadConfigError(f'unknown ArUco dictionary {name!r}')
    return cv2.aruco.getPredefinedDictionary(code)


def marker_centre_normalized(corners_xy: np.ndarray) -> np.ndarray | None:
    """Intersection of the diagonals 0-2 and 1-3 of 4 undistorted points (normalised coords).

    Returns (x, y) or None for degenerate diagonals. Homogeneous lines: l = a x b.
    """
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners_xy, dtype=float).tolist()
    # the products of np.cross, written out (same operations, same result; 30x faster)
    l02 = (y0 - y2, x2 - x0, x0 * y2 - y0 * x2)         # (x0, y0, 1) x (x2, y2, 1)
    l13 = (y1 - y3, x3 - x1, x1 * y3 - y1 * x3)
    cx = l02[1] * l13[2] - l02[2] * l13[1]
    cy = l02[2] * l13[0] - l02[0] * l13[2]
    cw = l02[0] * l13[1] - l02[1] * l13[0]
    if abs(cw) < _MIN_DIAGONAL_CROSS:
        return None
    return np.array([cx, cy]) / cw


def _ramp(x: float) -> float:
    """Return the smoothstep of ``x``: 0 below 0, 1 above 1, C1 in between."""
    x = min(max(float(x), 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


#: the smallest weight a complete group gets (a lone group at the border still counts)
MIN_GROUP_WEIGHT = 1e-3


def group_weight(corners_px: np.ndarray, width: int, height: int, border_px: float,
                 min_side_px: float, full_side_px: float) -> float:
    """Return a complete group's weight in the pad feature from its markers' corners (px).

    The product of two ramps (smoothstep): the distance of its nearest corner to the image
    border over ``border_px``, and its smallest marker's mean side between ``min_side_px``
    (0) and ``full_side_px`` (1); at least :data:`MIN_GROUP_WEIGHT`. A group is seen until it
    reaches the border, or shrinks to what ArUco cannot read, so its weight is near 0 when it
    appears or goes: q_t (features.pad_feature) then moves by a fraction of the group's own
    bias at that frame instead of by the whole step. ``corners_px`` (n, 4, 2), distorted.
    """
    c = np.asarray(corners_px, dtype=float).reshape(-1, MARKER_CORNERS, 2)
    margin = float(np.min(np.concatenate([c[..., 0].ravel(), c[..., 1].ravel(),
                                          (width - 1.0 - c[..., 0]).ravel(),
                                          (height - 1.0 - c[..., 1]).ravel()])))
    side = float(np.min(np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2).mean(axis=1)))
    w_border = 1.0 if border_px <= 0.0 else _ramp(margin / border_px)
    span = full_side_px - min_side_px
    w_size = (1.0 if side >= full_side_px else 0.0) if span <= 0.0 \
        else _ramp((side - min_side_px) / span)
    return max(w_border * w_size, MIN_GROUP_WEIGHT)


def layout_errors(group: MarkerGroup, corners_xy: list[np.ndarray], centres_xy: np.ndarray,
                  focal_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Corner errors of a complete group against its layout: (error px, side px) per marker.

    The pad is a plane, so its image is a homography of it. The homography H is fixed by the
    group's 4 marker centres (layout, pad-plane metres -> detected centres, undistorted
    normalised coordinates); each marker's square (``group.side``, axis-aligned on the pad)
    mapped by H must then land on its 4 detected corners. A marker's error is its largest
    corner distance for the best of the 4 cyclic corner orders in either direction (ArUco's
    corner order is the marker's own), its side the mean of its 4 detected sides, both in
    undistorted pixels (normalised x ``focal_px``). A foreign marker carrying a pad id moves
    one centre: H bends to it and the squares miss their corners; a correct group misses by
    the corner noise only (sim renders: <= 0.9 px for markers > 40 px, <= 2.6 px at 12 px).
    """
    plane = group.marker_centres_I()[:, :2]
    H = cv2.getPerspectiveTransform(plane.astype(np.float32), centres_xy.astype(np.float32))
    h = 0.5 * group.side
    square = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    pts = np.concatenate([np.column_stack([c + square, np.ones(MARKER_CORNERS)])
                          for c in plane]) @ H.T
    predicted = (pts[:, :2] / pts[:, 2:3]).reshape(len(plane), MARKER_CORNERS, 2)
    detected = np.asarray(corners_xy, dtype=float).reshape(len(plane), MARKER_CORNERS, 2)
    # predicted[:, order] for the 8 corner orders, (marker, order, corner, xy)
    distances = np.linalg.norm(predicted[:, _CORNER_ORDERS] - detected[:, None], axis=3)
    errors = distances.max(axis=2).min(axis=1)
    sides = np.linalg.norm(detected - np.roll(detected, -1, axis=1), axis=2).mean(axis=1)
    return focal_px * errors, focal_px * sides


@contextmanager
def opencv_settings(use_ipp: bool, threads: int) -> Iterator[None]:
    """Run a block with OpenCV's IPP switch and thread count set, then restore both.

    ``threads`` <= 0 leaves the thread count alone. The IPP switch is per thread (OpenCV's
    thread-local setting), the thread count is process-wide.
    """
    saved_ipp, saved_threads = cv2.ipp.useIPP(), cv2.getNumThreads()
    cv2.ipp.setUseIPP(use_ipp)
    if threads > 0:
        cv2.setNumThreads(threads)
    try:
        yield
    finally:
        cv2.ipp.setUseIPP(saved_ipp)
        if threads > 0:
            cv2.setNumThreads(saved_threads)


class PadDetector:
    """Detect the pad's ArUco markers and return the centres of complete groups.

    Stateful: the region of interest follows the last detection (see the module docstring).
    ``last_search`` tells how the last frame was searched: 'roi', 'full' or 'roi+full' (loss).
    """

    def __init__(self, layout: PadLayout, config: PadDetectorConfig) -> None:
        self.layout = layout
        self.config = config
        self._layout_ids = {i for g in layout.groups for i in g.ids}
        self._roi: tuple[int, int, int, int] | None = None     # x0, y0, x1, y1 (exclusive)
        self._roi_stamp: float | None = None
        self._frames_since_full = 0
        self.last_search = ''
        # s between two computed frames: the camera period times the frame stride (the node
        # sets it from vehicle.yaml's rate and ibvs/frame_grid)
        self.frame_period_s = DEFAULT_FRAME_PERIOD_S
        params = aruco_parameters()
        params.adaptiveThreshWinSizeMin = config.adaptive_thresh_win_size_min
        params.adaptiveThreshWinSizeMax = config.adaptive_thresh_win_size_max
        params.adaptiveThreshWinSizeStep = config.adaptive_thresh_win_size_step
        params.adaptiveThreshConstant = config.adaptive_thresh_constant
        params.minMarkerPerimeterRate = config.min_marker_perimeter_rate
        params.minCornerDistanceRate = config.min_corner_distance_rate
        # Sub-pixel refinement is done by _refine on the full image (same window and
        # criteria as ArUco's CORNER_REFINE_SUBPIX), not inside detectMarkers on a crop.
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        params.cornerRefinementWinSize = config.corner_refinement_win_size
        params.cornerRefinementMaxIterations = config.corner_refinement_max_iterations
        params.cornerRefinementMinAccuracy = config.corner_refinement_min_accuracy
        self._params = params
        self._detector = ArucoMarkerDetector(aruco_dictionary(layout.dictionary), params)

    def reset(self) -> None:
        """Forget the tracked region: the next frame is searched whole."""
        self._roi = None

    def detect_markers(self, gray: np.ndarray, roi: tuple[int, int, int, int] | None = None,
                       upscale: int = 1, min_side_px: float | None = None
                       ) -> dict[int, np.ndarray]:
        """Marker id -> corners (4, 2) in distorted px; ids seen more than once are dropped.

        ``roi``: (x0, y0, x1, y1), search only there (same minimum perimeter in pixels).
        ``upscale``: search the region enlarged by this integer factor (bicubic; corners
        mapped back to the image's pixels); ``min_side_px``: the smallest marker side (px of
        the image) accepted instead of the one of ``min_marker_perimeter_rate``.
        """
        if roi is None:
            image, offset, side = gray, np.zeros(2), max(gray.shape)
        else:
            x0, y0, x1, y1 = roi
            image, offset, side = gray[y0:y1, x0:x1], np.array([x0, y0], float), \
                max(x1 - x0, y1 - y0)
        if upscale > 1:
            image = cv2.resize(image, None, fx=upscale, fy=upscale,
                               interpolation=cv2.INTER_CUBIC)
        rate = (self.config.min_marker_perimeter_rate * max(gray.shape) / side
                if min_side_px is None else MARKER_CORNERS * min_side_px / side)
        if rate != self._params.minMarkerPerimeterRate:
            self._params.minMarkerPerimeterRate = rate
            self._detector.set_parameters(self._params)
        corners, ids = self._detector.detect(image)
        if ids is None:
            return {}
        found: dict[int, np.ndarray] = {}
        duplicated = set()
        for c, i in zip(corners, ids.reshape(-1)):
            i = int(i)
            if i in found:
                duplicated.add(i)
            c = np.asarray(c, dtype=float).reshape(MARKER_CORNERS, 2)
            # resize maps pixel centres: image x = (upscaled x + 0.5) / upscale - 0.5
            found[i] = (c + 0.5) / upscale - 0.5 + offset if upscale > 1 else c + offset
        return {i: c for i, c in found.items() if i not in duplicated}

    def _small_pass(self, gray: np.ndarray, camera: CameraModel, markers: dict[int, np.ndarray],
                    refined: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Markers of incomplete groups too small for the search, found in upscaled crops.

        ``markers``: all markers the search found; ``refined``: the complete groups' markers,
        corners refined on the full image. The largest complete group maps the pad plane to
        the image (homography of its 4 refined marker centres, undistorted normalised
        coordinates, as ``layout_errors``; refined, so that the crops do not depend on how
        the frame was searched) and so predicts every marker of the other groups. An
        incomplete group whose predicted smallest marker side (px) lies in
        [``small_marker_min_px``, ``small_marker_px``) and whose markers lie wholly inside the
        image is searched again in the bounding box of its predicted markers grown by one
        marker side, upscaled (bicubic) by an integer factor of 2-4 that brings that side near
        ``small_marker_target_px``. Only that group's ids are taken from the crop, and only
        ids the search did not find; the layout check then judges the group as any other.
        Returns the markers added (unrefined corners, distorted px).
        """
        cfg = self.config
        if cfg.small_marker_px <= 0.0 or cfg.small_marker_min_px <= 0.0:
            return {}
        base = next((g for g in self.layout.groups if all(i in refined for i in g.ids)), None)
        if base is None:
            return {}
        xy = camera.pixels_to_normalized(np.concatenate([refined[i] for i in base.ids]))
        centres = [marker_centre_normalized(c) for c in xy.reshape(-1, MARKER_CORNERS, 2)]
        if any(c is None or not np.all(np.isfinite(c)) for c in centres):
            return {}
        H = cv2.getPerspectiveTransform(base.marker_centres_I()[:, :2].astype(np.float32),
                                        np.asarray(centres, dtype=np.float32))
        h, w = gray.shape[:2]
        added: dict[int, np.ndarray] = {}
        for group in self.layout.groups:
            if all(i in markers for i in group.ids):
                continue
            half = 0.5 * group.side
            square = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
            plane = np.concatenate([c + square for c in group.marker_centres_I()[:, :2]])
            pts = np.column_stack([plane, np.ones(len(plane))]) @ H.T
            if np.any(pts[:, 2] <= 0.0):
                continue
            uv, inside = camera.bearings_to_pixels(pts)
            if not np.all(inside):
                continue
            quads = uv.reshape(len(group.ids), MARKER_CORNERS, 2)
            side = float(np.min(np.linalg.norm(quads - np.roll(quads, 1, axis=1), axis=2)))
            if not cfg.small_marker_min_px <= side < cfg.small_marker_px:
                continue
            lo, hi = uv.min(axis=0) - side, uv.max(axis=0) + side
            roi = (max(int(lo[0]), 0), max(int(lo[1]), 0),
                   min(int(np.ceil(hi[0])) + 1, w), min(int(np.ceil(hi[1])) + 1, h))
            factor = int(np.clip(np.ceil(cfg.small_marker_target_px / side), 2, 4))
            found = self.detect_markers(gray, roi, factor, 0.7 * cfg.small_marker_min_px)
            added.update({i: c for i, c in found.items()
                          if i in group.ids and i not in markers})
        return added

    def _complete(self, markers: dict[int, np.ndarray]) -> bool:
        return any(all(i in markers for i in g.ids) for g in self.layout.groups)

    def _complete_ids(self, markers: dict[int, np.ndarray]) -> list[int]:
        """Ids of the markers of every complete group (the only corners the centres need)."""
        return [i for g in self.layout.groups if all(j in markers for j in g.ids) for i in g.ids]

    def _refine(self, gray: np.ndarray, markers: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Refine every corner given sub-pixel on the full image (ArUco's SUBPIX settings).

        Done here rather than inside detectMarkers, whose refinement would run on the region
        of interest's crop: on the full image the result no longer depends on how the marker
        was found (region or whole image, i.e. on the frame history), which is what a replayed
        bag must reproduce.
        """
        if not markers:
            return markers
        cfg = self.config
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
                    cfg.corner_refinement_max_iterations, cfg.corner_refinement_min_accuracy)
        ids = list(markers)
        corners = np.stack([markers[i] for i in ids])                    # (n, 4, 2)
        # as ArUco: the window shrinks with the module size, so that it stays off the
        # marker's inner bits (module = side / (4 data bits + 2 border))
        sides = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).mean(axis=1)
        wins = np.clip(np.round(cfg.relative_corner_refinement_win_size * sides
                                / MODULES_PER_SIDE), 1, cfg.corner_refinement_win_size)
        refined = corners.astype(np.float32)
        for w in np.unique(wins).astype(int):                # one call per window size
            sel = wins == w
            pts = refined[sel].reshape(-1, 1, 2)
            cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), criteria)
            refined[sel] = pts.reshape(-1, MARKER_CORNERS, 2)
        return {i: refined[k].astype(float) for k, i in enumerate(ids)}

    def _track(self, gray: np.ndarray, camera: CameraModel,
               stamp_s: float | None = None) -> dict[int, np.ndarray]:
        """Markers of this frame: in the region of interest, else in the whole image.

        With a complete group: the markers of the complete groups, corners refined, including
        the groups that the small-marker pass (``_small_pass``) completes; else all markers
        found, unrefined (no group is reported).
        """
        cfg = self.config
        period = cfg.full_search_every_n_frames
        max_age_s = cfg.roi_max_age_frames * self.frame_period_s
        markers: dict[int, np.ndarray] = {}
        self.last_search = ''
        if stamp_s is not None and self._roi_stamp is not None \
                and not 0.0 < stamp_s - self._roi_stamp <= max_age_s:
            self._roi = None            # frames were skipped (or time went back): search all
        self._roi_stamp = stamp_s
        if self._roi is not None and (period <= 0 or self._frames_since_full + 1 < period):
            markers = self.detect_markers(gray, self._roi)
            self.last_search = 'roi'
            self._frames_since_full += 1
        if not self._complete(markers):
            markers = self.detect_markers(gray)
            self.last_search = 'roi+full' if self.last_search else 'full'
            self._frames_since_full = 0
        pad = [c for i, c in markers.items() if i in self._layout_ids]
        if not self._complete(markers) or not pad:
            self._roi = None
            return markers
        pts = np.concatenate(pad)      # region from the unrefined corners (margin >> 1 px)
        refined = self._refine(gray, {i: markers[i] for i in self._complete_ids(markers)})
        extra = self._small_pass(gray, camera, markers, refined)
        if extra:                   # groups the small-marker pass completed: refine them too
            markers.update(extra)
            refined.update(self._refine(gray, {i: markers[i] for i in self._complete_ids(markers)
                                               if i not in refined}))
        markers = refined
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        margin = cfg.roi_margin_fraction * float(np.max(hi - lo)) + cfg.roi_margin_px
        h, w = gray.shape[:2]
        self._roi = (max(int(lo[0] - margin), 0), max(int(lo[1] - margin), 0),
                     min(int(np.ceil(hi[0] + margin)) + 1, w),
                     min(int(np.ceil(hi[1] + margin)) + 1, h))
        return markers

    def process(self, gray: np.ndarray, camera: CameraModel,
                stamp_s: float | None = None) -> PadDetection:
        """Landmarks of every complete group (empty arrays when none is complete).

        ``stamp_s``: the image time; a region of interest from a frame more than
        ``roi_max_age_frames`` computed frames older is dropped for a whole-image search.
        """
        with opencv_settings(self.config.use_ipp, self.config.opencv_threads):
            markers = self._track(gray, camera, stamp_s)
        bearings, names, rejected, weights = [], [], [], []
        cfg = self.config
        for group in self.layout.groups:
            if not all(i in markers for i in group.ids):
                continue
            corners_xy = list(camera.pixels_to_normalized(   # one call: the same per point
                np.concatenate([markers[i] for i in group.ids])).reshape(-1, MARKER_CORNERS, 2))
            centres_xy = [marker_centre_normalized(xy) for xy in corners_xy]
            if any(c is None or not np.all(np.isfinite(c)) for c in centres_xy):
                continue
            centres_xy = np.asarray(centres_xy)
            errors_px, sides_px = layout_errors(group, corners_xy, centres_xy, camera.K[0, 0])
            if not np.all(errors_px <= self.config.max_layout_error * sides_px
                          + self.config.max_layout_error_px):
                rejected.append(group.name)
                continue
            names.append(group.name)
            bearings.extend(np.column_stack([centres_xy, np.ones(len(centres_xy))]))
            weights.append(group_weight(
                np.stack([markers[i] for i in group.ids]), gray.shape[1], gray.shape[0],
                cfg.group_weight_border_px, cfg.group_weight_min_side_px,
                cfg.group_weight_full_side_px))
        if not bearings:
            return PadDetection(np.zeros((0, 3)), (), np.zeros((0, 2)), tuple(rejected))
        b = np.asarray(bearings)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        centres, _ = camera.bearings_to_pixels(b)
        return PadDetection(b, tuple(names), centres, tuple(rejected), tuple(weights))
