"""Sensor and calibration errors a campaign run draws: the truth the sim flies vs the calibration.

A real vehicle's cameras are not what its vehicle.yaml says: the mounts are off by a fraction
of a degree, the intrinsics by what a good calibration leaves, the lever arms by millimetres,
the camera-IMU time offset by milliseconds, and the images come 15-40 ms after their stamps.
A :class:`SensorProfile` gives the ranges; :func:`draw` one run's values (seeded);
:func:`vehicle_files` the two vehicle descriptions: the *true* one the sim renders and flies
with, and the *onboard* one the graph is calibrated with (the nominal file with the lever
arms as measured). Angles in rad, lengths in m, times in s. ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from ibvs_common.core.frames import rot_from_euler_zyx

CAMERAS = ('front', 'down')


@dataclass(frozen=True)
class SensorProfile:
    """Ranges (uniform draws, per camera and axis where it applies) of a run's errors."""

    latency_s: tuple = (0.0, 0.0)        # camera delivery after the stamp, s
    jitter_s: float = 0.0                # s, +- around the latency
    camera_rate_hz: float = 50.0
    mount_error_rad: float = 0.0         # per axis: true mount vs calibrated
    focal_error: float = 0.0             # relative: true f = calibrated f (1 +- this)
    principal_point_error_px: float = 0.0   # per axis
    lever_arm_m: float = 0.0             # per component: the true t_BC (the nominal file's 0)
    lever_arm_error_m: float = 0.0       # per component: calibrated t_BC vs the true one
    time_offset_s: float = 0.0           # +-: true camera-IMU offset left uncalibrated


#: the profiles a campaign names (``--sensors``): 'realistic' is issue 46's: what a good
#: calibration leaves and a USB / MIPI camera delivers
PROFILES = {
    'ideal': SensorProfile(),
    'realistic': SensorProfile(latency_s=(0.015, 0.040), jitter_s=0.003,
                               mount_error_rad=math.radians(1.0), focal_error=0.005,
                               principal_point_error_px=2.0, lever_arm_m=0.05,
                               lever_arm_error_m=0.005, time_offset_s=0.003),
}


@dataclass(frozen=True)
class CameraErrors:
    """One camera's drawn errors."""

    mount_rpy_rad: tuple = (0.0, 0.0, 0.0)
    focal_scale: float = 1.0
    principal_point_px: tuple = (0.0, 0.0)
    t_BC_true: tuple = (0.0, 0.0, 0.0)
    t_BC_calibrated: tuple = (0.0, 0.0, 0.0)
    time_offset_s: float = 0.0


@dataclass(frozen=True)
class SensorDraw:
    """One run's errors: delivery and rate for both cameras, the rest per camera."""

    latency_s: float = 0.0
    jitter_s: float = 0.0
    camera_rate_hz: float = 50.0
    cameras: dict = field(default_factory=lambda: {c: CameraErrors() for c in CAMERAS})

    def as_dict(self) -> dict:
        """Return the draw as plain values (summary.json)."""
        return {'latency_s': self.latency_s, 'jitter_s': self.jitter_s,
                'camera_rate_hz': self.camera_rate_hz,
                'cameras': {c: {k: (list(v) if isinstance(v, tuple) else v)
                                for k, v in vars(e).items()} for c, e in self.cameras.items()}}


def draw(profile: SensorProfile, rng: np.random.Generator) -> SensorDraw:
    """Draw one run's errors from ``profile`` (uniform within each range)."""
    def u(half: float, n: int = 1) -> tuple:
        return tuple(float(x) for x in rng.uniform(-half, half, n)) if half > 0 else (0.0,) * n

    cams = {}
    for cam in CAMERAS:
        t_true = u(profile.lever_arm_m, 3)
        err = u(profile.lever_arm_error_m, 3)
        cams[cam] = CameraErrors(
            mount_rpy_rad=u(profile.mount_error_rad, 3),
            focal_scale=1.0 + u(profile.focal_error)[0],
            principal_point_px=u(profile.principal_point_error_px, 2), t_BC_true=t_true,
            t_BC_calibrated=tuple(a + b for a, b in zip(t_true, err)),
            time_offset_s=u(profile.time_offset_s)[0])
    lo, hi = profile.latency_s
    latency = float(rng.uniform(lo, hi)) if hi > lo else float(lo)
    return SensorDraw(latency, profile.jitter_s, profile.camera_rate_hz, cams)


def vehicle_files(nominal: dict, errors: SensorDraw) -> tuple[dict, dict]:
    """Return (true, calibrated) vehicle YAML dicts from the nominal vehicle.yaml's dict.

    True: each mount rotated by its error (R_BC_true = R_BC R_err, in the optical frame),
    focal lengths scaled, principal point moved, the true lever arms and time offsets, the
    camera rate. Calibrated: the nominal file with the calibrated lever arms and the rate
    (its mounts, intrinsics and time offsets are the nominal ones).
    """
    true, calibrated = _copy(nominal), _copy(nominal)
    for cam, e in errors.cameras.items():
        t, c = true['cameras'][cam], calibrated['cameras'][cam]
        R = np.asarray(t['R_BC'], dtype=float) @ rot_from_euler_zyx(*e.mount_rpy_rad)
        t['R_BC'] = R.tolist()
        K = list(map(float, t['K']))
        K[0] *= e.focal_scale
        K[4] *= e.focal_scale
        K[2] += e.principal_point_px[0]
        K[5] += e.principal_point_px[1]
        t['K'] = K
        t['t_BC'], c['t_BC'] = list(e.t_BC_true), list(e.t_BC_calibrated)
        t['time_offset_s'] = e.time_offset_s
        for d in (t, c):
            d['rate_hz'] = errors.camera_rate_hz
    return true, calibrated


def _copy(d):
    if isinstance(d, dict):
        return {k: _copy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_copy(v) for v in d]
    return d
