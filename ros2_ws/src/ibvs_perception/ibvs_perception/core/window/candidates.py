"""Whole-image search for window candidates: dark rings whose outline is a quadrilateral.

An adaptive dark mask of a down-scaled image, its contours with their holes, and for each dark
component the outer quads it may be the band of: its outer boundary's, or those the band's
proportions predict around its quadrilateral holes (the aperture, when dark texture touching
the band bends the outer boundary), and for a dark component without a hole, the quad of its
convex hull when the hull is mostly not dark: an open ring, the band with one side covered by
something bright (a lamp, a reflection, an arm), whose covered stretch the edge fits leave out.
"""
from __future__ import annotations

from collections.abc import Iterator
import itertools

import cv2
import numpy as np

from ibvs_common.core.camera import CameraModel

from .band import BandProportions
from .config import WindowDetectorConfig
from .geometry import (_intersect_consecutive, _quad_area, _SIDE_MARGIN, _undistorted_px,
                       N_CORNERS, order_corners_clockwise)

#: binary value of "dark" pixels after the inverted adaptive threshold
_DARK = 255
#: the dark offset below the local mean is at most this fraction of the mean's depth above the
#: local minimum: in a window mostly dark (the band beside a black brick and a dim aperture)
#: the contrast's fraction can exceed it and leave even the band's pixels "not dark", a gap
#: that opens the ring
_MEAN_DEPTH_FRACTION = 0.5


