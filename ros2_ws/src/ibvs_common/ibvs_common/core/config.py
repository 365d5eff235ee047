"""Typed views of the shared YAML files: pad layout, window layout, vehicle and cameras.

These files live in ``ibvs_bringup/config`` (installed to ``share/ibvs_bringup/config``) and are
the one source of truth for the sim, perception and control. Loaders raise ``ConfigError`` with
the file and key at fault; they never return partially filled objects.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ibvs_common.core.camera import CameraModel, CameraModelError
from ibvs_common.core.frames import is_rotation

CONFIG_PACKAGE = 'ibvs_bringup'


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or holds an invalid value."""


def default_config_path(file_name: str) -> str:
    """Return ``share/ibvs_bringup/config/<file_name>`` of the installed workspace."""
    try:
        from ament_index_python.packages import get_package_share_directory
        share = get_package_share_directory(CONFIG_PACKAGE)
    except Exception as exc:  # PackageNotFoundError, or ament_index missing
        raise ConfigError(f'cannot locate package {CONFIG_PACKAGE!r} to find {file_name}: '
                          f'{exc} (is AMENT_PREFIX_PATH set, is the workspace installed?)'
                          ) from exc
    return os.path.join(share, 'config', file_name)


def load_yaml(path: str | os.PathLike) -> dict:
    try:
        with open(path, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f'cannot read {path}: {exc}') from exc
    if not isinstance(data, dict):
        raise ConfigError(f'{path}: top level must be a mapping')
    return data


def get_key(data: dict, key: str, path: str | os.PathLike) -> Any:
    node = data
    for part in key.split('.'):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f'{path}: missing key {key!r}')
        node = node[part]
    return node


# --- Pad layout --------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerGroup:
    """One group of 4 ArUco markers whose centres form a square around the pad centre."""

    name: str
    ids: tuple[int, int, int, int]
    side: float            # m, marker side (black border included)
    c: float               # m, half-side of the square of marker centres

    def marker_centres_I(self) -> np.ndarray:
        """Marker centres (4, 3) in {I}, in the order of ``ids``."""
        c = self.c
        return np.array([[c, c, 0.0], [c, -c, 0.0], [-c, -c, 0.0], [-c, c, 0.0]])


@dataclass(frozen=True)
class PadLayout:
    """The landing pad: ArUco dictionary, quiet zone and marker groups (largest first)."""

    dictionary: str
    quiet_zone: float
    groups: tuple[MarkerGroup, ...]

    def group_of(self, marker_id: int) -> MarkerGroup | None:
        """Return the group a marker id belongs to, or None for a foreign id."""
        for g in self.groups:
            if marker_id in g.ids:
                return g
        return None


def load_pad_layout(path: str | os.PathLike | None = None) -> PadLayout:
    """Load the pad layout YAML (default: the installed ``pad_layout.yaml``)."""
    path = path or default_config_path('pad_layout.yaml')
    data = load_yaml(path)
    groups = []
    seen: set[int] = set()
    for i, g in enumerate(get_key(data, 'groups', path)):
        try:
            ids = tuple(int(x) for x in g['ids'])
            group = MarkerGroup(str(g['name']), ids, float(g['side']), float(g['c']))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f'{path}: groups[{i}] invalid: {exc}') from exc
        if len(ids) != 4 or seen.intersection(ids) or group.side <= 0 or group.c <= 0:
            raise ConfigError(f'{path}: groups[{i}] needs 4 unique ids, side > 0, c > 0')
        seen.update(ids)
        groups.append(group)
    groups.sort(key=lambda g: -g.side)
    return PadLayout(str(get_key(data, 'dictionary', path)), float(data.get('quiet_zone', 0.25)),
                     tuple(groups))


# --- Window ------------------------------------------------------------------------------

@dataclass(frozen=True)
class WindowLayout:
    """The window's known size (the vehicle's belief; the sim's world.yaml holds the truth)."""

    width: float           # m, r_w: aperture width (horizontal)
    height: float          # m, aperture height
    frame_band: float      # m, dark band on the wall face around the aperture


