"""Attitude R_IB at any stamp from the IMU samples, without waiting for a later sample.

Part of the flight path's timing model (docs/design.md, "Time"; the rest is
:mod:`ibvs_control.core.timing`), shared by perception (derotation, gyro-aided tracking) and
control. ROS-free.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field
import math
from typing import Sequence

import numpy as np

from ibvs_common.core.params import param
from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.stamps import NS_PER_S
from ibvs_common.core.frames import exp_so3, is_rotation, log_so3, R_IB_from_quat_map_base


@dataclass(frozen=True)
class AttitudeBufferConfig:
    """Sizes and tolerances of :class:`AttitudeBuffer` (seconds of the stamps' clock)."""

    history_s: float = param(1.0, 's (IMU stamps, ROS clock), IMU attitudes kept, > 0', 0.0)
    max_extrapolation_s: float = param(
        0.05,
        's (IMU stamps, ROS clock), the attitude is propagated with the gyro at most this far '
        'beyond the newest sample, > 0', 0.0)
    max_interpolation_gap_s: float = param(
        0.2, 's (IMU stamps, ROS clock), two IMU samples farther apart are not interpolated, > 0',
        0.0)

    def __post_init__(self) -> None:
        for name in ('history_s', 'max_extrapolation_s', 'max_interpolation_gap_s'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')


@dataclass
class AttitudeBuffer:
    """Time-ordered IMU attitudes R_IB with interpolation or propagation to any stamp.

    Attitudes are the paper's R_IB (body FRD -> {I}); rates Omega are body FRD (rad/s), so
    that ``R_dot = R S(Omega)`` (paper eq:R). Between two samples the attitude is interpolated
    on SO(3) (geodesic: ``R_a exp(s log(R_a^T R_b))``); after the newest sample it is
    propagated with its rate, ``R_n exp(Omega_n dt)``, for at most ``max_extrapolation_s``.
    Stamps are seconds on the ROS clock (images and IMU share it).

    Samples come either as R_IB (:meth:`add`) or as the ROS message's quaternion
    (:meth:`add_map_base`), whose R_IB is computed only when a query needs it: every node
    keeps every 100 Hz imu/data sample, but only the few around an image stamp are ever read
    (docs/performance.md, "Idle CPU").

    Late samples: a query answered by propagation (beyond the newest sample) and a sample
    stamped at or before that query's stamp arriving afterwards means the IMU reached this
    node after an image that needed it (the image was answered with a propagated attitude,
    never held back). :attr:`late_samples` counts them and :attr:`last_late` keeps the
    newest (sample stamp, query stamp), for the nodes to report: onboard it says the IMU path
    is slower than the camera's; in a lockstep sim it marks a run whose attitudes depended
    on delivery order (docs/design.md, "Time").

    Samples may come a little out of order (they are sorted in). A sample stamped more than
    :data:`~ibvs_common.core.clock_step.MAX_BACKSTEP_S` before the newest one means the clock
    stepped back (:mod:`ibvs_common.core.clock_step`): the history is dropped first, so that
    no attitude is ever interpolated between samples of two moments; ``add`` returns True.
    """

    config: AttitudeBufferConfig = field(default_factory=AttitudeBufferConfig)
    _stamps: list = field(default_factory=list)
    _R: list = field(default_factory=list)       # R_IB, or None until first read (_q then)
    _q: list = field(default_factory=list)       # unit q_map_base of an add_map_base sample
    _omega: list = field(default_factory=list)
    backsteps: BackstepWatch = field(default_factory=BackstepWatch)   # IMU stamps
    late_samples: int = 0                        # samples at/before a propagated query's stamp
    last_late: tuple[float, float] | None = None  # (sample stamp, query stamp) of the newest
    _propagated_through: float | None = None     # newest stamp answered by propagation

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> float | None:
        """Stamp (s) of the newest sample, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_s: float, R_IB: np.ndarray, omega_B: np.ndarray) -> bool:
        """Insert a sample; True if the clock stepped back and the history was dropped.

        Raises ValueError for non-finite values or a non-rotation.
        """
        R_IB = np.asarray(R_IB, dtype=float)
        omega_B = np.asarray(omega_B, dtype=float).reshape(3)
        if not np.isfinite(stamp_s) or not np.all(np.isfinite(omega_B)) \
                or not is_rotation(R_IB, tol=1e-4):
            raise ValueError('IMU sample with a non-finite stamp/rate or an invalid attitude')
        return self._insert(float(stamp_s), R_IB, None, omega_B)

    def add_map_base(self, stamp_s: float, q_map_base: Sequence[float] | np.ndarray,
                     omega_B: np.ndarray) -> bool:
        """Insert a sample given by a ROS attitude quaternion (base_link FLU in map ENU).

        ``q_map_base``: (w, x, y, z), unit within 10 % (normalised here); ``omega_B``: body
        FRD rates (rad/s). R_IB (:func:`frames.R_IB_from_quat_map_base`, a rotation by
        construction) is computed on the first query that reads this sample, so the result
        of every query is the same as with :meth:`add`. Returns and raises as :meth:`add`.
        """
        w, x, y, z = (float(v) for v in q_map_base)
        o0, o1, o2 = (float(v) for v in omega_B)
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if not (math.isfinite(stamp_s) and math.isfinite(o0 + o1 + o2) and math.isfinite(n)) \
                or abs(n - 1.0) > 0.1:
            raise ValueError('IMU sample with a non-finite stamp/rate or an invalid attitude')
        return self._insert(float(stamp_s), None, (w, x, y, z), np.array((o0, o1, o2)))

    def clear(self) -> None:
        """Drop every sample."""
        del self._stamps[:], self._R[:], self._q[:], self._omega[:]
        self._propagated_through = None

    def _insert(self, stamp_s: float, R_IB, q, omega_B: np.ndarray) -> bool:
        stepped = bool(self.backsteps.observe(round(stamp_s * NS_PER_S)))
        if stepped:
            self.clear()
        if self._propagated_through is not None and stamp_s <= self._propagated_through:
            self.late_samples += 1
            self.last_late = (stamp_s, self._propagated_through)
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i > 0 and self._stamps[i - 1] == stamp_s:
            self._R[i - 1], self._q[i - 1], self._omega[i - 1] = R_IB, q, omega_B
            return stepped
        self._stamps.insert(i, stamp_s)
        self._R.insert(i, R_IB)
        self._q.insert(i, q)
        self._omega.insert(i, omega_B)
        cutoff = self._stamps[-1] - self.config.history_s
        drop = bisect.bisect_left(self._stamps, cutoff)
        if drop > 0:
            del self._stamps[:drop], self._R[:drop], self._q[:drop], self._omega[:drop]
        return stepped

    def _rotation(self, i: int) -> np.ndarray:
        """R_IB of sample i (computed from its quaternion once, on the first read)."""
        R = self._R[i]
        if R is None:
            R = self._R[i] = R_IB_from_quat_map_base(self._q[i])
        return R

    def attitude_at(self, stamp_s: float) -> np.ndarray | None:
        """R_IB at ``stamp_s`` or None when the buffer does not cover it."""
        if not self._stamps or not np.isfinite(stamp_s):
            return None
        cfg = self.config
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i > 0 and self._stamps[i - 1] == stamp_s:       # a sample's own stamp
            return self._rotation(i - 1).copy()            # (the caller may modify it)
        if i == len(self._stamps):
            dt = stamp_s - self._stamps[-1]
            if dt > cfg.max_extrapolation_s:
                return None
            self._note_propagated(stamp_s)
            return self._rotation(-1) @ exp_so3(self._omega[-1] * dt)
        if i == 0:
            return None
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > cfg.max_interpolation_gap_s:
            return None
        s = (stamp_s - t0) / (t1 - t0)
        R0 = self._rotation(i - 1)
        return R0 @ exp_so3(s * log_so3(R0.T @ self._rotation(i)))

    def rate_at(self, stamp_s: float) -> np.ndarray | None:
        """Body rate omega_B (rad/s, FRD) at ``stamp_s``: interpolated, or the newest held.

        None where :meth:`attitude_at` is None (not covered by the buffer).
        """
        if not self._stamps or not np.isfinite(stamp_s):
            return None
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i > 0 and self._stamps[i - 1] == stamp_s:
            return np.array(self._omega[i - 1], dtype=float)
        if i == len(self._stamps):
            if stamp_s - self._stamps[-1] > self.config.max_extrapolation_s:
                return None
            return np.array(self._omega[-1], dtype=float)
        if i == 0:
            return None
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > self.config.max_interpolation_gap_s:
            return None
        s = (stamp_s - t0) / (t1 - t0)
        return (1.0 - s) * np.asarray(self._omega[i - 1], float) \
            + s * np.asarray(self._omega[i], float)

    def gyro_rotation(self, t0: float, t1: float) -> np.ndarray | None:
        """Body rotation dR from t0 to t1 integrated from the buffered rates (R(t1) = R(t0) dR).

        Rates are trapezoid-averaged between consecutive samples and held after the newest one
        (for at most ``max_extrapolation_s``); None when the buffer does not cover [t0, t1].
        """
        cfg = self.config
        if not self._stamps or not (np.isfinite(t0) and np.isfinite(t1)) or t1 < t0 \
                or t0 < self._stamps[0] or t1 - self._stamps[-1] > cfg.max_extrapolation_s:
            return None
        if t1 > self._stamps[-1]:
            self._note_propagated(t1)
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

    def _note_propagated(self, stamp_s: float) -> None:
        """Remember that ``stamp_s`` was answered beyond the newest sample (late samples)."""
        if self._propagated_through is None or stamp_s > self._propagated_through:
            self._propagated_through = stamp_s