class CandidateSearch:
    """Outer band quads (undistorted px) of the dark rings of an image, from scratch."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config
        self.band = BandProportions(config)

    def rings(self, gray: np.ndarray, camera: CameraModel) -> list[Iterator[np.ndarray]]:
        """Candidate outer quads (4, 2; undistorted px, TL, TR, BR, BL) per dark component.

        A candidate is the outer boundary of a dark connected component that is a convex
        quadrilateral of plausible size and aspect ratio, and whose holes (the aperture,
        possibly cut by dark texture seen through it) cover at least ``min_holes_fraction``
        of it: a filled dark square is not a ring. Dark texture touching the band (a dark
        brick) joins its component and bends the outer boundary out of shape, while the hole
        (the aperture) stays a quadrilateral: each large convex quadrilateral hole of a dark
        component also gives a candidate, the outer quad that the band's known proportions
        predict around it (:meth:`BandProportions.predicted_outer`).

        One lazy iterator per component: its outer boundary's quad first (if any), then its
        holes', computed only when asked for. The detector stops at a component's first
        candidate that refines into a window (its outer boundary's when intact), so an intact
        band costs no more than without the holes.
        """
        cfg = self.config
        scale = cfg.detection_scale
        small = gray if scale >= 1.0 else cv2.resize(gray, None, fx=scale, fy=scale,
                                                     interpolation=cv2.INTER_AREA)
        binary = _dark_mask(small, cfg.threshold_block_px, cfg.threshold_contrast_fraction,
                            cfg.threshold_offset)
        image_area = float(small.shape[0] * small.shape[1])
        binary = _without_small_components(binary, cfg.min_area_fraction * image_area)
        contours, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        if hierarchy is None:
            return []
        hierarchy = hierarchy[0]
        # a contour keeps every boundary pixel: one shorter than the perimeter of the smallest
        # admissible square cannot pass the area check (noise makes thousands of such specks)
        min_points = 4.0 * np.sqrt(cfg.min_area_fraction * image_area)
        # the smallest admissible aperture: min_hole_area_ratio of the smallest outer quad
        min_hole_area = cfg.min_hole_area_ratio * cfg.min_area_fraction * image_area
        min_hole_points = 4.0 * np.sqrt(min_hole_area)
        rings = []
        for i, (_, _, child, parent) in enumerate(hierarchy):
            if parent != -1:
                continue
            # last, for any large component: the hull of an open ring (lazy, as the rest)
            open_ring = self._open_ring_quads(contours[i], camera, scale, image_area) \
                if len(contours[i]) >= min_points else iter(())
            if child == -1 or len(contours[i]) < min_hole_points:
                rings.append(open_ring)
                continue
            outer = None
            if len(contours[i]) >= min_points:
                outer = self._ring_quad_u(contours, hierarchy, i, camera, scale, image_area)
            holes = []
            while child != -1:
                if len(contours[child]) >= min_hole_points \
                        and cv2.contourArea(contours[child]) >= min_hole_area:
                    holes.append(contours[child])
                child = hierarchy[child][0]
            rings.append(itertools.chain(
                () if outer is None else (outer,),
                self._hole_quads(holes, camera, scale, image_area / (scale * scale)),
                open_ring))
        return rings

    def _open_ring_quads(self, contour: np.ndarray, camera: CameraModel, scale: float,
                         image_area: float) -> Iterator[np.ndarray]:
        """Yield the open-ring quad of a component (:meth:`_open_ring_quad_u`), if any."""
        quad = self._open_ring_quad_u(contour, camera, scale, image_area)
        if quad is not None:
            yield quad

    def _open_ring_quad_u(self, contour: np.ndarray, camera: CameraModel, scale: float,
                          image_area: float) -> np.ndarray | None:
        """Outer quad (undistorted px) of a dark component's convex hull, or None.

        A band with one side cut by something bright is a dark "U": no hole, but its convex
        hull is the band's outer quad (while the cut leaves the side's two ends) and mostly
        not dark, as a ring's outline is mostly holes. The hull's 4 vertices (approxPolyDP)
        give the candidate; the area, hollowness (``min_holes_fraction``) and aspect checks
        of a ring apply. The edge refiner then fits each side on the stretches it finds, and
        the band's proportions give the aperture: what is not a band fails there.
        """
        cfg = self.config
        hull = cv2.convexHull(contour)
        hull_area = cv2.contourArea(hull)
        if not cfg.min_area_fraction * image_area <= hull_area \
                <= cfg.max_area_fraction * image_area:
            return None
        if hull_area - cv2.contourArea(contour) < cfg.min_holes_fraction * hull_area:
            return None
        approx = cv2.approxPolyDP(hull, cfg.approx_tolerance * cv2.arcLength(hull, True), True)
        if len(approx) != N_CORNERS or not cv2.isContourConvex(approx):
            return None
        corners = _undistorted_px(camera, (approx.reshape(N_CORNERS, 2) + 0.5) / scale - 0.5)
        quad = order_corners_clockwise(corners)
        return quad if self._plausible(quad, image_area / (scale * scale)) else None

    def _hole_quads(self, holes: list, camera: CameraModel, scale: float,
                    image_area: float) -> Iterator[np.ndarray]:
        """Yield the outer quads (undistorted px) predicted around quadrilateral holes.

        ``image_area``: full-resolution px^2, for the area check of the predicted quad.
        """
        for hole in holes:
            inner = self._contour_quad_u(hole, camera, scale)
            if inner is not None:
                quad = self.band.predicted_outer(inner)
                if self._plausible(quad, image_area):
                    yield quad

    def _ring_quad_u(self, contours, hierarchy, i: int, camera: CameraModel, scale: float,
                     image_area: float) -> np.ndarray | None:
        """Outer quad (undistorted px) of the outer boundary ``i`` of a dark ring, or None.

        The area (``image_area`` at detection scale), holes and aspect-ratio checks of
        :meth:`rings` on the boundary and its quad.
        """
        cfg = self.config
        outer = contours[i]
        outer_area = cv2.contourArea(outer)
        if not cfg.min_area_fraction * image_area <= outer_area \
                <= cfg.max_area_fraction * image_area:
            return None
        if _children_area(contours, hierarchy, hierarchy[i][2]) \
                < cfg.min_holes_fraction * outer_area:
            return None
        quad = self._contour_quad_u(outer, camera, scale)
        if quad is None or not self._aspect_ok(quad):
            return None
        return quad

    def _aspect_ok(self, quad: np.ndarray) -> bool:
        """Whether a quad's width / height lies in [min_aspect_ratio, max_aspect_ratio]."""
        cfg = self.config
        width = 0.5 * (np.linalg.norm(quad[1] - quad[0]) + np.linalg.norm(quad[2] - quad[3]))
        height = 0.5 * (np.linalg.norm(quad[3] - quad[0]) + np.linalg.norm(quad[2] - quad[1]))
        return bool(height > 0 and cfg.min_aspect_ratio <= width / height
                    <= cfg.max_aspect_ratio)

    def _plausible(self, quad: np.ndarray, image_area: float) -> bool:
        """Whether a predicted outer quad (px, ``image_area`` at that scale) may be a band.

        Finite, convex, of the outer boundary's area range and aspect ratio.
        """
        cfg = self.config
        if not np.all(np.isfinite(quad)) or not cv2.isContourConvex(quad.astype(np.float32)):
            return False
        area = _quad_area(quad)
        return bool(cfg.min_area_fraction * image_area <= area
                    <= cfg.max_area_fraction * image_area) and self._aspect_ok(quad)

    def _contour_quad_u(self, contour: np.ndarray, camera: CameraModel,
                        scale: float) -> np.ndarray | None:
        """Return a contour's quad in undistorted px from robust lines along its 4 sides.

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


def _dark_mask(small: np.ndarray, block: int, fraction: float, floor: float) -> np.ndarray:
    """Mask (_DARK / 0) of the pixels darker than their block's mean by a relative offset.

    The offset is ``fraction`` of the local contrast (max - min over the ``block`` x ``block``
    window), at least ``floor`` grey levels: it follows the exposure (gain) instead of a fixed
    grey level, and the band stays dark beside a bright aperture or a dark one. It is at most
    ``_MEAN_DEPTH_FRACTION`` of (mean - min) over the window, so that in a mostly dark window
    (a black brick, the band, a dim room beyond) the band stays below the threshold.
    """
    mean = cv2.blur(small.astype(np.float32), (block, block), borderType=cv2.BORDER_REPLICATE)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (block, block))
    low = cv2.erode(small, kernel)
    contrast = cv2.subtract(cv2.dilate(small, kernel), low)
    offset = np.maximum(np.minimum(fraction * contrast.astype(np.float32),
                                   _MEAN_DEPTH_FRACTION * (mean - low)), floor)
    return np.where(small <= mean - offset, _DARK, 0).astype(np.uint8)


def _without_small_components(binary: np.ndarray, min_area: float) -> np.ndarray:
    """Return the mask (_DARK / 0) without the dark components too small for a candidate.

    A component whose bounding box spans w x h pixels has an outer contour (through pixel
    centres) of area <= (w - 1)(h - 1): below ``min_area`` (px^2, this image's scale) it fails
    the area check. Texture and noise make hundreds of such specks, and ``findContours`` costs
    ~5 us per contour it returns. Components are 8-connected as the contours' dark regions, so
    every remaining contour, its holes and their order (raster order of the start points) are
    the same as on the whole mask.
    """
    _, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    keep = (stats[:, cv2.CC_STAT_WIDTH] - 1) * (stats[:, cv2.CC_STAT_HEIGHT] - 1) >= min_area
    keep[0] = False                                             # the background
    return np.where(keep, _DARK, 0).astype(np.uint8)[labels]


def _children_area(contours, hierarchy, child: int) -> float:
    """Total area of a contour's holes (its children in a RETR_CCOMP hierarchy)."""
    total = 0.0
    while child != -1:
        total += cv2.contourArea(contours[child])
        child = hierarchy[child][0]
    return total
