"""The wind model shared by the image-level sim and the feature-level loop (issue 14 item 2).

Reference values are computed here by hand from the documented formula (docs/sim.md "Wind"):
each gust axis j is a sum of K sines of amplitude A w_j / sqrt(K) at distinct frequencies, so
over a long window its mean is 0 and its standard deviation A w_j / sqrt(2), w = (1, 1, 0.5).
"""
import math

import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_control.core.controller import ControllerConfig
from ibvs_control.core.supervisor import SupervisorConfig
from ibvs_sim.core.dynamics import Wind, WindConfig
from ibvs_harness.feature_sim import FeatureSimConfig, run_feature_scenario
from ibvs_sim.core.world import load_world

MASS = 1.676          # kg, docs/spec.md's vehicle


def _samples(wind: Wind, t_end: float = 400.0, dt: float = 0.01) -> np.ndarray:
    return np.array([wind.force_I(t) for t in np.arange(0.0, t_end, dt)])


@pytest.mark.parametrize('components', [1, 4])
def test_gust_mean_zero_and_std_is_amplitude_over_sqrt2(components):
    A = 0.6               # N
    w = Wind(WindConfig(gust_amplitude_N=A, gust_frequency_hz=0.5, seed=7,
                        gust_components=components))
    s = _samples(w)
    assert s.mean(axis=0) == pytest.approx([0.0, 0.0, 0.0], abs=0.01)
    # A / sqrt(2) = 0.42426 N horizontally, half of it vertically
    assert s.std(axis=0) == pytest.approx([0.42426, 0.42426, 0.21213], rel=0.02)


def test_single_component_peak_is_the_amplitude_and_more_components_spread_it():
    one = _samples(Wind(WindConfig(gust_amplitude_N=1.0, seed=2)))
    four = _samples(Wind(WindConfig(gust_amplitude_N=1.0, seed=2, gust_components=4)))
    assert np.abs(one[:, 0]).max() == pytest.approx(1.0, abs=0.005)
    assert np.abs(one[:, 2]).max() == pytest.approx(0.5, abs=0.005)
    # four sines of amplitude 1/2: peaks beyond a single sine's, below the bound sqrt(4) = 2
    assert 1.2 < np.abs(four[:, 0]).max() < 2.0


def test_gusts_are_seeded():
    cfg = WindConfig(steady_force_I=(0.1, 0.2, 0.0), gust_amplitude_N=0.3, seed=5,
                     gust_components=3)
    a, b = Wind(cfg), Wind(cfg)
    c = Wind(WindConfig(steady_force_I=(0.1, 0.2, 0.0), gust_amplitude_N=0.3, seed=6,
                        gust_components=3))
    t = 12.34
    assert np.array_equal(a.force_I(t), b.force_I(t))
    assert not np.allclose(a.force_I(t), c.force_I(t))


def test_direction_towards_north_pushes_plus_x():
    """``direction_rad`` is where the wind blows TOWARDS, from north (+x_I) towards east."""
    north = WindConfig.from_level(0.2, 0.0, MASS)
    assert north.steady_force_I == pytest.approx((0.3352, 0.0, 0.0))     # 0.2 m/s^2 x 1.676 kg
    east = WindConfig.from_level(0.2, math.pi / 2, MASS)
    assert east.steady_force_I == pytest.approx((0.0, 0.3352, 0.0), abs=1e-12)
    south_west = WindConfig.from_level(0.5, 5 * math.pi / 4, MASS)
    assert south_west.steady_force_I == pytest.approx((-0.59255, -0.59255, 0.0), abs=1e-5)
    assert Wind(north).force_I(3.0) == pytest.approx([0.3352, 0.0, 0.0])


def test_vertical_factor_and_gust_level():
    w = WindConfig.from_level(0.5, 0.0, MASS, vertical_factor=0.3, gust_level=0.3,
                              gust_frequency_hz=0.4, gust_components=2, seed=9)
    # 0.5 m/s^2 x 1.676 kg = 0.838 N; x 0.3 = 0.2514 N down (+z_I); gusts A = 0.2514 N
    assert w.steady_force_I == pytest.approx((0.838, 0.0, 0.2514))
    assert w.gust_amplitude_N == pytest.approx(0.2514)
    assert (w.gust_frequency_hz, w.gust_components, w.seed) == (0.4, 2, 9)
    assert WindConfig.from_level(0.0, 1.0, MASS, 0.3, 0.3).gust_amplitude_N == 0.0
    with pytest.raises(ValueError):
        WindConfig.from_level(-0.1, 0.0, MASS)
    with pytest.raises(ValueError):
        Wind(WindConfig(gust_components=0))


WORLD, PAD, VEHICLE = load_world(), load_pad_layout(), load_vehicle()
CTRL = ControllerConfig.from_params({}, VEHICLE, WORLD.window.width)
SUP = SupervisorConfig(r_w=WORLD.window.width)


def _fly(**kw):
    cfg = FeatureSimConfig(initial_position_I=WORLD.initial_position_I, **kw)
    return run_feature_scenario(WORLD, PAD, VEHICLE, CTRL, SUP, cfg)


def test_feature_loop_constant_wind_two_ways_and_gusts():
    """A constant wind as wind_accel_I (m/s^2) or as a WindConfig (N) flies the same run."""
    a = np.array([0.0, 0.2, 0.0])
    s_accel, log_accel = _fly(wind_accel_I=a)
    s_force, log_force = _fly(wind=WindConfig(steady_force_I=tuple(a * VEHICLE.mass)))
    _, xa, _ = log_accel.truth.arrays()
    _, xf, _ = log_force.truth.arrays()
    assert len(xa) == len(xf)
    assert np.abs(xa - xf).max() < 1e-6
    assert s_accel['landing']['error_m'] == pytest.approx(s_force['landing']['error_m'],
                                                          abs=1e-6)
    # gusts on top move the trajectory (by millimetres to centimetres), deterministically
    gusty = WindConfig(steady_force_I=tuple(a * VEHICLE.mass), gust_amplitude_N=0.1, seed=1)
    _, log_g1 = _fly(wind=gusty)
    _, log_g2 = _fly(wind=gusty)
    _, xg1, _ = log_g1.truth.arrays()
    _, xg2, _ = log_g2.truth.arrays()
    assert np.array_equal(xg1, xg2)
    n = min(len(xg1), len(xa))
    assert np.abs(xg1[:n] - xa[:n]).max() > 1e-3
