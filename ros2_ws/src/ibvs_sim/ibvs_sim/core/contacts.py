"""Clearance of the vehicle's collision envelope to docs/spec.md section 2's world ({I}, m).

The envelope is a vertical cylinder (radius r = rotor tips, height h) centred on the body origin;
its tilt is ignored (the attitudes of this task stay within ~20 deg, where the tilted rotor disc
moves its rim by < 0.35 * r * sin(tilt) vertically; documented in docs/sim.md). Clearances are
signed distances: positive = free space, <= 0 = contact/penetration.

Surfaces: 'floor' (z = 0), 'wall' (the solid part of the plane x = wall_x), 'window_frame' (the
aperture's edges, i.e. the wall points closest to a vehicle inside the aperture's tube) and
'back_wall' (x = back_wall_x).
"""
from __future__ import annotations

import numpy as np

from ibvs_sim.core.world import WorldConfig

FLOOR = 'floor'
WALL = 'wall'
WINDOW_FRAME = 'window_frame'
BACK_WALL = 'back_wall'


def cylinder_sdf(point: np.ndarray, xi_I: np.ndarray, radius: float, height: float) -> float:
    """Signed distance (m) from a point to the vertical capped cylinder centred on xi_I."""
    (px, py, pz), (x, y, z) = _floats(point), _floats(xi_I)
    s = float(np.hypot(px - x, py - y)) - radius    # radial
    v = abs(pz - z) - height / 2.0                  # vertical (z down, symmetric)
    return min(max(s, v), 0.0) + float(np.hypot(max(s, 0.0), max(v, 0.0)))


def _floats(p) -> tuple[float, float, float]:
    """Return the 3 coordinates of a point (sequence or array) as Python floats."""
    x, y, z = p.tolist() if isinstance(p, np.ndarray) else p
    return float(x), float(y), float(z)


def wall_clearance(xi_I: np.ndarray, world: WorldConfig, radius: float,
                   height: float) -> tuple[float, str]:
    """Clearance to the wall plane with its rectangular aperture, and the surface name.

    The distance to the cylinder grows with |y - xi_y| and |z - xi_z| separately, so the closest
    solid wall point is the foot point (wall_x, xi_y, xi_z) when that is solid wall, otherwise
    one of the four perpendicular feet on the aperture's edges.
    """
    x, y, z = _floats(xi_I)
    win = world.window
    y_lo, y_hi = win.center_I[1] - win.width / 2.0, win.center_I[1] + win.width / 2.0
    z_lo, z_hi = win.center_I[2] - win.height / 2.0, win.center_I[2] + win.height / 2.0
    (wy0, wy1), (wz0, wz1) = world.wall_y_range, world.wall_z_range
    wy = min(max(y, float(wy0)), float(wy1))       # np.clip's value, for scalars
    wz = min(max(z, float(wz0)), float(wz1))
    inside_aperture = y_lo < wy < y_hi and z_lo < wz < z_hi
    if not inside_aperture:
        return cylinder_sdf((world.wall_x, wy, wz), xi_I, radius, height), WALL
    feet = [(world.wall_x, y_lo, wz), (world.wall_x, y_hi, wz),
            (world.wall_x, wy, z_lo), (world.wall_x, wy, z_hi)]
    return min(cylinder_sdf(f, xi_I, radius, height) for f in feet), WINDOW_FRAME


def min_clearance(xi_I: np.ndarray, world: WorldConfig, envelope_radius: float,
                  envelope_height: float) -> tuple[float, str]:
    """Smallest signed clearance (m) of the envelope to floor, wall/frame and back wall."""
    x, _, z = np.asarray(xi_I, dtype=float)
    candidates = [
        (world.floor_z - (z + envelope_height / 2.0), FLOOR),
        wall_clearance(xi_I, world, envelope_radius, envelope_height),
        (world.back_wall_x - x - envelope_radius, BACK_WALL),
    ]
    return min(candidates, key=lambda c: c[0])


def obstacle_clearance(xi_I: np.ndarray, world: WorldConfig, envelope_radius: float,
                       envelope_height: float) -> tuple[float, str]:
    """Like :func:`min_clearance` but without the floor (landing on it is the goal)."""
    x = float(np.asarray(xi_I)[0])
    return min([wall_clearance(xi_I, world, envelope_radius, envelope_height),
                (world.back_wall_x - x - envelope_radius, BACK_WALL)], key=lambda c: c[0])


def floor_clearance(xi_I: np.ndarray, world: WorldConfig, envelope_height: float) -> float:
    """Height (m) of the envelope's bottom above the floor (<= 0: touchdown)."""
    return world.floor_z - (float(np.asarray(xi_I)[2]) + envelope_height / 2.0)
