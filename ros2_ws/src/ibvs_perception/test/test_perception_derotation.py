"""Gyro-based derotation: integration against closed forms, noise rejection, no drift."""
import cv2
import numpy as np

from ibvs_common.core.attitude_buffer import AttitudeBuffer, AttitudeBufferConfig
from ibvs_perception.core.derotation import GyroDerotation


def expm(w):
    return cv2.Rodrigues(np.asarray(w, dtype=float).reshape(3, 1))[0]


def angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


OMEGA = np.array([0.4, -0.7, 0.9])          # rad/s, body FRD, constant
R0 = expm([0.1, 0.2, -0.3])


def filled_buffer(noise_rad=0.0, seed=0, t_end=2.0, dt=0.005):
    rng = np.random.default_rng(seed)
    buf = AttitudeBuffer(AttitudeBufferConfig(history_s=10.0))
    for t in np.arange(0.0, t_end + 1e-9, dt):
        R = R0 @ expm(OMEGA * t) @ expm(rng.normal(0.0, noise_rad, 3))
        buf.add(float(t), R, OMEGA)
    return buf


def test_gyro_rotation_is_the_closed_form_for_a_constant_rate():
    buf = filled_buffer()
    dR = buf.gyro_rotation(0.013, 0.067)
    assert angle(dR.T @ expm(OMEGA * 0.054)) < 1e-9
    assert buf.gyro_rotation(0.5, 0.4) is None            # backwards
    assert buf.gyro_rotation(-1.0, 0.1) is None           # before the buffer
    assert buf.gyro_rotation(1.9, 2.5) is None            # too far after the newest sample


def test_frame_to_frame_rotation_comes_from_the_gyro_not_the_noisy_attitude():
    noise = np.radians(0.2)
    buf = filled_buffer(noise_rad=noise, seed=1)
    derot = GyroDerotation(buf, gain=0.05)
    frames = np.arange(0.1, 1.9, 0.02)
    Rs = [derot.at_frame(float(t)) for t in frames]
    true_rel = expm(OMEGA * 0.02)
    rel_err = [angle((a.T @ b).T @ true_rel) for a, b in zip(Rs[:-1], Rs[1:])]
    raw = [buf.attitude_at(float(t)) for t in frames]
    raw_err = [angle((a.T @ b).T @ true_rel) for a, b in zip(raw[:-1], raw[1:])]
    assert np.sqrt(np.mean(np.square(rel_err))) < 0.1 * np.sqrt(np.mean(np.square(raw_err)))
    # and the absolute attitude stays within the measurement noise (no drift)
    abs_err = [angle(R.T @ R0 @ expm(OMEGA * t)) for R, t in zip(Rs, frames)]
    assert max(abs_err[20:]) < 5 * noise


def test_derotation_resets_without_imu_coverage():
    buf = filled_buffer(t_end=0.5)
    derot = GyroDerotation(buf)
    assert derot.at_frame(0.2) is not None
    assert derot.at_frame(3.0) is None
