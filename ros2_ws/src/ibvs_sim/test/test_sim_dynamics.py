"""Plant and inner attitude loop of ibvs_sim against closed forms and measured responses."""
import math

import numpy as np
import pytest

from ibvs_common.core.config import load_vehicle
from ibvs_common.core.frames import (GRAVITY, euler_zyx_from_rot, exp_so3, quat_from_rot,
                                     rot_from_euler_zyx)
from ibvs_sim.testing import second_order_step
from ibvs_sim.core.dynamics import (AttitudeController, Mixer, PlantParams, QuadrotorPlant,
                                    State, Wind, WindConfig, hover_state)


@pytest.fixture(scope='module')
def params():
    return PlantParams.from_vehicle(load_vehicle())


def _run(plant, state, cmd_fn, duration, delta=np.zeros(3)):
    n = int(round(duration / plant.p.dt))
    for _ in range(n):
        state = plant.step(state, cmd_fn(state), delta)
    return state


def test_free_fall_matches_closed_form(params):
    plant = QuadrotorPlant(params)
    s = State(np.array([0.0, 0.0, -20.0]), np.zeros(3), np.eye(3), np.zeros(3), np.zeros(4))
    t = 1.0
    s = _run(plant, s, lambda _: np.zeros(4), t)
    assert s.v_I == pytest.approx([0.0, 0.0, GRAVITY * t], abs=1e-9)
    assert s.xi_I == pytest.approx([0.0, 0.0, -20.0 + 0.5 * GRAVITY * t ** 2], abs=1e-9)
    assert plant.last_specific_force_B == pytest.approx([0, 0, 0], abs=1e-9)  # weightless


def test_hover_is_an_equilibrium(params):
    plant = QuadrotorPlant(params)
    R = rot_from_euler_zyx(0.0, 0.0, 0.7)
    s = hover_state(params, np.array([-2.0, 0.1, -1.82]), R)
    s = _run(plant, s, lambda _: np.full(4, params.mass * GRAVITY / 4), 2.0)
    assert s.xi_I == pytest.approx([-2.0, 0.1, -1.82], abs=1e-9)
    assert np.allclose(s.R_IB, R, atol=1e-9)
    assert plant.last_specific_force_B == pytest.approx([0, 0, -GRAVITY], abs=1e-9)


def test_rotor_lag_first_order(params):
    plant = QuadrotorPlant(params)
    s = hover_state(params, np.array([0.0, 0.0, -10.0]), np.eye(3))
    T0 = s.rotor_thrust[0]
    cmd = np.full(4, 1.3 * T0)
    n = 6
    s = _run(plant, s, lambda _: cmd, n * params.dt)
    expected = cmd[0] + (T0 - cmd[0]) * math.exp(-n * params.dt / params.tau_up)
    assert s.rotor_thrust == pytest.approx(np.full(4, expected), rel=1e-9)


def test_single_rotor_torque_by_cross_product(params):
    """Extra thrust on the front-right rotor: Gamma = r x (-dT e3) + k_m dT e3 (CCW)."""
    mixer = Mixer(params)
    dT = 1.0
    T = np.zeros(4)
    T[0] = dT
    F, Gamma = mixer.wrench(T)
    r = params.arm_length / math.sqrt(2) * np.array([1.0, 1.0, 0.0])
    expected = np.cross(r, [0.0, 0.0, -dT]) + params.moment_constant * dT * np.array([0, 0, 1])
    assert F == pytest.approx(dT)
    assert Gamma == pytest.approx(expected)
    # front-right pushing up: roll left (negative) and pitch up (positive) in FRD
    assert Gamma[0] < 0 and Gamma[1] > 0


def test_angular_acceleration_from_torque(params):
    plant = QuadrotorPlant(params)
    hover = params.mass * GRAVITY / 4
    s = hover_state(params, np.array([0.0, 0.0, -10.0]), np.eye(3))
    s.rotor_thrust = np.array([hover + 0.2, hover, hover, hover])
    cmd = s.rotor_thrust.copy()
    t = 0.01
    s = _run(plant, s, lambda _: cmd, t)
    Gamma = Mixer(params).wrench(cmd)[1]
    assert s.Omega_B == pytest.approx(Gamma / params.inertia_diag * t, rel=1e-3)


