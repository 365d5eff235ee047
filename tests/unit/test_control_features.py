"""Paper section 3 features against geometric ground truth (not against their own formulas)."""
import numpy as np
import pytest

from ibvs_common.core import features as ft
from ibvs_common.core.config import load_pad_layout
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import (
    bearings_C_to_I, bearings_I_to_C, proj_orth, R_BC_FRONT_DEFAULT, rot_from_euler_zyx)

WORLD = load_world()
CORNERS = WORLD.window.corners_I()
CENTRE = WORLD.window.center_I
RNG = np.random.default_rng(3)


def bearings(points_I, xi):
    P = np.asarray(points_I) - xi
    return P / np.linalg.norm(P, axis=1, keepdims=True)


def random_approach_position():
    return np.array([RNG.uniform(-2.6, -0.8), RNG.uniform(-0.3, 0.3), RNG.uniform(-1.9, -1.35)])


def closest_point_on_segment(a, b, x):
    t = np.clip((x - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return a + t * (b - a)


def test_q_t_is_negated_mean_bearing_and_points_back_to_the_vehicle():
    pad = load_pad_layout()
    xi = np.array([-0.4, 0.2, -1.5])
    for g in pad.groups:
        s = g.marker_centres_I()
        expected = -np.mean([(si - xi) / np.linalg.norm(si - xi) for si in s], axis=0)
        q = ft.centroid_feature(bearings(s, xi))
        assert np.allclose(q, expected)
        # far from the group, q_t is nearly the direction pad centre -> vehicle
        if g.c < 0.1:
            assert np.degrees(np.arccos(q @ xi / np.linalg.norm(q) / np.linalg.norm(xi))) < 0.5


def test_eta_w_from_rotated_camera_bearings_is_the_true_normal():
    for _ in range(30):
        xi = random_approach_position()
        R_IB = rot_from_euler_zyx(*RNG.uniform(-0.3, 0.3, 3))
        # what the camera sees, then the derotation the nodes apply
        b_C = bearings_I_to_C(bearings(CORNERS, xi), R_IB, R_BC_FRONT_DEFAULT)
        p_I = bearings_C_to_I(b_C, R_IB, R_BC_FRONT_DEFAULT)
        f = ft.compute_window_features(p_I, 0.2, 0.05)
        assert np.allclose(f.eta_w, [1, 0, 0], atol=1e-9)        # wall normal, travel direction
        assert np.allclose(f.u_w, [0, 0, 1], atol=1e-9)          # vertical edges, top -> bottom
        assert np.allclose(f.rho_w, [0, 1, 0], atol=1e-9)        # horizontal edges, left -> right
        assert np.allclose(np.cross(f.u_w, f.eta_w), f.rho_w)    # rho_w = u_w x eta_w (paper)
        assert f.eta_w @ f.q_w < 0                               # sign rule of eq:etaw


def test_eta_w_continuity_reference_overrides_sign_rule():
    xi = np.array([-1.0, 0.0, -1.6])
    p = bearings(CORNERS, xi)
    h = ft.edge_normals(p)
    u, rho = ft.window_axes(h, p)
    assert np.allclose(ft.window_normal(u, rho, ft.centroid_feature(p), eta_ref=-np.array(
        [1.0, 0, 0])), [-1, 0, 0])


def test_q_w_bar_far_from_window_is_xi_w_over_d_o():
    for _ in range(30):
        xi = random_approach_position()
        f = ft.compute_window_features(bearings(CORNERS, xi), 0.2, 0.05)
        xi_w = xi - CENTRE
        d_o = WORLD.wall_x - xi[0]
        assert f.alpha_w == 1.0
        assert np.allclose(f.q_w_bar, xi_w / d_o)


def test_q_w_bar_inside_region_W_is_xi_w_over_d_e():
    # Near the window plane and its centre, |q_w| <= eps: alpha_w = 0, q_bar_w = xi_w / d_e
    xi = np.array([WORLD.wall_x - 0.1, 0.05, CENTRE[2] + 0.04])
    f = ft.compute_window_features(bearings(CORNERS, xi), 0.2, 0.05)
    assert f.alpha_w == 0.0
    edges = [(CORNERS[i], CORNERS[(i + 1) % 4]) for i in range(4)]
    d_e = min(np.linalg.norm(closest_point_on_segment(a, b, xi) - xi) for a, b in edges)
    assert np.allclose(f.q_w_bar, (xi - CENTRE) / d_e, rtol=1e-9)
    # l^e points at that closest edge point
    a, b = min(edges, key=lambda e: np.linalg.norm(closest_point_on_segment(*e, xi) - xi))
    L = closest_point_on_segment(a, b, xi) - xi
    assert np.allclose(f.l_e, L / np.linalg.norm(L))


def test_alpha_w_piecewise_and_continuous():
    assert ft.alpha_w(0.1, 0.2, 0.05) == 0.0
    assert ft.alpha_w(0.2, 0.2, 0.05) == 0.0
    assert ft.alpha_w(0.225, 0.2, 0.05) == pytest.approx(0.5)
    assert ft.alpha_w(0.25, 0.2, 0.05) == 1.0
    assert ft.alpha_w(3.0, 0.2, 0.05) == 1.0


def test_phi_w_is_v_over_d_w():
    xi = np.array([WORLD.wall_x - 0.1, 0.05, CENTRE[2] + 0.04])
    v = np.array([0.3, -0.05, 0.02])
    f = ft.compute_window_features(bearings(CORNERS, xi), 0.2, 0.05)
    d_o = WORLD.wall_x - xi[0]
    edges = [(CORNERS[i], CORNERS[(i + 1) % 4]) for i in range(4)]
    d_e = min(np.linalg.norm(closest_point_on_segment(a, b, xi) - xi) for a, b in edges)
    phi = ft.window_flow(v / d_o, f.eta_w, f.l_e, f.alpha_w)
    assert np.allclose(phi, v / d_e)       # alpha_w = 0 here
    assert np.allclose(ft.window_flow(v / d_o, f.eta_w, f.l_e, 1.0), v / d_o)


def test_translational_flow_kinematics_by_finite_difference():
    """eq:p_t: p_dot = -(eta^T p) pi_p v / d for a fixed floor point (paper section 3.3)."""
    s = np.array([0.3, -0.2, 0.0])          # floor point
    xi = np.array([-0.5, 0.1, -1.4])
    v = np.array([0.4, -0.1, 0.2])
    h = 1e-6
    p0 = (s - xi) / np.linalg.norm(s - xi)
    p1 = (s - xi - v * h) / np.linalg.norm(s - xi - v * h)
    d_t = -xi[2]
    eta_t = np.array([0.0, 0.0, 1.0])
    predicted = -(eta_t @ p0) * proj_orth(p0) @ (v / d_t)
    assert np.allclose((p1 - p0) / h, predicted, atol=1e-5)


def test_distance_to_window_plane_and_pad_height():
    for _ in range(10):
        xi = random_approach_position()
        d = ft.distance_to_window_plane(bearings(CORNERS, xi), np.array([1.0, 0, 0]),
                                        WORLD.window.width)
        assert d == pytest.approx(WORLD.wall_x - xi[0], rel=1e-9)
    pad = load_pad_layout()
    for g in pad.groups:
        for h in (1.5, 0.5, 0.15):
            p = bearings(g.marker_centres_I(), np.array([0.0, 0.0, -h]))
            assert ft.pad_height_estimate(p, g.c) == pytest.approx(h, rel=1e-9)


def test_pad_height_is_exact_off_the_pad_centre():
    """The height from the group's known size, not from how far below the group looks.

    Group D (c = 0.045 m) 0.17 m beside the pad at 0.3 m: the centroid-angle formula used
    before read 0.11 m (h sqrt(2) c / x), below the 0.14 m shutdown height; PX4 SIH shut down
    there and touched down at 2.1 m/s. From geometry, any offset and height: exact.
    """
    pad = load_pad_layout()
    rng = np.random.default_rng(5)
    for g in pad.groups:
        for h in (1.5, 0.5, 0.3, 0.15):
            for x, y in ((0.17, 0.0), (0.0, -0.3), *rng.uniform(-0.5, 0.5, (3, 2))):
                p = bearings(g.marker_centres_I(), np.array([x, y, -h]))
                assert ft.pad_height_estimate(p, g.c) == pytest.approx(h, rel=1e-9)
    D = next(g for g in pad.groups if g.name == 'D')
    p = bearings(D.marker_centres_I(), np.array([0.17, 0.0, -0.3]))
    cos_t = -p.mean(axis=0)[2]                      # the old, vertical-only reading
    assert np.sqrt(2) * D.c * cos_t / np.sqrt(1 - cos_t ** 2) < 0.14 < 0.3
    with pytest.raises(ValueError):                  # a marker above the camera
        ft.pad_height_estimate(-p, D.c)


def test_degenerate_inputs_raise():
    with pytest.raises(ValueError):
        ft.centroid_feature(np.zeros((0, 3)))
    p = bearings(CORNERS, np.array([-1.0, 0, -1.6]))
    p[1] = p[0]
    with pytest.raises(ValueError):
        ft.compute_window_features(p, 0.2, 0.05)
