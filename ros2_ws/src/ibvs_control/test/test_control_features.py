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


def test_window_centre_offset_is_the_centre_off_the_axis_in_the_wall_plane():
    """From the window's geometry: its centre minus the camera, without the part along the
    wall normal (the image alone says how far off the axis the camera is)."""
    eta = np.array([1.0, 0, 0])
    centre = WORLD.window.center_I
    for _ in range(10):
        xi = random_approach_position()
        offset = ft.window_centre_offset(bearings(CORNERS, xi), eta, WORLD.window.width)
        expected = (centre - xi) - ((centre - xi) @ eta) * eta
        assert offset == pytest.approx(expected, abs=1e-9)
    xi = np.array([-1.5, 0.3, -1.4])                  # 0.3 m left, 0.2 m low: sign and size
    assert ft.window_centre_offset(bearings(CORNERS, xi), eta, WORLD.window.width) == \
        pytest.approx([0.0, -0.3, -0.2], abs=1e-9)


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


def test_centroid_of_the_complete_groups_depends_on_which_groups_are_complete():
    """Why q_t jumped at a group switch: rings of other radii have other spherical centroids.

    Straight above the pad at height h, a group's 4 bearings make the angle atan(sqrt(2) c /
    h) with the vertical, so its centroid is h / sqrt(h^2 + 2 c^2) e3-up; beside the pad the
    direction differs too. The same pose, two sets of groups: two features.
    """
    pad = load_pad_layout()
    h = 0.6
    for g in pad.groups:
        q = ft.centroid_feature(bearings(g.marker_centres_I(), np.array([0.0, 0.0, -h])))
        assert np.allclose(q, [0.0, 0.0, -h / np.hypot(h, np.sqrt(2.0) * g.c)], atol=1e-12)
    xi = np.array([0.3, -0.2, -0.6])
    A, D = (bearings(g.marker_centres_I(), xi) for g in (pad.groups[0], pad.groups[-1]))
    q_A, q_AD = ft.centroid_feature(A), ft.centroid_feature(np.vstack([A, D]))
    assert np.linalg.norm(q_A - q_AD) > 0.03
    assert np.degrees(np.arccos(q_A @ q_AD / np.linalg.norm(q_A) / np.linalg.norm(q_AD))) > 0.5


def pad_subsets(pad):
    """Every non-empty set of groups, in layout order (as pad/landmarks lists them)."""
    n = len(pad.groups)
    return [[g for k, g in enumerate(pad.groups) if mask >> k & 1] for mask in range(1, 2 ** n)]


def test_pad_feature_is_the_same_for_every_set_of_complete_groups():
    """q_t on fixed pad points: the same vector from any set of groups, in any frame.

    Default: the pad centre alone, q_t = -p_centre = xi / |xi| (the unit direction from the
    pad centre to the camera). With a reference square of half-side r: minus the mean of the
    true bearings of its 4 corners (+-r, +-r). Bearings expressed in a rotated frame (as
    the optical frame is): the feature comes out in that frame.
    """
    pad = load_pad_layout()
    rng = np.random.default_rng(15)
    r = 0.25
    square = np.array([[r, r, 0.0], [r, -r, 0.0], [-r, -r, 0.0], [-r, r, 0.0]])
    for _ in range(30):
        xi = np.array([*rng.uniform(-0.5, 0.5, 2), -rng.uniform(0.12, 2.5)])
        R = rot_from_euler_zyx(*rng.uniform(-0.4, 0.4, 3))      # {I} <- the bearings' frame
        centre_truth = xi / np.linalg.norm(xi)
        square_truth = -bearings(square, xi).mean(axis=0)
        for groups in pad_subsets(pad):
            p = np.vstack([bearings(g.marker_centres_I(), xi) for g in groups]) @ R  # R^T p
            np.testing.assert_allclose(R @ ft.pad_feature(p), centre_truth, atol=1e-12)
            q = ft.pad_feature(p, [g.c for g in groups], reference_half_side=r)
            np.testing.assert_allclose(R @ q, square_truth, atol=1e-12)


