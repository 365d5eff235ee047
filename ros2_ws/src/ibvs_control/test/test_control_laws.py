"""Force laws, gain checks and force -> attitude: stated signs tested against physics."""
import numpy as np
import pytest

from ibvs_control.core import control_laws as cl
from ibvs_control.core.attitude import (
    attitude_from_force, limit_tilt, shutdown_thrust_scale, yaw_facing)
from ibvs_common.core.frames import e3, euler_zyx_from_rot, GRAVITY, rot_x, rot_z

M = 1.676
ETA_W = np.array([1.0, 0.0, 0.0])


def accel(F):
    """Acceleration the force commands, from eq:system with Delta = 0."""
    return (-np.asarray(F) + M * GRAVITY * e3) / M


def test_landing_force_attracts_to_pad_and_damps():
    # vehicle 0.5 m to the right (+y) of the pad, 1 m up: bearings to the pad centre
    xi = np.array([0.0, 0.5, -1.0])
    q_t = xi / np.linalg.norm(xi)          # far-field value of q_t (points pad -> vehicle)
    a = accel(cl.force_landing(q_t, np.zeros(3), cl.LandingGains(), M))
    assert a[1] < 0.0                      # towards the pad laterally
    assert a[2] > 0.0                      # downwards (z down)
    v = np.array([0.3, 0.0, 0.0])
    a_v = accel(cl.force_landing(np.zeros(3), v / 1.0, cl.LandingGains(), M))
    assert np.allclose(a_v, -4.0 * v)      # K_d^t = 4 I damps the flow
    # robust variant eq:FT2: phi*_t > 0 keeps descending at zero flow
    a_r = accel(cl.force_landing(np.zeros(3), np.zeros(3), cl.LandingGains(phi_t_star=0.1), M))
    assert a_r[2] == pytest.approx(4.0 * 0.1)


def test_window_force_equilibrium_and_signs():
    d = 1.0
    # on the window axis, flying at the reference flow: only gravity compensation
    F = cl.force_window(-ETA_W, np.array([-1.0, 0, 0]), ETA_W * 0.3, ETA_W, cl.WindowGains(), M)
    assert np.allclose(F, M * GRAVITY * e3)
    # 0.2 m left of the axis (-y): pushed right; too slow along eta: pushed forward
    xi_w = np.array([-d, -0.2, 0.0])
    F = cl.force_window(-ETA_W, xi_w / d, np.zeros(3), ETA_W, cl.WindowGains(), M)
    a = accel(F)
    assert a[1] > 0.0 and a[0] == pytest.approx(0.3)
    # after the crossing (sigma = 0) only gravity compensation remains
    F = cl.force_window(ETA_W, xi_w / d, np.zeros(3), ETA_W, cl.WindowGains(), M)
    assert np.allclose(F, M * GRAVITY * e3)


def test_gain_schedule_near_the_ground():
    g = cl.LandingGains()                  # in-plane below 1.5 m, along eta_t below 0.8 m
    assert g.lateral_scale(None) == 1.0 and g.lateral_scale(2.0) == 1.0
    assert g.lateral_scale(0.75) == pytest.approx(0.5)
    assert g.lateral_scale(0.01) == g.lateral_scale_min
    assert g.vertical_scale(None) == 1.0 and g.vertical_scale(1.0) == 1.0
    assert g.vertical_scale(0.4) == pytest.approx(0.5)
    assert g.vertical_scale(0.01) == g.vertical_scale_min
    assert cl.LandingGains(lateral_schedule_height_m=0.0).lateral_scale(0.1) == 1.0   # off
    q_t = np.array([0.1, 0.0, -0.9])
    phi_t = np.array([0.2, 0.0, 0.3])
    full = accel(cl.force_landing(q_t, phi_t, g, M))
    half = accel(cl.force_landing(q_t, phi_t, g, M, lateral_scale=0.5))
    assert half[0] == pytest.approx(full[0] / 2) and half[2] == pytest.approx(full[2])
    third = accel(cl.force_landing(q_t, phi_t, g, M, vertical_scale=1 / 3))
    assert third[0] == pytest.approx(full[0]) and third[2] == pytest.approx(full[2] / 3)
    # eq:FT's effective damping K_d/d is bounded as d -> 0: lateral kd_xy/1.5 m, vertical
    # kd_z/0.8 m (until the scale's lower bound), instead of growing as 1/d
    for d in (1.5, 0.8, 0.4, 0.2):
        assert g.kd_xy * g.lateral_scale(d) / d <= g.kd_xy / 1.5 + 1e-9
        assert g.kd_z * g.vertical_scale(d) / d <= g.kd_z / 0.8 + 1e-9
    with pytest.raises(cl.GainError, match='vertical'):
        cl.LandingGains(vertical_scale_min=0.0).validate()


