"""Calibrated camera model: pixel <-> undistorted unit bearing in the optical frame.

Implements the paper's eq:barpi, ``p_bar = A^-1 [X, Y, 1]^T`` followed by normalisation, with
the lens distortion of a ROS CameraInfo undone first. Two distortion models, as CameraInfo names
them: ``plumb_bob`` (radial-tangential k1 k2 p1 p2 k3, also ``rational_polynomial`` with 8
coefficients) and ``equidistant`` (fisheye k1..k4). Pixel coordinates follow the ROS/OpenCV
convention: (u, v) with (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import cv2
import numpy as np

PLUMB_BOB = 'plumb_bob'
RATIONAL_POLYNOMIAL = 'rational_polynomial'
EQUIDISTANT = 'equidistant'
SUPPORTED_MODELS = (PLUMB_BOB, RATIONAL_POLYNOMIAL, EQUIDISTANT)

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


class CameraModelError(ValueError):
    """A CameraInfo that cannot describe a usable camera (degenerate K, bad D, bad size)."""


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera: K (3x3, px), distortion D and its model, image size (px)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = PLUMB_BOB

    @classmethod
    def from_camera_info(cls, width: int, height: int, k: 'list[float] | np.ndarray',
                         d: 'list[float] | np.ndarray',
                         distortion_model: str) -> 'CameraModel':
        """Build and validate from CameraInfo fields (k row-major 9, d, distortion_model).

        Raises CameraModelError with a readable reason when the fields are unusable.
        """
        K = np.asarray(k, dtype=float).reshape(-1)
        D = np.asarray(d, dtype=float).reshape(-1)
        if width <= 0 or height <= 0:
            raise CameraModelError(f'image size {width}x{height} is not positive')
        if K.size != 9 or not np.all(np.isfinite(K)):
            raise CameraModelError('K must hold 9 finite numbers')
        K = K.reshape(3, 3)
        if K[0, 0] <= 0.0 or K[1, 1] <= 0.0 or abs(K[2, 2] - 1.0) > 1e-9 \
                or np.any(K[2, :2] != 0.0) or K[1, 0] != 0.0:
            raise CameraModelError(f'K is degenerate or not upper-triangular: {K.tolist()}')
        if distortion_model not in SUPPORTED_MODELS:
            raise CameraModelError(
                f'distortion model {distortion_model!r} not supported {SUPPORTED_MODELS}')
        if not np.all(np.isfinite(D)):
            raise CameraModelError('D holds a non-finite value')
        if distortion_model == EQUIDISTANT and D.size != 4:
            raise CameraModelError(f'equidistant needs 4 coefficients, got {D.size}')
        if distortion_model == PLUMB_BOB and D.size not in (0, 4, 5):
            raise CameraModelError(f'plumb_bob needs 5 coefficients, got {D.size}')
        if distortion_model == RATIONAL_POLYNOMIAL and D.size != 8:
            raise CameraModelError(f'rational_polynomial needs 8 coefficients, got {D.size}')
        if D.size == 0:
            D = np.zeros(5)
        return cls(int(width), int(height), K, D, distortion_model)

    @property
    def is_fisheye(self) -> bool:
        """True for the equidistant (fisheye) model."""
        return self.distortion_model == EQUIDISTANT

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistort pixels (N, 2) to normalised perspective coordinates (x/z, y/z), (N, 2)."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        if self.is_fisheye:
            out = cv2.fisheye.undistortPoints(pts, self.K, self.D,
                                              criteria=_UNDISTORT_CRITERIA)
        else:
            out = cv2.undistortPointsIter(pts, self.K, self.D, None, None, _UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def pixels_to_bearings(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit bearings (N, 3) in the optical frame (paper eq:barpi).

        Bearings point from the optical centre to the scene (z > 0 in front of the lens).
        """
        xy = self.pixels_to_normalized(uv)
        b = np.column_stack([xy, np.ones(len(xy))])
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def bearings_to_pixels(self, bearings_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project bearings or points (N, 3) of the optical frame to distorted pixels.

        Returns (uv (N, 2), valid (N,)) where valid means in front of the lens (z > 0) and
        inside the image. Points behind the lens get NaN pixels.
        """
        P = np.asarray(bearings_C, dtype=np.float64).reshape(-1, 3)
        uv = np.full((len(P), 2), np.nan)
        front = P[:, 2] > 1e-9
        if np.any(front):
            Pf = P[front]
            if self.is_fisheye or np.size(self.D) > 8:
                zero = np.zeros(3)
                project = cv2.fisheye.projectPoints if self.is_fisheye else cv2.projectPoints
                img, _ = project(Pf.reshape(-1, 1, 3), zero, zero, self.K, self.D)
                uv[front] = img.reshape(-1, 2)
            else:
                inv_z = 1.0 / Pf[:, 2]              # as projectPoints: x * (1 / z)
                uv[front] = self._distort(Pf[:, 0] * inv_z, Pf[:, 1] * inv_z)
        inside = front & (uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5)
        return uv, inside

    def border_margin_px(self, bearings_C: np.ndarray) -> float:
        """Return how far (px) the projected points keep from the image border, the closest one.

        The pixel grid spans -0.5 ... width - 0.5 (and height); the margin of a pixel (u, v)
        is min(u + 0.5, width - 0.5 - u, v + 0.5, height - 0.5 - v): negative outside the
        image, -inf for a point behind the lens or no point at all.
        """
        uv, _ = self.bearings_to_pixels(bearings_C)
        if len(uv) == 0 or not np.all(np.isfinite(uv)):
            return -math.inf
        u, v = uv[:, 0], uv[:, 1]
        return float(min(np.min(u + 0.5), np.min(self.width - 0.5 - u),
                         np.min(v + 0.5), np.min(self.height - 0.5 - v)))

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Normalised perspective coordinates (x/z, y/z), (N, 2) -> distorted pixels (N, 2).

        The inverse of :meth:`pixels_to_normalized`; the same pixels, to the last bit, as
        :meth:`bearings_to_pixels` of the points (x, y, 1).
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.is_fisheye or np.size(self.D) > 8:
            uv, _ = self.bearings_to_pixels(np.column_stack([xy, np.ones(len(xy))]))
            return uv
        return self._distort(xy[:, 0], xy[:, 1])

    def _distort(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) of normalised coordinates: plumb_bob / rational_polynomial.

        OpenCV's ``projectPoints`` model (k1 k2 p1 p2 k3 k4 k5 k6, as its C code: radial
        ``1 + k1 r^2 + k2 r^4 + k3 r^6`` over ``1 + k4 r^2 + k5 r^4 + k6 r^6``, tangential
        ``2 p1 x y + p2 (r^2 + 2 x^2)`` and ``p1 (r^2 + 2 y^2) + 2 p2 x y``, then
        ``u = fx x_d + cx``, ``v = fy y_d + cy``; the skew K[0, 1] is not used, as there)
        written out: the same double operations in the same order, so the same pixels to the
        last bit (a zero coefficient is skipped: its term is an exact +0 or a factor of
        exactly 1). ``projectPoints`` costs ~60 us a call even for 4 points: it always
        computes the Jacobians.
        """
        D = np.asarray(self.D, dtype=float).reshape(-1)
        D = np.concatenate([D, np.zeros(8 - D.size)])
        k1, k2, p1, p2, k3, k4, k5, k6 = D.tolist()
        K = self.K
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        r2 = x * x + y * y
        r4 = r2 * r2
        radial = 1 + k1 * r2 + k2 * r4 + k3 * (r4 * r2)
        xd, yd = x * radial, y * radial
        if k4 or k5 or k6:
            inverse = 1. / (1 + k4 * r2 + k5 * r4 + k6 * (r4 * r2))
            xd, yd = xd * inverse, yd * inverse
        if p1 or p2:
            a1 = 2 * x * y
            xd = xd + p1 * a1 + p2 * (r2 + 2 * x * x)
            yd = yd + p1 * (r2 + 2 * y * y) + p2 * a1
        return np.column_stack([xd * fx + cx, yd * fy + cy])
