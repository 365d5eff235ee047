"""DisturbanceObserver (ibvs_control/core/observer.py): the IMU channel and the velocity channel.

Independent values: the first-order step response in closed form, and pushes made up of a
part the IMU sees (a wind: in the specific force) and a part it cannot see (an estimate
error's push: only in the velocity), which the estimate must recover separately.
"""
from dataclasses import replace

import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_common.core.frames import bearings_I_to_C, e3, GRAVITY
from ibvs_common.core.modes import Mode
from ibvs_control.core.control_laws import DisturbanceLaw, GainError, ObserverGains
from ibvs_control.core.controller import ControllerConfig, IbvsController, Measurements
from ibvs_control.core.observer import DisturbanceObserver
from ibvs_sim.core.world import load_world

M = 1.676                          # kg
DT = 0.02                          # s, one camera frame
HOVER = M * GRAVITY * e3           # N, F_app of a level hover


def fly(obs: DisturbanceObserver, seconds: float, wind, unseen, v0=None, velocity=True):
    """Feed ``seconds`` of hover: ``wind`` in f_I and v, ``unseen`` in v only (m/s^2, {I})."""
    wind, unseen = np.asarray(wind, float), np.asarray(unseen, float)
    v = np.zeros(3) if v0 is None else np.array(v0, float)
    for _ in range(int(round(seconds / DT))):
        v = v + DT * (wind + unseen)                 # m v' = -F_app + m g e3 + Delta, hover
        f_I = -HOVER / M + wind                      # what the IMU reads (estimate-rotated)
        obs.update(DT, f_I, HOVER, v if velocity else None)
    return v


def test_the_imu_channel_alone_is_the_first_order_low_pass_in_closed_form():
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.0), M)
    wind = np.array([0.3, -0.2, 0.1])
    fly(obs, 1.0, wind, np.zeros(3))
    expected = wind * (1.0 - (1.0 - DT / 0.5) ** 50)       # Euler steps of dt / tau
    assert obs.d_imu == pytest.approx(expected, rel=1e-12)
    assert np.array_equal(obs.estimate, obs.d_imu) and not obs.velocity_aided
    assert np.array_equal(obs.bias, np.zeros(3))             # off: velocity ignored


def test_the_velocity_channel_finds_the_push_the_imu_cannot_see_and_holds_it():
    """0.29 m/s^2 sideways (1.7 deg of roll-estimate error) unseen, 0.2 along x a wind."""
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.2), M)
    wind, unseen = np.array([0.2, 0.0, 0.0]), np.array([0.0, -0.29, 0.0])
    v = fly(obs, 6.0, wind, unseen)
    assert obs.d_imu == pytest.approx(wind, abs=1e-6)        # the IMU: the wind only
    assert obs.bias == pytest.approx(unseen, abs=1e-4)       # the rest, from the velocity
    assert obs.estimate == pytest.approx(wind + unseen, abs=1e-4)
    # no velocity any more (the blind crossing): the correction is held, the IMU goes on
    bias = obs.bias.copy()
    fly(obs, 3.0, 2 * wind, unseen, v0=v, velocity=False)
    assert np.array_equal(obs.bias, bias)
    assert obs.estimate == pytest.approx(2 * wind + unseen, abs=2e-3)


def test_the_correction_is_horizontal_only():
    """A vertical push the IMU does not see (e.g. a flow error) is not taken into b."""
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.2), M)
    fly(obs, 6.0, np.zeros(3), [0.1, -0.2, 0.3])
    assert obs.bias == pytest.approx([0.1, -0.2, 0.0], abs=1e-4)


def test_a_wind_both_channels_see_is_not_counted_twice():
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.2), M)
    fly(obs, 6.0, [0.0, 0.5, -0.1], np.zeros(3))
    assert obs.bias == pytest.approx(np.zeros(3), abs=1e-4)
    assert obs.estimate == pytest.approx([0.0, 0.5, -0.1], abs=1e-4)


def test_the_velocity_channel_starts_bumpless_and_refuses_non_finite_velocity():
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.2), M)
    fly(obs, 2.0, [0.1, 0.0, 0.0], np.zeros(3), velocity=False)
    before = obs.estimate
    obs.update(DT, -HOVER / M + np.array([0.1, 0.0, 0.0]), HOVER, np.array([1.0, 2.0, 3.0]))
    assert np.array_equal(obs.bias, np.zeros(3))             # first sample: only a start
    assert obs.estimate == pytest.approx(before, abs=1e-3)
    obs.update(DT, -HOVER / M, HOVER, np.array([np.nan, 0.0, 0.0]))
    assert np.all(np.isfinite(obs.estimate)) and np.array_equal(obs.bias, np.zeros(3))


def test_the_correction_is_clamped_and_bad_gains_are_refused():
    obs = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.2, bias_max=0.1), M)
    fly(obs, 6.0, np.zeros(3), [0.0, -0.5, 0.0])
    assert np.linalg.norm(obs.bias) == pytest.approx(0.1)
    for bad in ({'bias_tau_s': -0.1}, {'bias_max': 0.0}, {'tau_s': 0.0}):
        with pytest.raises(GainError):
            replace(ObserverGains(), **bad).validate()


