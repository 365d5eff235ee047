"""Geometry of quads and lines shared by the window detector's stages.

Quads are (4, 2) arrays ordered TL, TR, BR, BL (clockwise in the image); side i joins corner
i and i+1; lines are (nx, ny, c) with n.x + c = 0. "Undistorted px" are ideal pinhole pixels
``K [x/z, y/z, 1]`` of the camera's own K, where straight 3-D edges stay straight.
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.camera import CameraModel
from ibvs_common.core.features import edge_normals

N_CORNERS = 4
#: index of corner i+1 and of corner i-1 (cyclic; np.roll costs ~10 us on 4 rows)
_NEXT = np.array([1, 2, 3, 0])
_PREVIOUS = np.array([3, 0, 1, 2])
#: fraction of each side left out at both ends (near the corners the other band interferes)
_SIDE_MARGIN = 0.1
#: |sin| of the angle between two edges below which their intersection is refused
_MIN_SIN_EDGE_ANGLE = 0.2
#: |p_i x p_(i+1)| below which an edge normal is degenerate (features.edge_normals raises)
_MIN_EDGE_NORMAL = 1e-9


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


def _side_lines_through(quad: np.ndarray) -> np.ndarray:
    """Lines (4, 3) (nx, ny, c) through the sides of a quad, |n| = 1 (nan for a null side).

    Side i joins corner i and i+1; the line is the cross product (a, 1) x (b, 1) written out.
    """
    a, b = quad, quad[_NEXT]
    lines = np.column_stack([a[:, 1] - b[:, 1], b[:, 0] - a[:, 0],
                             a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])
    with np.errstate(invalid='ignore', divide='ignore'):
        return lines / np.sqrt(lines[:, 0] * lines[:, 0] + lines[:, 1] * lines[:, 1])[:, None]


def _sides(quad: np.ndarray) -> list[np.ndarray]:
    """End points (2, 2) of the 4 sides of a quad: side i joins corner i and i+1."""
    return [np.array([quad[k], quad[(k + 1) % N_CORNERS]]) for k in range(N_CORNERS)]


def _largest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance (px) between corresponding corners of two quads (4, 2)."""
    return float(np.max(np.hypot(*(a - b).T)))


def _quad_area(quad: np.ndarray) -> float:
    """Area of a simple polygon (shoelace)."""
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _undistorted_px(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels -> ideal pinhole pixels K [x/z, y/z, 1] (same K, no distortion)."""
    xy = camera.pixels_to_normalized(uv)
    return xy * np.array([camera.K[0, 0], camera.K[1, 1]]) + camera.K[:2, 2]


def _distort_px(camera: CameraModel, uv_u: np.ndarray) -> np.ndarray:
    """Ideal pinhole pixels (N, 2) -> distorted pixels (N, 2) (``normalized_to_pixels``)."""
    uv_u = np.asarray(uv_u, dtype=float)
    K = camera.K
    return camera.normalized_to_pixels((uv_u - K[:2, 2]) / np.array([K[0, 0], K[1, 1]]))


def _edge_normals(p: np.ndarray) -> np.ndarray:
    """Edge normals (4, 3) h_i = unit(p_i x p_(i+1)) of corner bearings p (4, 3).

    :func:`ibvs_common.core.features.edge_normals` (the same values) for the 4 edges at once;
    it is called instead for a degenerate edge, and raises.
    """
    q = p[_NEXT]
    h = np.column_stack([p[:, 1] * q[:, 2] - p[:, 2] * q[:, 1],
                         p[:, 2] * q[:, 0] - p[:, 0] * q[:, 2],
                         p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]])
    norm = np.linalg.norm(h, axis=1)
    if np.any(~(norm >= _MIN_EDGE_NORMAL)):
        return edge_normals(p)
    return h / norm[:, None]


def _intersect_consecutive(lines: list[np.ndarray] | np.ndarray) -> np.ndarray | None:
    """Corners (4, 2): corner i = line i-1 x line i (homogeneous cross product), or None.

    None when two consecutive lines meet at |sin| < _MIN_SIN_EDGE_ANGLE (unit normals).
    """
    l2 = np.asarray(lines, dtype=float).reshape(N_CORNERS, 3)
    l1 = l2[_PREVIOUS]
    cross_z = l1[:, 0] * l2[:, 1] - l1[:, 1] * l2[:, 0]
    if np.any(np.abs(cross_z) < _MIN_SIN_EDGE_ANGLE):
        return None
    x = l1[:, 1] * l2[:, 2] - l1[:, 2] * l2[:, 1]
    y = l1[:, 2] * l2[:, 0] - l1[:, 0] * l2[:, 2]
    return np.column_stack([x / cross_z, y / cross_z])
