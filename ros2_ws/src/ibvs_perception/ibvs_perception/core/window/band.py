"""The window's band and aperture as one known planar rectangle pair.

The aperture (``window_width_m`` x ``window_height_m``) lies inside the dark frame band
(``frame_band_m`` wide), so a view of either rectangle predicts the other by a homography.
"""
from __future__ import annotations

import cv2
import numpy as np

from ibvs_common.core.camera import CameraModel

from .config import WindowDetectorConfig


class BandProportions:
    """Homographies between the band's outer rectangle, the aperture and their image quads."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config

    def homography(self, outer_u: np.ndarray) -> np.ndarray:
        """Homography (3, 3): band plane (m, origin at the band's outer top-left) -> undist. px."""
        cfg = self.config
        w = cfg.window_width_m + 2 * cfg.frame_band_m
        h = cfg.window_height_m + 2 * cfg.frame_band_m
        rect = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]], np.float32)
        return cv2.getPerspectiveTransform(rect, outer_u.astype(np.float32))

    def predicted_inner(self, outer_u: np.ndarray) -> np.ndarray:
        """Aperture quad (4, 2) undistorted px predicted from the outer quad and the proportions.

        The band and the aperture are one planar rectangle pair: the homography of the outer
        rectangle (``window_*_m + 2 frame_band_m``) onto the outer quad maps the aperture.
        """
        cfg = self.config
        b = cfg.frame_band_m
        w, h = cfg.window_width_m + b, cfg.window_height_m + b
        inner = np.array([[[b, b], [w, b], [w, h], [b, h]]], np.float32)
        return cv2.perspectiveTransform(inner, self.homography(outer_u))[0].astype(float)

    def predicted_outer(self, inner_u: np.ndarray) -> np.ndarray:
        """Outer band quad (4, 2) predicted from an aperture quad and the band's proportions.

        The inverse of :meth:`predicted_inner`: the homography of the aperture rectangle
        (``window_*_m``, at ``frame_band_m`` from the outer one) onto the aperture quad maps the
        band's outer rectangle.
        """
        cfg = self.config
        b = cfg.frame_band_m
        w, h = cfg.window_width_m + b, cfg.window_height_m + b
        inner = np.array([[b, b], [w, b], [w, h], [b, h]], np.float32)
        outer = np.array([[[0.0, 0.0], [w + b, 0.0], [w + b, h + b], [0.0, h + b]]],
                         np.float32)
        H = cv2.getPerspectiveTransform(inner, inner_u.astype(np.float32))
        return cv2.perspectiveTransform(outer, H)[0].astype(float)

    def shape_error(self, camera: CameraModel, outer_u: np.ndarray) -> float:
        """How far the outer quad is from a perspective view of the band's rectangle.

        With H = K [s r1, s r2, s t] (band plane metres -> undistorted px), K^-1 H's first two
        columns are orthogonal and of equal norm for a true view: returns the larger of |cos|
        of their angle and their relative norm difference (0 for an exact view).
        """
        cols = np.linalg.solve(camera.K, self.homography(outer_u))[:, :2]
        n1, n2 = np.linalg.norm(cols, axis=0)
        if min(n1, n2) <= 0.0:
            return float('inf')
        return max(abs(float(cols[:, 0] @ cols[:, 1])) / (n1 * n2), abs(n1 / n2 - 1.0))
