"""Landing-pad detection: ArUco markers grouped by the pad layout, marker centres as bearings.

The landmarks of the paper's eq:q_t are the marker *centres* of every complete group (4 of 4
markers seen). A marker centre is the intersection of its diagonals in undistorted
coordinates (the image of the 3-D centre under a perspective map, unlike the corner mean),
then turned into a unit bearing in the optical frame (x right, y down, z forward).
Each complete group is centred on the pad, so using all complete groups keeps the centroid
direction consistent when groups appear or disappear during the descent.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ibvs_control.core.camera import CameraModel
from ibvs_control.core.config import PadLayout

MARKER_CORNERS = 4
#: smallest |cross| of the two diagonals (normalised coordinates) accepted as a centre
_MIN_DIAGONAL_CROSS = 1e-12


class PadConfigError(ValueError):
    """The pad layout names an ArUco dictionary that OpenCV does not know."""


@dataclass(frozen=True)
class PadDetectorConfig:
    """Tuning of the ArUco detector (OpenCV DetectorParameters names, pixels)."""

    adaptive_thresh_win_size_min: int = 21    # px (one window: min = max, fastest)
    adaptive_thresh_win_size_max: int = 21    # px
    adaptive_thresh_win_size_step: int = 10   # px
    adaptive_thresh_constant: float = 30.0    # grey levels below the local mean = black
    min_marker_perimeter_rate: float = 0.04   # marker perimeter / max image side
    corner_refinement_win_size: int = 5       # px, sub-pixel corner refinement window
    corner_refinement_max_iterations: int = 30
    corner_refinement_min_accuracy: float = 0.01  # px


@dataclass(frozen=True)
class PadDetection:
    """Landmarks of all complete groups: ordered group by group (largest first), ids order."""

    bearings_C: np.ndarray          # (N, 3) unit bearings of the marker centres, N = 4 k
    group_names: tuple[str, ...]    # the complete groups used, same order
    centres_px: np.ndarray          # (N, 2) distorted pixels of the centres (debug)


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
    h = np.column_stack([corners_xy, np.ones(MARKER_CORNERS)])
    centre = np.cross(np.cross(h[0], h[2]), np.cross(h[1], h[3]))
    if abs(centre[2]) < _MIN_DIAGONAL_CROSS:
        return None
    return centre[:2] / centre[2]


class PadDetector:
    """Detect the pad's ArUco markers and return the centres of complete groups."""

    def __init__(self, layout: PadLayout, config: PadDetectorConfig) -> None:
        self.layout = layout
        params = cv2.aruco.DetectorParameters()
        params.adaptiveThreshWinSizeMin = config.adaptive_thresh_win_size_min
        params.adaptiveThreshWinSizeMax = config.adaptive_thresh_win_size_max
        params.adaptiveThreshWinSizeStep = config.adaptive_thresh_win_size_step
        params.adaptiveThreshConstant = config.adaptive_thresh_constant
        params.minMarkerPerimeterRate = config.min_marker_perimeter_rate
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = config.corner_refinement_win_size
        params.cornerRefinementMaxIterations = config.corner_refinement_max_iterations
        params.cornerRefinementMinAccuracy = config.corner_refinement_min_accuracy
        self._detector = cv2.aruco.ArucoDetector(aruco_dictionary(layout.dictionary), params)

    def detect_markers(self, gray: np.ndarray) -> dict[int, np.ndarray]:
        """Marker id -> corners (4, 2) in distorted px; ids seen more than once are dropped."""
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None:
            return {}
        found: dict[int, np.ndarray] = {}
        duplicated = set()
        for c, i in zip(corners, ids.reshape(-1)):
            i = int(i)
            if i in found:
                duplicated.add(i)
            found[i] = np.asarray(c, dtype=float).reshape(MARKER_CORNERS, 2)
        return {i: c for i, c in found.items() if i not in duplicated}

    def process(self, gray: np.ndarray, camera: CameraModel) -> PadDetection:
        """Landmarks of every complete group (empty arrays when none is complete)."""
        markers = self.detect_markers(gray)
        bearings, names, centres = [], [], []
        for group in self.layout.groups:
            if not all(i in markers for i in group.ids):
                continue
            group_b = []
            for marker_id in group.ids:
                xy = camera.pixels_to_normalized(markers[marker_id])
                centre = marker_centre_normalized(xy)
                if centre is None or not np.all(np.isfinite(centre)):
                    break
                group_b.append([centre[0], centre[1], 1.0])
            else:
                names.append(group.name)
                bearings.extend(group_b)
        if not bearings:
            return PadDetection(np.zeros((0, 3)), (), np.zeros((0, 2)))
        b = np.asarray(bearings)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        centres, _ = camera.bearings_to_pixels(b)
        return PadDetection(b, tuple(names), centres)
