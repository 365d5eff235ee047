"""Attitude of each camera frame for derotating the optical flow (paper section 3.3).

The IMU attitudes come from :class:`ibvs_common.core.attitude_buffer.AttitudeBuffer`
(interpolated at an image stamp, or propagated with the gyro for a bounded time: a frame never
waits for a later IMU sample).
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.frames import exp_so3, log_so3
from ibvs_common.core.attitude_buffer import AttitudeBuffer


class GyroDerotation:
    """Attitude of each camera frame for derotating the optical flow.

    The previous frame's attitude is propagated with the gyro (AttitudeBuffer.gyro_rotation),
    then pulled towards the measured attitude by a small complementary gain: the rotation
    between two frames comes from the low-noise gyro (an attitude estimate's own noise would
    read as spurious rotation), while the absolute attitude cannot drift.
    """

    def __init__(self, buffer: AttitudeBuffer, gain: float = 0.05,
                 max_gap_s: float = 0.2) -> None:
        self.buffer, self.gain, self.max_gap_s = buffer, gain, max_gap_s
        self._R: np.ndarray | None = None
        self._t: float | None = None

    def at_frame(self, stamp_s: float) -> np.ndarray | None:
        """R_IB to use for the frame at ``stamp_s`` (None: no IMU coverage, state reset)."""
        R_meas = self.buffer.attitude_at(stamp_s)
        if R_meas is None:
            self._R, self._t = None, None
            return None
        R = R_meas
        if self._R is not None and 0.0 < stamp_s - self._t <= self.max_gap_s:
            dR = self.buffer.gyro_rotation(self._t, stamp_s)
            if dR is not None:
                R_prop = self._R @ dR
                R = R_prop @ exp_so3(self.gain * log_so3(R_prop.T @ R_meas))
        self._R, self._t = R, stamp_s
        return R