def test_the_controller_feeds_the_window_distance_times_the_wall_flow():
    """v = d_o phi_wall in WINDOW: d_o from the corners and r_w, here the wall 1.5 m ahead."""
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    cfg = ControllerConfig.from_params({'disturbance_law': 'observer_integral',
                                        'observer.bias_tau_s': 0.2}, vehicle,
                                       world.window.width, pad)
    ctrl = IbvsController(cfg)
    xi = np.array([world.window.center_I[0] - 1.5, 0.2, -1.5])
    P = world.window.corners_I() - xi
    b_C = bearings_I_to_C(P / np.linalg.norm(P, axis=1, keepdims=True), np.eye(3),
                          vehicle.cameras['front'].R_BC)
    v_true = np.array([0.3, -0.1, 0.05])
    meas = Measurements(t=0.0, R_IB=np.eye(3), window_bearings_C=b_C, pad_bearings_C=None,
                        phi_front_I=v_true / 1.5, phi_down_I=None)
    p_I = ctrl._window_bearings_I(meas, np.eye(3))
    win = ctrl._window_features(p_I)
    assert ctrl._window_velocity(meas.phi_front_I, p_I, win) == pytest.approx(v_true, rel=1e-9)
    off = IbvsController(replace(cfg, observer=ObserverGains(bias_tau_s=0.0)))
    assert off._window_velocity(meas.phi_front_I, p_I, win) is None
    assert cfg.disturbance_law == DisturbanceLaw.OBSERVER_INTEGRAL
    ctrl.step(Mode.WINDOW, meas)                    # and step() takes it without complaint


def test_a_step_time_constant_overrides_the_gains_and_a_zero_one_holds():
    """update(bias_tau_s=...): LANDING's own time constant, with WINDOW's channel off."""
    unseen = np.array([0.0, 0.12, 0.0])             # 0.7 deg of roll-estimate error
    fast = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.0), M)
    slow = DisturbanceObserver(ObserverGains(tau_s=0.5, bias_tau_s=0.0), M)
    v_fast, v_slow = np.zeros(3), np.zeros(3)
    for _ in range(int(round(1.0 / DT))):
        v_fast, v_slow = v_fast + DT * unseen, v_slow + DT * unseen
        fast.update(DT, -HOVER / M, HOVER, v_fast, bias_tau_s=0.1)
        slow.update(DT, -HOVER / M, HOVER, v_slow, bias_tau_s=1.0)
    assert np.linalg.norm(fast.bias - unseen) < np.linalg.norm(slow.bias - unseen)
    fly(fast, 6.0, np.zeros(3), unseen)            # the gains' own 0: velocity ignored, held
    held = fast.bias.copy()
    assert np.linalg.norm(held - unseen) < 0.03
    for _ in range(50):
        fast.update(DT, -HOVER / M, HOVER, np.array([5.0, 5.0, 0.0]), bias_tau_s=0.0)
    assert np.array_equal(fast.bias, held)
    for bad in ({'landing_bias_tau_s': -0.1}, {'landing_bias_tau_s': float('nan')}):
        with pytest.raises(GainError):
            replace(ObserverGains(), **bad).validate()


def test_the_controller_feeds_the_pad_height_times_the_floor_flow_in_landing():
    """v = h phi_floor in LANDING: h from the smallest complete pad group (any offset)."""
    from ibvs_harness.feature_sim import FeatureSensors
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    cfg = ControllerConfig.from_params({'disturbance_law': 'observer_integral',
                                        'observer.landing_bias_tau_s': 0.1}, vehicle,
                                       world.window.width, pad)
    ctrl = IbvsController(cfg)
    sensors = FeatureSensors(world, pad, vehicle, np.random.default_rng(0), 0.0, 0.0)
    xi = np.array([0.05, -0.03, world.floor_z - 0.6])          # 0.6 m up, off the centre
    v_true = np.array([0.1, -0.05, 0.25])
    p_C, groups = sensors.pad_landmarks(np.eye(3), xi)
    assert groups                                                 # the geometry sees a group
    meas = Measurements(t=0.0, R_IB=np.eye(3), window_bearings_C=None, pad_bearings_C=p_C,
                        phi_front_I=None, phi_down_I=sensors.flow_down(xi, v_true),
                        pad_groups=tuple(groups))
    height = ctrl._pad_height(meas, np.eye(3))
    assert height == pytest.approx(0.6, rel=1e-6)
    assert ctrl._landing_velocity(meas.phi_down_I, height) == pytest.approx(v_true, rel=1e-6)
    assert ctrl._landing_velocity(meas.phi_down_I, None) is None       # no complete group
    assert ctrl._landing_velocity(meas.phi_down_I, 0.01) is None       # implausible height
    off = IbvsController(replace(cfg, observer=ObserverGains(landing_bias_tau_s=0.0)))
    assert off._landing_velocity(meas.phi_down_I, height) is None
    ctrl.step(Mode.LANDING, meas)                  # and step() takes it without complaint