def test_mixer_respects_rotor_limits(params):
    mixer = Mixer(params)
    T = mixer.allocate(params.mass * GRAVITY, np.array([0.3, -0.2, 0.05]))
    F, Gamma = mixer.wrench(T)
    assert F == pytest.approx(params.mass * GRAVITY) and Gamma == pytest.approx([0.3, -0.2, 0.05])
    big = np.array([30.0, 0.0, 0.0])
    T = mixer.allocate(params.mass * GRAVITY, big)
    assert np.all(T <= params.rotor_thrust_max + 1e-12) and np.all(T >= params.rotor_thrust_min)
    F, Gamma = mixer.wrench(T)
    assert F == pytest.approx(params.mass * GRAVITY)       # thrust priority
    assert Gamma[0] > 0 and abs(Gamma[1]) < 1e-9           # same direction, scaled down
    assert mixer.allocate(1e3, np.zeros(3)) == pytest.approx(np.full(4, params.rotor_thrust_max))


def test_linear_drag_decay(params):
    """Level flight at hover thrust: v_x(t) = v0 exp(-k_D t / m) (and no height change)."""
    plant = QuadrotorPlant(params)
    s = hover_state(params, np.array([0.0, 0.0, -10.0]), np.eye(3))
    s.v_I = np.array([2.0, 0.0, 0.0])
    t = 1.5
    s = _run(plant, s, lambda _: np.full(4, params.mass * GRAVITY / 4), t)
    expected = 2.0 * math.exp(-params.drag_coefficient * t / params.mass)
    assert s.v_I[0] == pytest.approx(expected, rel=2e-3)
    assert s.xi_I[2] == pytest.approx(-10.0, abs=1e-9)


def _step_response(params, roll=0.0, pitch=0.0, yaw=0.0, duration=0.6):
    plant = QuadrotorPlant(params)
    ctrl = AttitudeController(params)
    s = hover_state(params, np.array([0.0, 0.0, -10.0]), np.eye(3))
    q_d = quat_from_rot(rot_from_euler_zyx(roll, pitch, yaw))
    t, angles = [], []
    for k in range(int(duration / params.dt)):
        s = plant.step(s, ctrl.rotor_commands_q(s, q_d, 0.5), np.zeros(3))
        t.append((k + 1) * params.dt)
        angles.append(euler_zyx_from_rot(s.R_IB))
    return np.array(t), np.array(angles)


@pytest.mark.parametrize('axis, step', [(0, 0.05), (1, -0.08)])
def test_inner_loop_roll_pitch_step_follows_the_second_order_model(params, axis, step):
    """vehicle.yaml's loop (PX4 SIH's fit): nothing before the setpoint delay, then the
    closed-form response of (wn, zeta) (textbook, not the simulator's code), within the
    rotors' lag, which the model leaves out."""
    kwargs = {0: 'roll', 1: 'pitch'}
    t, ang = _step_response(params, **{kwargs[axis]: step}, duration=1.0)
    a = ang[:, axis] / step
    delay = round(params.setpoint_delay_s / params.dt) * params.dt
    assert params.setpoint_delay_s > 0.0
    assert np.all(np.abs(a[t <= delay]) < 1e-9)          # the setpoint has not arrived yet
    wn, zeta = params.attitude_wn, params.attitude_zeta
    model = second_order_step(t - delay, wn, zeta)

    def t63(x):
        return t[np.argmax(x >= 1.0 - math.exp(-1.0))]
    overshoot = math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta ** 2))
    print(f'{kwargs[axis]}: 63 % at {t63(a) * 1e3:.0f} ms (model {t63(model) * 1e3:.0f} ms), '
          f'overshoot {100 * (a.max() - 1):.1f} % (model {100 * overshoot:.1f} %)')
    # the rotors' lag, which the model leaves out, delays the damping torque as much as the
    # rest: the shape moves by no more than the slower rotor time constant
    assert abs(t63(a) - t63(model)) <= params.tau_down
    assert a.max() - 1.0 <= overshoot + 0.06
    assert abs(a[-1] - 1.0) < 0.01                        # settled


