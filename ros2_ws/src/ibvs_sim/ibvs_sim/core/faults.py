"""Test-only fault injection by sim-time windows: cameras off or frozen (the IMU's: autopilot).

The windows are ``[start, end)`` in sim seconds, given flat (``start, end, start, end, ...``,
as ROS parameters) or as pairs; ``[0, 0]`` never happens. :class:`CameraFaults` withholds or
freezes the images the sim node publishes; the autopilot's IMU faults
(``AutopilotConfig.imu_off_s`` / ``imu_nan_s``) use the same windows. ROS-free.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def fault_windows(name: str, flat: Sequence[float] | Sequence[Sequence[float]]
                  ) -> tuple[tuple[float, float], ...]:
    """Return the (start, end) sim-time windows (s) of a sequence start, end, start, end, ...

    The sequence may be flat or of pairs. ValueError, naming ``name``, for an odd or empty
    sequence or a window with end < start.
    """
    v = np.asarray(flat, dtype=float).ravel().tolist()
    if not v or len(v) % 2:
        raise ValueError(f'{name} needs [start, end, ...] pairs, got {v}')
    windows = tuple(zip(v[0::2], v[1::2]))
    for a, b in windows:
        if not (math.isfinite(a) and math.isfinite(b) and b >= a):
            raise ValueError(f'{name} needs start <= end in each window, got [{a}, {b}]')
    return windows


class CameraFaults:
    """Fault injection on the published camera images (test harness), by sim-time windows.

    ``off_s`` and ``frozen_s`` map a camera name to its [start, end) window in sim seconds, or
    to several: a flat sequence (start, end, start, end, ...) (start == end: never). Off: the
    camera's images are withheld. Frozen: the camera keeps delivering the image of the first
    frame in the window with the new frames' stamps, as a hung camera driver that re-publishes
    its last buffer (read noise included: the very same bytes). :meth:`apply` gives each
    frame's images to publish.
    """

    def __init__(self, off_s: dict | None = None, frozen_s: dict | None = None) -> None:
        self.off_s = {k: fault_windows(k, v) for k, v in (off_s or {}).items()}
        self.frozen_s = {k: fault_windows(k, v) for k, v in (frozen_s or {}).items()}
        self.held: dict[str, tuple[float, np.ndarray]] = {}   # frozen camera -> (t, image)

    @staticmethod
    def _active(windows: tuple | None, t: float) -> bool:
        return windows is not None and any(a <= t < b for a, b in windows)

    def apply(self, t: float, images: dict) -> tuple[dict, list, list]:
        """Return (images to publish, cameras withheld, cameras frozen) of the frame at ``t``."""
        withheld = [n for n in images if self._active(self.off_s.get(n), t)]
        frozen = [n for n in images if n not in withheld
                  and self._active(self.frozen_s.get(n), t)]
        out = {}
        for name, img in images.items():
            if name in withheld:
                continue
            if name in frozen:
                img = self.held.setdefault(name, (t, img))[1]
            else:
                self.held.pop(name, None)
            out[name] = img
        return out, withheld, frozen
