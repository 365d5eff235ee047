"""Hover-thrust seed and online estimator against a closed-form vehicle response.

The "vehicle" here is the model the estimator assumes, written out: a body-z specific force
a = g u b / theta_true (u the applied thrust, b the autopilot's own tilt boost) plus white
accelerometer noise, sampled at 100 Hz. The estimator must recover theta_true from a wrong seed.
"""
import numpy as np
import pytest

from ibvs_common.core.frames import GRAVITY
from ibvs_control.mavlink.hover import (
    EstimatorConfig, HoverThrustEstimator, HoverThrustSeed)

NS = 1_000_000_000
DT_NS = 10_000_000                 # 100 Hz


def fly(est, theta_true, seconds, t0_ns=0, noise=0.5, boost=1.0, estimator_boost=None,
        airborne=True, seed=0, u_mean=None):
    """Feed ``seconds`` of samples; return the boot time after the last one."""
    rng = np.random.default_rng(seed)
    n = int(seconds * NS / DT_NS)
    u_mean = theta_true if u_mean is None else u_mean
    for k in range(n):
        t = t0_ns + k * DT_NS
        u = u_mean + 0.05 * np.sin(2 * np.pi * 0.7 * k * DT_NS / NS)   # the controller works
        a = GRAVITY * u * boost / theta_true + rng.normal(0.0, noise)
        est.update(t, -a, abs(a), u, boost if estimator_boost is None else estimator_boost,
                   airborne)
    return t0_ns + n * DT_NS


def test_converges_from_a_wrong_seed_to_the_true_hover_thrust():
    est = HoverThrustEstimator(EstimatorConfig(accel_noise=2.0))
    est.start(0.5)
    fly(est, 0.42, 5.0)
    assert est.theta == pytest.approx(0.42, abs=0.003)
    assert est.std < 0.01               # as the filter sees it, with 2 m/s^2 of assumed noise
    assert est.accepted == 500 and est.rejected == 0


@pytest.mark.parametrize('theta_true, seed', [(0.49, 0.5), (0.35, 0.39), (0.5, 0.5)])
def test_converges_within_two_seconds_for_the_three_autopilots(theta_true, seed):
    # PX4 SIH (0.49, seed MPC_THR_HOVER 0.5), ArduCopter SITL (~0.35, MOT_THST_HOVER 0.39),
    # the sim (0.5 = vehicle.yaml): vibration noise 2 m/s^2 as on a real frame
    est = HoverThrustEstimator()
    est.start(seed)
    fly(est, theta_true, 2.0, noise=2.0)
    assert est.theta == pytest.approx(theta_true, abs=0.01)


def test_the_autopilots_own_tilt_boost_is_part_of_the_model():
    # ArduPilot ATC_ANGLE_BOOST = 1 reports the thrust before its 1/cos(tilt) boost: without
    # the boost in the model the estimate would be 1/cos(tilt) too low... or high
    cos_tilt = np.cos(np.radians(25.0))
    est = HoverThrustEstimator()
    est.start(0.4)
    fly(est, 0.35, 5.0, boost=1.0 / cos_tilt)
    assert est.theta == pytest.approx(0.35, abs=0.003)
    naive = HoverThrustEstimator()
    naive.start(0.4)
    fly(naive, 0.35, 5.0, boost=1.0 / cos_tilt, estimator_boost=1.0)
    assert naive.theta == pytest.approx(0.35 * cos_tilt, abs=0.005)


def test_bounded_around_the_seed():
    est = HoverThrustEstimator(EstimatorConfig(max_deviation=0.3))
    est.start(0.5)
    fly(est, 0.3, 5.0, u_mean=0.35)
    assert est.theta == pytest.approx(0.35)          # 0.5 * (1 - 0.3)


def test_nothing_learnt_on_the_ground_outside_the_thrust_range_or_from_outliers():
    est = HoverThrustEstimator()
    est.start(0.5)
    fly(est, 0.4, 1.0, airborne=False)
    assert est.accepted == 0 and est.theta == 0.5
    assert not est.update(0, -GRAVITY, GRAVITY, 0.05, 1.0, True)      # idle thrust
    assert not est.update(0, -GRAVITY, GRAVITY, 0.95, 1.0, True)      # saturated
    assert not est.update(0, -4 * GRAVITY, 4 * GRAVITY, 0.5, 1.0, True)   # > 3 g: a shock
    fly(est, 0.4, 3.0)
    n = est.accepted
    assert not est.update(4 * NS, -25.0, 25.0, 0.4, 1.0, True)      # 15 m/s^2 off: gated
    assert est.rejected == 1 and est.accepted == n
    disabled = HoverThrustEstimator(EstimatorConfig(enabled=False))
    disabled.start(0.5)
    fly(disabled, 0.4, 1.0)
    assert disabled.accepted == 0 and disabled.value_at(NS) == 0.5


def test_tracks_a_change_of_hover_thrust():
    # e.g. a payload picked up: 0.45 -> 0.5; the process noise lets the estimate follow
    est = HoverThrustEstimator()
    est.start(0.45)
    t = fly(est, 0.45, 10.0, noise=2.0)
    fly(est, 0.5, 10.0, t0_ns=t, noise=2.0, seed=1)
    assert est.theta == pytest.approx(0.5, abs=0.01)


def test_value_at_uses_only_samples_older_than_the_margin():
    # The setpoint of stamp S uses the estimate of the samples up to S - margin: the same
    # value whether or not the bridge has already read the samples after that.
    cfg = EstimatorConfig(margin_s=0.1)
    a, b = HoverThrustEstimator(cfg), HoverThrustEstimator(cfg)
    a.start(0.5)
    b.start(0.5)
    fly(a, 0.42, 2.0)
    fly(b, 0.42, 1.915)                      # b has not read the last 0.1 s yet
    S = 2 * NS
    assert a.value_at(S) == b.value_at(S) == b.theta
    assert a.value_at(S) != a.theta
    assert a.value_at(0) == 0.5              # before any sample: the seed
    assert a.value_at(None) == a.theta       # None: the latest


def test_seed_from_the_autopilot_or_the_configured_value():
    s = HoverThrustSeed(0.5, use_autopilot=True)
    assert s.value is None and s.source == 'pending'
    s.on_param('MPC_THR_HOVER', 0.48)
    assert (s.value, s.source) == (0.48, 'autopilot MPC_THR_HOVER')
    bad = HoverThrustSeed(0.5, use_autopilot=True)
    bad.on_param('MOT_THST_HOVER', 1.2)
    assert bad.value == 0.5 and 'refused' in bad.source and bad.error
    late = HoverThrustSeed(0.5, use_autopilot=True)
    late.on_timeout()
    assert late.value == 0.5 and 'did not answer' in late.source
    assert HoverThrustSeed(0.45, use_autopilot=False).value == 0.45


def test_a_touchdown_at_low_thrust_is_not_learnt():
    # On the ground the specific force stays g whatever the thrust: far below the estimate,
    # such samples are not used (the land detector may still say "in the air").
    est = HoverThrustEstimator()
    est.start(0.49)
    fly(est, 0.49, 2.0)
    theta, n = est.theta, est.accepted
    for k in range(300):                       # 3 s resting at thrust 0.15 -> 0.05
        u = 0.15 - 0.1 * k / 300
        est.update(3 * NS + k * DT_NS, -GRAVITY, GRAVITY, u, 1.0, True)
    assert est.accepted == n and est.theta == theta