def test_inner_loop_yaw_step_overshoot_and_settling(params):
    """Yaw: the closed-form overshoot exp(-pi zeta / sqrt(1 - zeta^2)) of (yaw_wn, yaw_zeta)
    (16 % for PX4 SIH's fitted 0.5), settled within 2 % after 8 / (zeta wn)."""
    step = 0.1
    zeta, wn = params.yaw_zeta, params.yaw_wn
    t, ang = _step_response(params, yaw=step, duration=8.0 / (zeta * wn))
    a = ang[:, 2] / step
    overshoot = math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta ** 2))
    assert a.max() - 1.0 == pytest.approx(overshoot, abs=0.03)
    assert abs(a[-1] - 1.0) < 0.02


def test_floor_stops_a_falling_body(params):
    plant = QuadrotorPlant(params)
    s = State(np.array([0.0, 0.0, -0.5]), np.zeros(3), np.eye(3), np.zeros(3), np.zeros(4))
    s = _run(plant, s, lambda _: np.zeros(4), 1.0)
    assert s.xi_I[2] == pytest.approx(-params.envelope_height / 2)
    assert s.v_I == pytest.approx([0, 0, 0])
    # the impact speed is that of a free fall over 0.4 m (within one step)
    assert plant.last_impact_speed == pytest.approx(math.sqrt(2 * GRAVITY * 0.4), abs=0.03)


def test_wind_default_off_and_gust_mean(params):
    assert Wind(WindConfig()).force_I(3.0) == pytest.approx([0, 0, 0])
    w = Wind(WindConfig(steady_force_I=(0.3, -0.2, 0.0), gust_amplitude_N=0.5,
                        gust_frequency_hz=0.5, seed=4))
    samples = np.array([w.force_I(t) for t in np.arange(0.0, 200.0, 0.01)])
    assert samples.mean(axis=0) == pytest.approx([0.3, -0.2, 0.0], abs=0.02)
    assert np.abs(samples[:, 0] - 0.3).max() == pytest.approx(0.5, abs=0.01)


def test_wind_pushes_like_a_force(params):
    """A steady force on a hovering body: x(t) ~ F t^2 / (2 m) early on (drag negligible)."""
    plant = QuadrotorPlant(params)
    s = hover_state(params, np.array([0.0, 0.0, -10.0]), np.eye(3))
    t = 0.2
    s = _run(plant, s, lambda _: np.full(4, params.mass * GRAVITY / 4), t,
             delta=np.array([0.0, 0.5, 0.0]))
    assert s.xi_I[1] == pytest.approx(0.5 * t ** 2 / (2 * params.mass), rel=0.02)


@pytest.mark.parametrize('key, value', [('setpoint_delay', -0.01), ('setpoint_delay', 0.5),
                                        ('yaw_damping', 0.0), ('attitude_damping', -0.9),
                                        ('yaw_damping', None)])
def test_inner_loop_values_out_of_range_or_missing_are_refused(key, value):
    """A bad or missing inner-loop value in vehicle.yaml: a PlantConfigError naming the
    section, never a plant that runs on it."""
    import copy
    import dataclasses
    from ibvs_sim.core.dynamics import PlantConfigError, SIM_PLANT_KEY
    vehicle = load_vehicle()
    raw = copy.deepcopy(vehicle.raw)
    if value is None:
        del raw[SIM_PLANT_KEY][key]
    else:
        raw[SIM_PLANT_KEY][key] = value
    with pytest.raises(PlantConfigError, match=SIM_PLANT_KEY):
        PlantParams.from_vehicle(dataclasses.replace(vehicle, raw=raw))


def test_attitude_error_is_the_rotation_angle_for_small_errors():
    """e_R of R = R_d exp(S(a n)): sin(a) n (Lee et al.), so a for small a: a second method."""
    from ibvs_sim.core.dynamics import attitude_error
    R_d = rot_from_euler_zyx(0.2, -0.1, 0.7)
    n = np.array([1.0, 2.0, -2.0]) / 3.0
    for a in (1e-3, 0.3):
        e = attitude_error(R_d @ exp_so3(a * n), R_d)
        assert e == pytest.approx(math.sin(a) * n, abs=1e-12)
