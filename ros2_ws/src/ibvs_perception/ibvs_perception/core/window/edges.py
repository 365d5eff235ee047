"""Sub-pixel edges of a candidate: its band's outer quad and the aperture inside it.

Each side of a quad is sampled in undistorted px (where a straight 3-D edge stays straight),
the samples are mapped into the distorted image and an intensity profile is read along the
local image normal; the edge is the gradient centroid of the step of the expected polarity
that leads into the band. A robust line through each side's edge points gives the corners.
The aperture is the band's inner edge, near where the band's proportions put it.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import cv2
import numpy as np

from ibvs_common.core.camera import CameraModel

from .band import BandProportions
from .config import SINGLE_PASS_MARGIN, WindowDetectorConfig
from .geometry import (_distort_px, _edge_normals, _intersect_consecutive, _largest_distance,
                       _NEXT, _quad_area, _side_lines_through, _SIDE_MARGIN, _sides,
                       _undistorted_px, N_CORNERS)
from .results import Reject, WindowDetection

#: the step of the intensity profiles along the edge normal, px
_PROFILE_STEP_PX = 0.5
#: half-width of the gradient window whose centroid gives the sub-pixel edge, in profile steps
_CENTROID_HALF_WIDTH = 3
#: small pixel offset used to map an undistorted normal into the distorted image, px
_NORMAL_PROBE_PX = 1.0
#: points per side checked to lie inside the image (edges are curved there)
_OUTLINE_SAMPLES = 9
#: where the band's dark level is read, inwards of the outer edge, px
_BAND_PROBE_PX = 1.5
#: polarity of a step along the inward normal
_RISING = 1
_FALLING = -1
#: a band edge's dark side reaches the band's level within this distance of the step, px
#: (a blurred edge spans ~2 px; a texture step beside the band does not lead into it)
_BAND_REACH_PX = 2.0
#: tangential offsets of the parallel profiles averaged per edge sample, px (noise / sqrt(3);
#: +-2 px measured 0.02 px worse median on clean sim frames)
_TANGENT_OFFSETS_PX = (-1.0, 0.0, 1.0)
#: a blurred step's centroid window extends while the gradient stays above this fraction of
#: its peak, up to _MAX_EDGE_HALF_WIDTH profile steps on either side (lower fractions let
#: texture gradients beside a sharp edge in: 0.25 gave 0.17 px median on clean frames)
_EDGE_RUN_FRACTION = 0.7
_MAX_EDGE_HALF_WIDTH = 12
#: where the band's level is read between the outer and the predicted inner edge (fractions
#: of the predicted band width, from the outer edge)
_BAND_LEVEL_SPAN = (0.25, 0.5)


class Aperture(NamedTuple):
    """What one refine found of the aperture, for the track of the next frame."""

    quad_u: np.ndarray                # (4, 2) undistorted px
    predicted_u: np.ndarray           # (4, 2) where the band's proportions put it
    sign: np.ndarray | None           # each side's polarity; None: a side not measured
    level: np.ndarray                 # the band's level per sample
    one_pass: bool                    # refined once from the prediction (no search)


class Refined(NamedTuple):
    """A candidate refined into a window."""

    detection: WindowDetection
    outer_u: np.ndarray               # (4, 2) the band's refined outer quad, undistorted px
    aperture: Aperture
    one_pass: bool                    # the outer edges took one pass of the refine range


class EdgeRefiner:
    """Sub-pixel outer and aperture edges of one candidate, the window they give or why not."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config
        self.band = BandProportions(config)

    def refine(self, gray: np.ndarray, camera: CameraModel, outer_u: np.ndarray,
               single_pass: bool = False, last_aperture: Aperture | None = None
               ) -> Refined | str:
        """Sub-pixel aperture corners of a candidate ring and its refined outer quad.

        Outer edges (light wall -> dark band, inwards) are fitted first, in two passes (the
        search range, then the refine range around the first fit; ``single_pass``: the refine
        range only, for a well predicted track); the aperture edges are the first dark -> light
        step inwards of them, then fitted again in a narrow band (``last_aperture``: first
        refined once from where the band's proportions put them, with its polarities and band
        level, :meth:`_aperture_from_track`). All fits are straight lines in undistorted pixels.
        Returns the window, or the :class:`Reject` reason of the stage that failed.
        """
        cfg = self.config
        threshold = None
        passes = (cfg.refine_half_width_px,) if single_pass \
            else (cfg.search_half_width_px, cfg.refine_half_width_px)
        for half_width in passes:
            outer_u, threshold = self._fit_quad(gray, camera, outer_u, half_width, _FALLING,
                                                threshold)
            if outer_u is None:
                return Reject.OUTER_EDGES
        if not self._inside_image(camera, outer_u):
            return Reject.OUTSIDE
        predicted = self.band.predicted_inner(outer_u)
        aperture = None if last_aperture is None else self._aperture_from_track(
            gray, camera, outer_u, predicted, threshold, last_aperture)
        if aperture is None:
            aperture = self._search_aperture(gray, camera, outer_u, predicted, threshold)
        if aperture is None:
            return Reject.INNER_EDGES
        inner_u = aperture.quad_u
        if not cv2.isContourConvex(inner_u.astype(np.float32)):
            return Reject.BAND_SHAPE
        ratio = _quad_area(inner_u) / _quad_area(outer_u)
        if not cfg.min_hole_area_ratio <= ratio <= cfg.max_hole_area_ratio:
            return Reject.BAND_SHAPE
        K = camera.K
        normalized = (inner_u - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        bearings = np.column_stack([normalized, np.ones(N_CORNERS)])
        bearings /= np.linalg.norm(bearings, axis=1, keepdims=True)
        corners_px = _distort_px(camera, inner_u)
        return Refined(WindowDetection(corners_px, bearings, _edge_normals(bearings)), outer_u,
                       aperture, single_pass)

    def _inside_image(self, camera: CameraModel, quad_u: np.ndarray) -> bool:
        """Whether the whole (curved) outline of a quad lies border_margin_px inside."""
        t = np.linspace(0.0, 1.0, _OUTLINE_SAMPLES)[None, :, None]
        outline = quad_u[:, None, :] + t * (quad_u[_NEXT] - quad_u)[:, None, :]
        uv = _distort_px(camera, outline.reshape(-1, 2))
        m = self.config.border_margin_px
        return bool(np.all(np.isfinite(uv)) and np.all(uv >= m)
                    and np.all(uv <= np.array([camera.width, camera.height]) - 1 - m))

    def _quad_samples(self, corners_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return sample points (4 n, 2) along the 4 sides and their inward unit normals.

        Sides follow each other (n samples each); undistorted px.
        """
        n = self.config.samples_per_side
        t = _side_fractions(n)[None, :, None]
        a = corners_u
        side = corners_u[_NEXT] - a                   # b - a per side
        direction = side / np.linalg.norm(side, axis=1, keepdims=True)
        inward = np.column_stack([-direction[:, 1], direction[:, 0]])
        to_centre = corners_u.mean(axis=0) - a
        inward[inward[:, 0] * to_centre[:, 0] + inward[:, 1] * to_centre[:, 1] < 0.0] *= -1.0
        samples = a[:, None, :] + t * side[:, None, :]
        return samples.reshape(-1, 2), np.repeat(inward, n, axis=0)

    def _side_lines(self, camera: CameraModel, base: np.ndarray, normal_d: np.ndarray,
                    pos: np.ndarray, ok: np.ndarray, inward: np.ndarray) -> list:
        """Line of each of the 4 sides through its valid edge points (undistorted px) or None.

        None for a side with fewer than min_edge_inlier_fraction valid points or no line fit.
        """
        cfg = self.config
        n = cfg.samples_per_side
        edge_u = np.full((len(ok), 2), np.nan)
        if ok.any():
            edge_u[ok] = _undistorted_px(camera, base[ok] + pos[ok, None] * normal_d[ok])
        enough = ok.reshape(N_CORNERS, n).sum(axis=1) >= cfg.min_edge_inlier_fraction * n
        lines = _robust_lines(edge_u.reshape(N_CORNERS, n, 2),
                              ok.reshape(N_CORNERS, n) & enough[:, None], cfg.line_inlier_px,
                              int(np.ceil(cfg.min_edge_inlier_fraction * n)))
        # each normal inwards
        return [None if line is None else (line if line[:2] @ inward[k * n] >= 0.0 else -line)
                for k, line in enumerate(lines)]

    def _fit_lines(self, gray: np.ndarray, camera: CameraModel, corners_u: np.ndarray,
                   half_width: float, polarity, threshold: float | None,
                   band_level: np.ndarray | None = None) -> tuple[list, float]:
        """Refit the 4 side lines of a quad (undistorted px) to the strongest step into the band.

        ``polarity``: +1 intensity rises inwards (band -> lighter aperture), -1 falls (wall ->
        band, or band -> darker aperture); one for all sides or one per side (4,).
        ``threshold``: the least valid step, grey levels; None: from these profiles' contrast
        (:meth:`_edge_threshold`). ``band_level``: None for the outer edges (the band lies
        inwards, its level is the profile's darkest); for the aperture edges the band's level
        per sample (4 samples_per_side,), the band lying outwards.
        Returns (the 4 lines or None per side, threshold).
        """
        offsets = np.arange(-half_width, half_width + 1e-9, _PROFILE_STEP_PX)
        samples_u, inward = self._quad_samples(corners_u)
        profile, base, normal_d = _profiles(gray, camera, samples_u, inward, offsets)
        if threshold is None:
            threshold = self._edge_threshold(profile)
        sign = np.repeat(np.broadcast_to(np.asarray(polarity, dtype=float), (N_CORNERS,)),
                         self.config.samples_per_side)
        grad = sign[:, None] * np.diff(profile, axis=1)
        if band_level is None:
            into_band = _steps_into_band(profile, _RISING, profile.min(axis=1), 0.5 * threshold)
        else:
            into_band = _steps_into_band(profile, _FALLING, band_level, 0.5 * threshold)
        peak = np.argmax(np.where(into_band, grad, -np.inf), axis=1)
        pos, ok = self._step_positions(grad, offsets, peak, threshold)
        ok &= into_band.any(axis=1)
        return self._side_lines(camera, base, normal_d, pos, ok, inward), threshold

    def _fit_quad(self, gray: np.ndarray, camera: CameraModel, corners_u: np.ndarray,
                  half_width: float, polarity: int,
                  threshold: float | None) -> tuple[np.ndarray | None, float]:
        """Refit a quad's 4 sides (:meth:`_fit_lines`) and intersect them: (quad, threshold)."""
        lines, threshold = self._fit_lines(gray, camera, corners_u, half_width, polarity,
                                           threshold)
        if any(line is None for line in lines):
            return None, threshold
        return _intersect_consecutive(lines), threshold

    def _edge_threshold(self, profile: np.ndarray) -> float:
        """Least valid edge step, grey levels, relative to the band's contrast to the wall.

        ``edge_contrast_fraction`` of the median range (max - min) of the outer-edge profiles
        (wall to band), at least ``min_edge_contrast``: an underexposed image lowers it.
        """
        cfg = self.config
        contrast = float(np.median(profile.max(axis=1) - profile.min(axis=1)))
        return max(cfg.min_edge_contrast, cfg.edge_contrast_fraction * contrast)

    def _search_aperture(self, gray: np.ndarray, camera: CameraModel, outer_u: np.ndarray,
                         predicted: np.ndarray, threshold: float) -> Aperture | None:
        """Aperture searched at the band's inner edge (undistorted px), brighter or darker beyond.

        Inwards along each sample of the outer sides the band's level is read over
        ``_BAND_LEVEL_SPAN`` of the band width predicted from the proportions, and the aperture
        edge is the first step beyond where the profile leaves that level by half the threshold,
        up or down (one polarity per side, by majority), then refined in a narrow band. The
        aperture may be lighter or darker than the band. A side with too few points, or whose
        line lies more than ``max_band_deviation`` band widths off the predicted one (a post or
        texture beside the band beyond the window), is taken from the prediction, provided the
        outer quad is a true view of the band's rectangle (``max_shape_error``). Else None.
        """
        cfg = self.config
        n = cfg.samples_per_side
        pred_lines = _side_lines_through(predicted)
        band = self._band_widths(outer_u, predicted)
        if band is None:
            return None
        offsets = np.arange(0.0, band.max() * (1.0 + cfg.max_band_deviation) + _BAND_REACH_PX
                            + 1e-9, _PROFILE_STEP_PX)
        samples_u, inward = self._quad_samples(outer_u)
        profile, base, normal_d = _profiles(gray, camera, samples_u, inward, offsets)
        level, crossing, sign = _band_departure(profile, offsets, band, 0.5 * threshold,
                                                cfg.max_band_deviation)
        side_sign = np.sign(sign.reshape(N_CORNERS, n).sum(axis=1))
        side_sign[side_sign == 0] = _RISING
        grad = np.repeat(side_sign, n)[:, None] * np.diff(profile, axis=1)
        hi = np.clip(crossing + 2 * _CENTROID_HALF_WIDTH, 0, grad.shape[1] - 1)
        window = np.clip(crossing[:, None] - 1 + np.arange(2 * _CENTROID_HALF_WIDTH + 2)[None, :],
                         0, hi[:, None])
        peak = np.take_along_axis(window, np.argmax(np.take_along_axis(grad, window, axis=1),
                                                    axis=1)[:, None], axis=1)[:, 0]
        pos, ok = self._step_positions(grad, offsets, peak, threshold)
        ok &= (sign == np.repeat(side_sign, n)) & (crossing > 0)
        lines = self._side_lines(camera, base, normal_d, pos, ok, inward)
        lines = [_near_or_none(line, pred, p, dev)
                 for line, pred, p, dev in zip(lines, pred_lines, _sides(predicted),
                                               cfg.max_band_deviation * band)]
        if any(line is None for line in lines) \
                and self.band.shape_error(camera, outer_u) > cfg.max_shape_error:
            return None
        first = _intersect_consecutive([p if m is None else m
                                        for m, p in zip(lines, pred_lines)])
        if first is None:
            return None
        refined, _ = self._fit_lines(gray, camera, first, cfg.refine_half_width_px, side_sign,
                                     threshold, band_level=level)
        final = []
        for line, again, pred, p, dev in zip(lines, refined, pred_lines, _sides(predicted),
                                             cfg.max_band_deviation * band):
            again = None if line is None else _near_or_none(again, pred, p, dev)
            final.append(pred if line is None else (line if again is None else again))
        quad = _intersect_consecutive(final)
        if quad is None:
            return None
        # a side taken from the proportions (no edge, e.g. a room as dark as the band) has no
        # polarity to refine with: the next frame searches again
        measured = all(line is not None for line in lines)
        return Aperture(quad, predicted, side_sign if measured else None, level, False)

    def _band_widths(self, outer_u: np.ndarray, predicted: np.ndarray) -> np.ndarray | None:
        """Predicted band width (4,) of each side, px, or None when no band fits the quad.

        Each outer side's line to the middle of the predicted aperture side; None when a width
        is not finite, under twice ``_BAND_PROBE_PX`` or over ``max_band_fraction`` of the
        shortest outer side.
        """
        outer_lines = _side_lines_through(outer_u)
        mid = 0.5 * (predicted + predicted[_NEXT])
        band = np.abs(outer_lines[:, 0] * mid[:, 0] + outer_lines[:, 1] * mid[:, 1]
                      + outer_lines[:, 2])
        sides = np.linalg.norm(outer_u - outer_u[_NEXT], axis=1)
        if not np.all(np.isfinite(band)) or band.min() < 2 * _BAND_PROBE_PX \
                or band.max() > self.config.max_band_fraction * float(sides.min()):
            return None
        return band

    def _aperture_from_track(self, gray: np.ndarray, camera: CameraModel, outer_u: np.ndarray,
                             predicted: np.ndarray, threshold: float, last: Aperture
                             ) -> Aperture | None:
        """Return the aperture refined once from its predicted quad, or None (then search).

        The refine pass of :meth:`_search_aperture` (refine range, the band lying outwards)
        from ``predicted`` (where this frame's outer quad and the band's proportions put the
        aperture: its samples, so its noise, do not depend on earlier frames) with the
        polarity and band level of its last search (``last``): every side must be found,
        within ``max_band_deviation`` band widths of the predicted side, and the quad within
        ``refine_half_width_px / SINGLE_PASS_MARGIN`` of it. A room beyond the window that
        turned from lighter to darker, a band whose level moved (exposure), a post: the
        aperture is searched instead.
        """
        cfg = self.config
        band = self._band_widths(outer_u, predicted)
        if band is None:
            return None
        lines, _ = self._fit_lines(gray, camera, predicted, cfg.refine_half_width_px,
                                   last.sign, threshold, band_level=last.level)
        for line, pred, p, dev in zip(lines, _side_lines_through(predicted), _sides(predicted),
                                      cfg.max_band_deviation * band):
            if line is None or _near_or_none(line, pred, p, dev) is None:
                return None
        quad = _intersect_consecutive(lines)
        if quad is None or _largest_distance(quad, predicted) \
                > cfg.refine_half_width_px / SINGLE_PASS_MARGIN:
            return None
        return Aperture(quad, predicted, last.sign, last.level, True)

    def _step_positions(self, grad: np.ndarray, offsets: np.ndarray, peak: np.ndarray,
                        threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel step offsets: centroid of the positive gradient around ``peak``.

        Gradient sample j sits between profile samples j and j+1. The centroid window is
        +-_CENTROID_HALF_WIDTH steps, widened while the gradient stays above
        _EDGE_RUN_FRACTION of the peak's (a motion-blurred edge is a ramp several px long:
        its whole ramp is weighed, not its start). Valid: the summed step >= ``threshold``.
        Returns (offset, valid).
        """
        half = _MAX_EDGE_HALF_WIDTH
        window = np.arange(-half, half + 1)
        n, m = grad.shape
        # the positive gradient, 0 beyond the profile's ends: padded, one gather
        padded = np.zeros((n, m + 2 * half))
        np.maximum(grad, 0.0, out=padded[:, half:half + m])
        raw = peak[:, None] + window[None, :]
        g = padded[np.arange(n)[:, None], raw + half]
        run = g >= _EDGE_RUN_FRACTION * g[:, half:half + 1]
        use = np.concatenate([np.logical_and.accumulate(run[:, half::-1], axis=1)[:, :0:-1],
                              np.logical_and.accumulate(run[:, half:], axis=1)], axis=1)
        use[:, half - _CENTROID_HALF_WIDTH:half + _CENTROID_HALF_WIDTH + 1] = True
        g = g * use
        step = g.sum(axis=1)
        middle = offsets[np.clip(raw, 0, m - 1)] + 0.5 * _PROFILE_STEP_PX   # of each step
        pos = (g * middle).sum(axis=1) / np.maximum(step, 1e-9)
        ok = (step >= threshold) & (peak > 0) & (peak < m - 1)
        return pos, ok


def _steps_into_band(profile: np.ndarray, band_side: int, level: np.ndarray,
                     margin: float) -> np.ndarray:
    """Mask (n, m - 1) of the steps between profile samples j, j+1 that lead into the band.

    ``band_side`` +1: the band lies inwards of the step (samples j+1 ...), -1: outwards
    (... j). The step leads into the band when a sample within ``_BAND_REACH_PX`` on that side
    is within ``margin`` grey levels of the band's ``level`` (n,).
    """
    reach = max(1, int(round(_BAND_REACH_PX / _PROFILE_STEP_PX)))
    m = profile.shape[1]
    dev = np.abs(profile - np.asarray(level, dtype=float).reshape(-1, 1))
    # profile sample k sits at padded column k + reach (the end samples repeated beyond)
    padded = np.concatenate([np.repeat(dev[:, :1], reach, axis=1), dev,
                             np.repeat(dev[:, -1:], reach, axis=1)], axis=1)
    # step j: samples j+1 ... j+reach (band inwards) or j-reach+1 ... j (outwards)
    first = reach + 1 if band_side == _RISING else 1
    side_min = padded[:, first:first + m - 1]
    for shift in range(1, reach):
        side_min = np.minimum(side_min, padded[:, first + shift:first + shift + m - 1])
    return side_min <= margin


def _band_departure(profile: np.ndarray, offsets: np.ndarray, band_px: np.ndarray,
                    margin: float, deviation: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Band level and the first departure from it, on profiles inwards from the outer edge.

    ``band_px`` (4,): the predicted band width of each side, px; the profiles (n, m) are the
    sides' in turn, n / 4 each. The level is the median over ``_BAND_LEVEL_SPAN`` of the band
    width (at least from ``_BAND_PROBE_PX``); the departure is the first sample beyond both that
    span and ``(1 - deviation) band_px`` that differs from the level by more than ``margin``.
    Returns (level (n,), its index (n,), 0 where none, sign (n,) of the difference, +1 lighter
    beyond, -1 darker, 0 none).
    """
    band_px = np.asarray(band_px, dtype=float)
    lo = np.maximum(_BAND_PROBE_PX, _BAND_LEVEL_SPAN[0] * band_px)
    hi = np.maximum(lo + 2 * _PROFILE_STEP_PX, _BAND_LEVEL_SPAN[1] * band_px)
    per_side = len(profile) // len(band_px)
    lo, hi = np.repeat(lo, per_side), np.repeat(hi, per_side)
    span = (offsets[None, :] >= lo[:, None]) & (offsets[None, :] <= hi[:, None])
    level = _row_medians(profile, span)
    beyond = offsets[None, :] > np.maximum(hi, (1.0 - deviation) * np.repeat(band_px, per_side)
                                           )[:, None]
    diff = profile - level[:, None]
    away = beyond & (np.abs(diff) > margin)
    crossing = np.where(away.any(axis=1), np.argmax(away, axis=1), 0)
    sign = np.where(crossing > 0, np.sign(diff[np.arange(len(diff)), crossing]), 0.0)
    return level, crossing, sign


def _row_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median (n,) of each row of ``values`` (n, m) over its ``mask``-ed entries (nan: none).

    The middle of the sorted entries, or the mean of the two middle ones, as np.median.
    """
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(values))
    median = (ordered[rows, (count - 1) // 2] + ordered[rows, count // 2]) / 2
    return np.where(count > 0, median, np.nan)


@functools.lru_cache(maxsize=8)
def _side_fractions(n: int) -> np.ndarray:
    """Where the n samples of a side lie, fractions of it from corner i (read-only, cached)."""
    t = np.linspace(_SIDE_MARGIN, 1.0 - _SIDE_MARGIN, n)
    t.flags.writeable = False
    return t


def _near_or_none(line: np.ndarray | None, reference: np.ndarray, ends: np.ndarray,
                  tolerance: float) -> np.ndarray | None:
    """``line`` if both ``ends`` of the reference side lie within ``tolerance`` px of it."""
    if line is None or not np.all(np.isfinite(reference)):
        return line
    distance = np.abs(ends @ line[:2] + line[2]) / max(np.linalg.norm(line[:2]), 1e-12)
    return line if float(distance.max()) <= tolerance else None


def _profiles(gray: np.ndarray, camera: CameraModel, samples_u: np.ndarray,
              inward_u: np.ndarray, offsets: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intensity profiles along the image normal of a straight undistorted edge.

    The samples and the normal are mapped into the distorted image (where the edge is
    curved); returns (profiles (n, m) bilinear, base points (n, 2) and unit normals (n, 2)
    in distorted pixels).
    """
    n, m = len(samples_u), len(offsets)
    # one projection for the samples and their probes (each point on its own: same values)
    both = _distort_px(camera, np.concatenate([samples_u,
                                               samples_u + _NORMAL_PROBE_PX * inward_u]))
    base, probe = both[:n], both[n:]
    normal_d = probe - base
    normal_d /= np.linalg.norm(normal_d, axis=1, keepdims=True)
    tangent = np.column_stack([-normal_d[:, 1], normal_d[:, 0]])
    along = np.asarray(_TANGENT_OFFSETS_PX)
    # x and y maps (n, len(along), m): base + offset normal + along tangent, in float64 and
    # then float32 (remap's map type); one coordinate at a time, without an (..., 2) grid
    map_x, map_y = ((base[:, k, None, None] + offsets[None, None, :] * normal_d[:, k, None, None]
                     + along[None, :, None] * tangent[:, k, None, None])
                    .reshape(n * len(along), m).astype(np.float32) for k in (0, 1))
    profile = cv2.remap(gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # the parallel profiles' mean (an exact integer sum divided once, as ndarray.mean)
    return (profile.reshape(n, len(along), m).sum(axis=1, dtype=float) / len(along),
            base, normal_d)


def _robust_lines(points: np.ndarray, valid: np.ndarray, inlier_px: float,
                  min_inliers: int) -> list[np.ndarray | None]:
    """Robust total-least-squares lines (nx, ny, c), n.x + c = 0, |n| = 1, or None per set.

    ``points`` (k, n, 2), ``valid`` (k, n): k point sets (undistorted px), each fitted to its
    valid points. Huber fit (cv2.fitLine) of each set, then the points farther than
    ``inlier_px`` from it are dropped and the line refitted by orthogonal least squares, the
    k sets at once: n is the minor axis of the inliers' 2x2 scatter matrix (closed form, the
    last singular vector of the centred points). None: fewer than ``max(2, min_inliers)``
    points or inliers. The sign of n is arbitrary.
    """
    least = max(2, min_inliers)
    k = len(points)
    huber = np.full((k, 3), np.nan)
    points_f32 = points.astype(np.float32)                      # fitLine's input type
    for i, n_valid in enumerate(valid.sum(axis=1).tolist()):
        if n_valid >= least:
            vx, vy, x0, y0 = cv2.fitLine(points_f32[i][valid[i]], cv2.DIST_HUBER, 0, 0.01,
                                         0.01).reshape(-1)
            vx, vy, x0, y0 = float(vx), float(vy), float(x0), float(y0)
            huber[i] = -vy, vx, -(-vy * x0 + vx * y0)
    with np.errstate(invalid='ignore'):
        inliers = valid & (np.abs(points[..., 0] * huber[:, None, 0]
                                  + points[..., 1] * huber[:, None, 1] + huber[:, None, 2])
                           <= inlier_px)
    count = inliers.sum(axis=1)
    fitted = count >= least
    if not fitted.any():
        return [None] * k
    weight = inliers[..., None]
    centre = np.where(weight, points, 0.0).sum(axis=1) / np.maximum(count, 1)[:, None]
    d = np.where(weight, points - centre[:, None, :], 0.0)
    sxx = (d[..., 0] * d[..., 0]).sum(axis=1)
    syy = (d[..., 1] * d[..., 1]).sum(axis=1)
    sxy = (d[..., 0] * d[..., 1]).sum(axis=1)
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)       # the major axis' direction
    normal = np.column_stack([-np.sin(theta), np.cos(theta)])
    c = -(normal[:, 0] * centre[:, 0] + normal[:, 1] * centre[:, 1])
    return [np.array([normal[i, 0], normal[i, 1], c[i]]) if fitted[i] else None
            for i in range(k)]
