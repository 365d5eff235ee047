"""The sim's world: wall, window, floor, back wall and the reference start (world.yaml).

Sim-only data (docs/spec.md section 2): the onboard graph never reads it. The controller and the
supervisor get the window size and the pad layout as their own configuration; the sim, the
scenario runner and the evaluation read the world from here.
"""
from __future__ import annotations

from dataclasses import dataclass
import os

import numpy as np

from ibvs_common.core.config import ConfigError, default_config_path, get_key, load_yaml


@dataclass(frozen=True)
class WindowGeometry:
    """The rectangular window aperture in the wall, paper frame {I}."""

    center_I: np.ndarray    # m
    width: float            # m, r_w (along y_I)
    height: float           # m (along z_I)
    frame_band: float       # m, dark border around the aperture on the wall face

    def corners_I(self) -> np.ndarray:
        """Aperture corners (4, 3) in {I}: top-left, top-right, bottom-right, bottom-left.

        As seen from the approach side (looking along +x_I): left is -y_I, top is -z_I.
        """
        cx, cy, cz = self.center_I
        hw, hh = self.width / 2.0, self.height / 2.0
        return np.array([[cx, cy - hw, cz - hh], [cx, cy + hw, cz - hh],
                         [cx, cy + hw, cz + hh], [cx, cy - hw, cz + hh]])

    def outer_corners_I(self) -> np.ndarray:
        """Outer corners (4, 3) of the dark frame band in {I}, same order as corners_I."""
        grown = WindowGeometry(self.center_I, self.width + 2.0 * self.frame_band,
                               self.height + 2.0 * self.frame_band, 0.0)
        return grown.corners_I()


@dataclass(frozen=True)
class WorldConfig:
    """Reference scenario of docs/spec.md section 2."""

    floor_z: float
    floor_extent_x: tuple[float, float]
    floor_extent_y: tuple[float, float]
    wall_x: float
    wall_z_range: tuple[float, float]
    wall_y_range: tuple[float, float]
    window: WindowGeometry
    back_wall_x: float
    texture_seeds: dict
    initial_position_I: np.ndarray
    initial_yaw: float
    random_box: dict


def load_world(path: str | os.PathLike | None = None) -> WorldConfig:
    """Load the world YAML (default: the installed ``world.yaml``)."""
    path = path or default_config_path('world.yaml')
    d = load_yaml(path)
    try:
        window = WindowGeometry(np.array(get_key(d, 'window.center', path), dtype=float),
                                float(get_key(d, 'window.width', path)),
                                float(get_key(d, 'window.height', path)),
                                float(get_key(d, 'window.frame_band', path)))
        world = WorldConfig(
            floor_z=float(get_key(d, 'floor.z', path)),
            floor_extent_x=tuple(get_key(d, 'floor.extent_x', path)),
            floor_extent_y=tuple(get_key(d, 'floor.extent_y', path)),
            wall_x=float(get_key(d, 'wall.x', path)),
            wall_z_range=tuple(get_key(d, 'wall.z_range', path)),
            wall_y_range=tuple(get_key(d, 'wall.y_range', path)),
            window=window,
            back_wall_x=float(get_key(d, 'back_wall.x', path)),
            texture_seeds={'floor': int(d['floor'].get('texture_seed', 1)),
                           'wall': int(d['wall'].get('texture_seed', 2)),
                           'back_wall': int(d['back_wall'].get('texture_seed', 3))},
            initial_position_I=np.array(get_key(d, 'initial_condition.position', path),
                                        dtype=float),
            initial_yaw=float(get_key(d, 'initial_condition.yaw', path)),
            random_box={k: tuple(map(float, v))
                        for k, v in get_key(d, 'random_initial_box', path).items()})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'{path}: {exc}') from exc
    if window.width <= 0 or window.height <= 0 or window.center_I.shape != (3,):
        raise ConfigError(f'{path}: window needs a 3-vector centre and positive size')
    return world
