"""Sensor noise of the sim autopilot's telemetry, a function of sim time only.

Gyro (``gyro_noise_std``, rad/s) and accelerometer (``accel_noise_std``, m/s²), one std per body
axis, white Gaussian per axis. The attitude estimate's error is a small body rotation
``R_err``: the autopilot's estimate is ``R_IB R_err`` (R_IB the truth, FRD -> NED). It is a
static offset (``attitude_estimate_offset_rad``: roll and pitch, a body rotation vector (x, y,
0), e.g. the tilt b/g that an accelerometer bias b leaves in an estimator levelling on it; PX4
SIH measured 1.5-1.8 deg in one axis, docs/sim.md) composed with a first-order Gauss-Markov
process per axis (stationary std ``attitude_noise_std`` rad, correlation time
``attitude_noise_tau_s`` s), advanced on a fixed sim-time grid of ``NOISE_GRID_S``: an attitude
estimator's error wanders, white noise per message would read as spurious rotation between two
camera frames. The autopilot both reports that estimate (ATTITUDE_QUATERNION) and flies it (its
attitude loop drives the estimate, not the truth, to the setpoint: ``PhysicsLoop`` gives the
inner loop ``R_d R_err^T``). Every draw is keyed by (``noise_seed``, stream, sim-time index),
so the noise does not depend on how many messages were sent before: two lockstep runs see the
same noise.
"""
from __future__ import annotations

import enum
import math

import numpy as np

from ibvs_common.core.frames import exp_so3, quat_from_rot, quat_multiply, rot_from_quat
from ibvs_sim.core.autopilot.config import AutopilotConfig
from ibvs_sim.core.autopilot.protocol import US_PER_S

NOISE_GRID_S = 0.01      # s, sim-time step of the attitude error process


class NoiseStream(enum.IntEnum):
    """Independent noise streams of the telemetry (part of each sample's RNG key)."""

    ATTITUDE = 1
    ATTITUDE_RATES = 2
    HIGHRES_IMU = 3


class SensorNoise:
    """The noise model of ATTITUDE_QUATERNION and HIGHRES_IMU (sim time t in s)."""

    def __init__(self, config: AutopilotConfig) -> None:
        """Draw the attitude error at grid index 0 (rad, body axes)."""
        self.config = config
        self._att_err = self.rng_at(NoiseStream.ATTITUDE, 0).normal(
            0.0, config.attitude_noise_std, 3)                   # rad, body axes
        self._att_k = 0
        roll, pitch = config.attitude_estimate_offset_rad
        self._offset_q = quat_from_rot(exp_so3(np.array([roll, pitch, 0.0])))

    def rng_at(self, stream: NoiseStream, index: int) -> np.random.Generator:
        """Return the generator of one noise sample, keyed by (seed, stream, sim-time index).

        Noise then depends on the sim time only, not on how many messages were sent before
        (which depends on wall-clock timing of rate requests): two lockstep runs see the same
        noise.
        """
        return np.random.default_rng((self.config.noise_seed, int(stream), int(index)))

    def error_quat(self, t: float) -> np.ndarray:
        """Return the estimate's error R_err at sim time t as a unit quaternion (w, x, y, z).

        The static offset times the Gauss-Markov error (std attitude_noise_std, correlation
        time attitude_noise_tau_s), advanced to t (s); it is not wound back for an earlier t.
        """
        cfg = self.config
        a = math.exp(-NOISE_GRID_S / cfg.attitude_noise_tau_s) \
            if cfg.attitude_noise_tau_s > 0 else 0.0
        k = int(t / NOISE_GRID_S)
        while self._att_k < k:            # advance on the grid: same errors whatever the rates
            self._att_k += 1
            self._att_err = a * self._att_err + math.sqrt(1.0 - a * a) * self.rng_at(
                NoiseStream.ATTITUDE, self._att_k).normal(0.0, cfg.attitude_noise_std, 3)
        half = 0.5 * self._att_err
        dq = np.concatenate(([1.0], half))
        return quat_multiply(self._offset_q, dq / np.linalg.norm(dq))

    def attitude_error(self, t: float) -> np.ndarray:
        """Return R_err (3x3) at sim time t: the autopilot's attitude estimate is R_IB R_err."""
        return rot_from_quat(self.error_quat(t))

    def noisy_attitude(self, R_IB: np.ndarray, t: float) -> np.ndarray:
        """Return the quaternion (w, x, y, z, w >= 0) of the estimate R_IB R_err at sim time t."""
        q = quat_multiply(quat_from_rot(R_IB), self.error_quat(t))
        return q if q[0] >= 0.0 else -q

    def noisy_rates(self, Omega_B: np.ndarray, t: float) -> np.ndarray:
        """Return the FRD rates (rad/s) plus gyro noise, as ATTITUDE_QUATERNION sends them."""
        return np.asarray(Omega_B, dtype=float) + self.rng_at(
            NoiseStream.ATTITUDE_RATES, int(round(t * US_PER_S))).normal(
            0.0, np.asarray(self.config.gyro_noise_std, dtype=float), 3)

    def noisy_imu(self, accel_B_specific: np.ndarray, Omega_B: np.ndarray,
                  t: float) -> tuple[np.ndarray, np.ndarray]:
        """Return (specific force m/s², rates rad/s) in FRD plus noise, as HIGHRES_IMU sends."""
        c = self.config
        rng = self.rng_at(NoiseStream.HIGHRES_IMU, int(round(t * US_PER_S)))
        acc = np.asarray(accel_B_specific, dtype=float) + rng.normal(
            0.0, np.asarray(c.accel_noise_std, dtype=float), 3)
        gyro = np.asarray(Omega_B, dtype=float) + rng.normal(
            0.0, np.asarray(c.gyro_noise_std, dtype=float), 3)
        return acc, gyro
