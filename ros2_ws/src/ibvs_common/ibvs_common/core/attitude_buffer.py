"""Attitude R_IB at any stamp from the IMU samples, without waiting for a later sample.

Part of the flight path's timing model (docs/design.md, "Time"; the rest is
:mod:`ibvs_control.core.timing`), shared by perception (derotation, gyro-aided tracking) and
control. ROS-free.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from ibvs_common.core.frames import exp_so3, is_rotation, log_so3


@dataclass(frozen=True)
class AttitudeBufferConfig:
    """Sizes and tolerances of :class:`AttitudeBuffer` (seconds of the stamps' clock)."""

    history_s: float = 1.0              # samples older than newest - history_s are dropped
    max_extrapolation_s: float = 0.05   # propagation beyond the newest sample, at most
    max_interpolation_gap_s: float = 0.2  # two samples farther apart are not interpolated

    def __post_init__(self) -> None:
        for name in ('history_s', 'max_extrapolation_s', 'max_interpolation_gap_s'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')


#: spec of each AttitudeBufferConfig field as a ROS parameter, declared as ``imu_<field>``
#: (description with unit, inclusive range; ibvs_common.param_descriptors)
ATTITUDE_BUFFER_SPECS = {
    'history_s': ('s (IMU stamps, ROS clock), IMU attitudes kept, > 0', 0.0, None),
    'max_extrapolation_s': ('s (IMU stamps, ROS clock), the attitude is propagated with the '
                            'gyro at most this far beyond the newest sample, > 0', 0.0, None),
    'max_interpolation_gap_s': ('s (IMU stamps, ROS clock), two IMU samples farther apart are '
                                'not interpolated, > 0', 0.0, None),
}


@dataclass
class AttitudeBuffer:
    """Time-ordered IMU attitudes R_IB with interpolation or propagation to any stamp.

    Attitudes are the paper's R_IB (body FRD -> {I}); rates Omega are body FRD (rad/s), so
    that ``R_dot = R S(Omega)`` (paper eq:R). Between two samples the attitude is interpolated
    on SO(3) (geodesic: ``R_a exp(s log(R_a^T R_b))``); after the newest sample it is
    propagated with its rate, ``R_n exp(Omega_n dt)``, for at most ``max_extrapolation_s``.
    Stamps are seconds on the ROS clock (images and IMU share it).
    """

    config: AttitudeBufferConfig = field(default_factory=AttitudeBufferConfig)
    _stamps: list = field(default_factory=list)
    _R: list = field(default_factory=list)
    _omega: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> float | None:
        """Stamp (s) of the newest sample, or None when empty."""
        return self._stamps[-1] if self._stamps else None

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