def test_gain_conditions_are_enforced():
    cl.WindowGains().validate(1.2)                       # the paper's: 0.64 > 0.6
    with pytest.raises(cl.GainError, match='r_w'):
        cl.WindowGains(kd=0.7).validate(1.2)             # 0.49 < 0.6
    with pytest.raises(cl.GainError):
        cl.WindowGains(phi_star=0.0).validate(1.2)
    with pytest.raises(cl.GainError):
        cl.LandingGains(kp_z=-1.0).validate()


def test_seed_mode2_law_brakes_and_intended_law_pushes():
    # F_w just before the loss: the vehicle slightly slower than the reference flow
    F_w = M * GRAVITY * e3 + M * np.array([-0.1, 0.02, 0.0])
    a_seed = accel(cl.force_crossing_seed(F_w, ETA_W))
    assert a_seed[0] < 0.0                  # brakes along eta_w: the SPEC's defect
    assert a_seed[2] == pytest.approx(GRAVITY)   # and no gravity compensation
    a_int = accel(cl.force_crossing_intended(F_w, ETA_W, M))
    assert a_int[0] == pytest.approx(0.1) and a_int[2] == pytest.approx(0.0)


def test_closed_mode2_law_holds_position_and_speed():
    F_w = M * GRAVITY * e3 + M * np.array([0.0, -0.2, 0.0])   # was balancing a side wind
    phi_ref = 0.15
    a = accel(cl.force_crossing_closed(F_w, ETA_W, ETA_W * phi_ref, np.zeros(3), phi_ref,
                                       cl.CrossingGains(), M))
    assert np.allclose(a, [0.0, 0.2, 0.0])    # keeps the wind compensation, nothing else
    a = accel(cl.force_crossing_closed(M * GRAVITY * e3, ETA_W, np.array([0.05, 0.1, 0.0]),
                                       np.array([0.0, 0.1, 0.0]), phi_ref,
                                       cl.CrossingGains(), M))
    assert a[0] > 0.0 and a[1] < 0.0          # speeds up towards phi_ref, resists drift


def test_hover_and_yaw_setpoint():
    sp = attitude_from_force(M * GRAVITY * e3, 0.0, M, 0.5)
    assert np.allclose(sp.R_IB_des, np.eye(3)) and sp.thrust_norm == pytest.approx(0.5)
    sp = attitude_from_force(M * GRAVITY * e3, np.pi / 2, M, 0.5)
    assert np.allclose(sp.q_IB_wxyz, [np.sqrt(.5), 0, 0, np.sqrt(.5)])


def test_forward_acceleration_needs_nose_down():
    a_des = np.array([1.0, 0.0, 0.0])                 # accelerate along +x (forward)
    sp = attitude_from_force(M * GRAVITY * e3 - M * a_des, 0.0, M, 0.5)
    roll, pitch, yaw = euler_zyx_from_rot(sp.R_IB_des)
    assert pitch < 0.0 and abs(roll) < 1e-12          # FRD/NED: negative pitch = nose down
    assert np.tan(-pitch) == pytest.approx(1.0 / GRAVITY)
    # rightward acceleration (+y) needs a right roll (positive roll in FRD)
    sp = attitude_from_force(M * GRAVITY * e3 - M * np.array([0, 1.0, 0]), 0.0, M, 0.5)
    assert euler_zyx_from_rot(sp.R_IB_des)[0] > 0.0
    # thrust vector is preserved: R_d e3 |F| = F
    F = np.array([1.0, -2.0, 15.0])
    sp = attitude_from_force(F, 0.3, M, 0.5)
    assert np.allclose(sp.R_IB_des[:, 2] * sp.thrust_N, F)
    assert euler_zyx_from_rot(sp.R_IB_des)[2] == pytest.approx(0.3)


def test_tilt_limit_keeps_vertical_part_and_nan_refused():
    F = limit_tilt(np.array([100.0, 0.0, 10.0]), 0.5)
    assert F[2] == 10.0 and np.arctan2(F[0], F[2]) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        attitude_from_force(np.array([np.nan, 0, 1.0]), 0.0, M, 0.5)


def test_yaw_facing_with_spec_and_paper_mounts():
    spec_front = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
    assert yaw_facing(ETA_W, spec_front) == pytest.approx(0.0)
    assert yaw_facing(np.array([0.0, 1.0, 0.0]), spec_front) == pytest.approx(np.pi / 2)
    paper_front = rot_z(-np.pi / 4) @ rot_x(np.pi / 2)       # paper's mount
    psi = yaw_facing(ETA_W, paper_front)
    axis_I = rot_z(psi) @ paper_front[:, 2]
    assert np.allclose(axis_I / np.linalg.norm(axis_I[:2]), [1, 0, axis_I[2] / np.linalg.norm(
        axis_I[:2])], atol=1e-9)


def test_shutdown_ramp():
    assert shutdown_thrust_scale(0.0, 2.0) == 1.0
    assert shutdown_thrust_scale(1.0, 2.0) == pytest.approx(0.5)
    assert shutdown_thrust_scale(5.0, 2.0) == 0.0