def test_pad_feature_weights_fade_a_biased_group_in_and_out():
    """Weights (the pad detector's, per group): equal weights are the plain mean; a group of
    weight 0+ counts for nothing (the feature of the other groups), so a group with a bias of
    its own (here 0.5 deg, a calibration error or blur) moves q_t by the bias times its share
    of the weights, and by nothing while its weight is ~0 at the frame it appears."""
    pad = load_pad_layout()
    xi = np.array([0.2, -0.1, -0.9])
    A, B, C = (bearings(g.marker_centres_I(), xi) for g in pad.groups[:3])
    bias = rot_from_euler_zyx(0.0, np.radians(0.5), 0.0)
    C_biased = C @ bias.T
    p = np.vstack([A, B, C_biased])
    np.testing.assert_array_equal(ft.pad_feature(p, weights=[2.0, 2.0, 2.0]), ft.pad_feature(p))
    np.testing.assert_allclose(ft.pad_feature(p, weights=[1.0, 1.0, 1e-12]),
                               ft.pad_feature(np.vstack([A, B])), atol=1e-12)
    truth = xi / np.linalg.norm(xi)
    alone_C = ft.pad_feature(C_biased)

    def moved(weights):       # the angle (deg) q_t moves when C joins A and B
        q = ft.pad_feature(p, weights=weights)
        return np.degrees(np.arccos(np.clip(q @ truth / np.linalg.norm(q), -1.0, 1.0)))
    full = np.degrees(np.arccos(alone_C @ truth / np.linalg.norm(alone_C)))
    assert full == pytest.approx(0.5, abs=0.05)
    assert moved([1.0, 1.0, 1.0]) == pytest.approx(full / 3.0, rel=0.05)
    assert moved([1.0, 1.0, 0.1]) == pytest.approx(full * 0.1 / 2.1, rel=0.05)
    for bad in ([1.0, 1.0], [1.0, -1.0, 1.0], [0.0, 0.0, 0.0], [1.0, np.nan, 1.0]):
        with pytest.raises(ValueError, match='weights'):
            ft.pad_feature(p, weights=bad)


def test_pad_reference_bearings_of_one_group_are_the_true_bearings():
    """Any pad point, seen through one group's plane map: its true bearing (inside or out)."""
    pad = load_pad_layout()
    xi = np.array([0.35, -0.25, -0.4])
    points = np.array([[0.0, 0.0], [0.36, 0.36], [-0.5, 0.2], [0.01, -0.03]])
    truth = bearings(np.column_stack([points, np.zeros(len(points))]), xi)
    for g in pad.groups:
        got = ft.pad_reference_bearings(bearings(g.marker_centres_I(), xi), g.c, points)
        np.testing.assert_allclose(got, truth, atol=1e-11)


def test_pad_feature_refuses_what_is_not_the_view_of_complete_groups():
    pad = load_pad_layout()
    xi = np.array([0.1, 0.0, -0.8])
    A = bearings(pad.groups[0].marker_centres_I(), xi)
    with pytest.raises(ValueError):                  # not 4 per group
        ft.pad_feature(A[:3])
    with pytest.raises(ValueError):
        ft.pad_feature(np.zeros((0, 3)))
    with pytest.raises(ValueError):                  # markers out of layout order (a bow tie)
        ft.pad_feature(A[[0, 2, 1, 3]])
    with pytest.raises(ValueError):                  # three centres on one great circle
        ft.pad_feature(np.array([A[0], A[1], A[1], A[3]]))
    with pytest.raises(ValueError):                  # a reference square needs the sizes
        ft.pad_feature(A, reference_half_side=0.1)
    D = bearings(pad.groups[-1].marker_centres_I(), xi)       # a degenerate group is left out
    np.testing.assert_allclose(ft.pad_feature(np.vstack([A[[0, 2, 1, 3]], D])),
                               xi / np.linalg.norm(xi), atol=1e-12)
    with pytest.raises(ValueError):
        ft.pad_reference_points(-0.1)