def load_window_layout(path: str | os.PathLike | None = None) -> WindowLayout:
    """Load the window layout YAML (default: the installed ``window_layout.yaml``)."""
    path = path or default_config_path('window_layout.yaml')
    data = load_yaml(path)
    try:
        layout = WindowLayout(*(float(get_key(data, k, path))
                                for k in ('width', 'height', 'frame_band')))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'{path}: {exc}') from exc
    if not all(np.isfinite(v) and v > 0 for v in (layout.width, layout.height,
                                                  layout.frame_band)):
        raise ConfigError(f'{path}: width, height and frame_band must be > 0, got {layout}')
    return layout


# --- Vehicle and cameras -----------------------------------------------------------------

@dataclass(frozen=True)
class CameraConfig:
    """One camera: intrinsics (as CameraInfo carries them), mount, rate, timing, frame id.

    ``t_BC``: the camera's optical centre in body FRD (m), the lever arm from the body origin;
    ``time_offset_s``: the camera-IMU time offset (kalibr's ``timeshift_cam_imu``): the
    image taken at stamp s was exposed at IMU time s + time_offset_s.
    """

    name: str
    frame_id: str
    R_BC: np.ndarray        # optical -> body FRD
    model: CameraModel
    rate_hz: float
    t_BC: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_offset_s: float = 0.0


@dataclass(frozen=True)
class VehicleConfig:
    """Pelican-class vehicle: mass, thrust model, collision envelope and cameras."""

    mass: float                  # kg
    arm_length: float            # m
    max_thrust_factor: float     # max collective thrust / (m g)
    hover_thrust: float          # normalised thrust at hover
    envelope_radius: float       # m
    envelope_height: float       # m
    cameras: dict                # name -> CameraConfig
    raw: dict                    # the whole file, for sim-only keys (inertia, rotors, ...)


def load_vehicle(path: str | os.PathLike | None = None) -> VehicleConfig:
    """Load the vehicle YAML (default: the installed ``vehicle.yaml``)."""
    path = path or default_config_path('vehicle.yaml')
    return vehicle_from_dict(load_yaml(path), path)


def vehicle_from_dict(d: dict, path: str | os.PathLike = '<vehicle>') -> VehicleConfig:
    """Check and build a VehicleConfig from a vehicle YAML's contents (``path``: for errors)."""
    cameras = {}
    for name, c in get_key(d, 'cameras', path).items():
        try:
            R_BC = np.array(c['R_BC'], dtype=float)
            model = CameraModel.from_camera_info(int(c['width']), int(c['height']), c['K'],
                                                 c['D'], str(c['distortion_model']))
            t_BC = np.array(c.get('t_BC', (0.0, 0.0, 0.0)), dtype=float).reshape(3)
            cam = CameraConfig(name, str(c['frame_id']), R_BC, model, float(c['rate_hz']),
                               t_BC, float(c.get('time_offset_s', 0.0)))
        except (KeyError, TypeError, ValueError, CameraModelError) as exc:
            raise ConfigError(f'{path}: cameras.{name} invalid: {exc}') from exc
        if not is_rotation(R_BC):
            raise ConfigError(f'{path}: cameras.{name}.R_BC is not a rotation matrix')
        if not (np.all(np.isfinite(cam.t_BC)) and np.linalg.norm(cam.t_BC) < 1.0):
            raise ConfigError(f'{path}: cameras.{name}.t_BC must be finite and under 1 m')
        if not (cam.rate_hz > 0.0 and abs(cam.time_offset_s) < 1.0):
            raise ConfigError(f'{path}: cameras.{name}: rate_hz must be > 0 and '
                              '|time_offset_s| < 1 s')
        cameras[name] = cam
    try:
        v = VehicleConfig(float(get_key(d, 'mass', path)), float(get_key(d, 'arm_length', path)),
                          float(get_key(d, 'max_thrust_factor', path)),
                          float(get_key(d, 'hover_thrust', path)),
                          float(get_key(d, 'envelope.radius', path)),
                          float(get_key(d, 'envelope.height', path)), cameras, d)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'{path}: {exc}') from exc
    if v.mass <= 0 or not 0.0 < v.hover_thrust < 1.0 or v.max_thrust_factor <= 1.0:
        raise ConfigError(f'{path}: need mass > 0, 0 < hover_thrust < 1, max_thrust_factor > 1')
    return v


def config_file(path: str | os.PathLike | None, file_name: str) -> Path:
    """Return ``path`` if given (non-empty), else the installed default for ``file_name``."""
    return Path(path) if path else Path(default_config_path(file_name))
