"""Buffer of recent IMU attitudes, interpolated or propagated to an image stamp.

Attitudes are the paper's R_IB (body FRD -> {I}); rates Omega are body FRD (rad/s), so that
``R_dot = R S(Omega)`` (paper eq:R). Between two samples the attitude is interpolated on SO(3)
(geodesic: ``R_a exp(s log(R_a^T R_b))``); after the newest sample it is propagated with its
rate for at most ``max_extrapolation_s``. Stamps are seconds (any clock, as long as images and
IMU share it).
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from ibvs_control.core.frames import exp_so3, is_rotation, log_so3


@dataclass(frozen=True)
class AttitudeBufferConfig:
    """Sizes and tolerances of :class:`AttitudeBuffer`."""

    history_s: float = 1.0              # samples older than newest - history_s are dropped
    max_extrapolation_s: float = 0.05   # propagation beyond the newest sample, at most
    max_interpolation_gap_s: float = 0.2  # two samples farther apart are not interpolated


class AttitudeBuffer:
    """Time-ordered IMU attitudes with interpolation to arbitrary stamps."""

    def __init__(self, config: AttitudeBufferConfig) -> None:
        self.config = config
        self._stamps: list[float] = []
        self._R: list[np.ndarray] = []
        self._omega: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> float | None:
        """Stamp (s) of the newest sample, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def covers(self, stamp_s: float) -> bool:
        """Whether a sample at or after ``stamp_s`` is in (interpolation, not extrapolation)."""
        return bool(self._stamps) and self._stamps[-1] >= stamp_s

    def add(self, stamp_s: float, R_IB: np.ndarray, omega_B: np.ndarray) -> None:
        """Insert a sample; raises ValueError for non-finite values or a non-rotation."""
        R_IB = np.asarray(R_IB, dtype=float)
        omega_B = np.asarray(omega_B, dtype=float).reshape(3)
        if not np.isfinite(stamp_s) or not np.all(np.isfinite(omega_B)) \
                or not is_rotation(R_IB, tol=1e-4):
            raise ValueError('IMU sample with a non-finite stamp/rate or an invalid attitude')
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i > 0 and self._stamps[i - 1] == stamp_s:
            self._R[i - 1], self._omega[i - 1] = R_IB, omega_B
            return
        self._stamps.insert(i, float(stamp_s))
        self._R.insert(i, R_IB)
        self._omega.insert(i, omega_B)
        cutoff = self._stamps[-1] - self.config.history_s
        drop = bisect.bisect_left(self._stamps, cutoff)
        if drop > 0:
            del self._stamps[:drop], self._R[:drop], self._omega[:drop]

    def attitude_at(self, stamp_s: float) -> np.ndarray | None:
        """R_IB at ``stamp_s`` or None when the buffer does not cover it."""
        if not self._stamps or not np.isfinite(stamp_s):
            return None
        cfg = self.config
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i == len(self._stamps):
            dt = stamp_s - self._stamps[-1]
            if dt > cfg.max_extrapolation_s:
                return None
            return self._R[-1] @ exp_so3(self._omega[-1] * dt)
        if i == 0:
            return None
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > cfg.max_interpolation_gap_s:
            return None
        s = (stamp_s - t0) / (t1 - t0)
        R0 = self._R[i - 1]
        return R0 @ exp_so3(s * log_so3(R0.T @ self._R[i]))

    def gyro_rotation(self, t0: float, t1: float) -> np.ndarray | None:
        """Body rotation dR from t0 to t1 integrated from the buffered rates (R(t1) = R(t0) dR).

        Rates are trapezoid-averaged between consecutive samples and held after the newest one
        (for at most ``max_extrapolation_s``); None when the buffer does not cover [t0, t1].
        """
        cfg = self.config
        if not self._stamps or not (np.isfinite(t0) and np.isfinite(t1)) or t1 < t0 \
                or t0 < self._stamps[0] or t1 - self._stamps[-1] > cfg.max_extrapolation_s:
            return None
        dR = np.eye(3)
        n = len(self._stamps)
        for k in range(bisect.bisect_right(self._stamps, t0) - 1, n):
            a = max(self._stamps[k], t0)
            b = min(self._stamps[k + 1], t1) if k + 1 < n else t1
            if b <= a:
                if a >= t1:
                    break
                continue
            if k + 1 < n and self._stamps[k + 1] - self._stamps[k] > cfg.max_interpolation_gap_s:
                return None
            omega = self._omega[k] if k + 1 == n else 0.5 * (self._omega[k] + self._omega[k + 1])
            dR = dR @ exp_so3(omega * (b - a))
        return dR


class GyroDerotation:
    """Attitude of each camera frame for derotating the optical flow (paper section 3.3).

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
