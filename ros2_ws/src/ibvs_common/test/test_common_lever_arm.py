"""Lever arms: features from a camera off the body origin, re-taken from the origin.

The references are plain geometry: the points' bearings from the body origin computed from
their known positions (never the module's formulas).
"""
import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout
from ibvs_common.core.frames import rot_from_euler_zyx
from ibvs_common.core.lever_arm import (flow_from_body, has_lever_arm,
                                        pad_landmarks_from_body, plane_bearings_from_body,
                                        window_corners_from_body, window_plane)

# a window 1.2 m x 1.0 m in the plane x = -0.5 ({I}, z down), centred at (-0.5, 0, -1.6)
CORNERS = np.array([[-0.5, -0.6, -2.1], [-0.5, 0.6, -2.1], [-0.5, 0.6, -1.1],
                    [-0.5, -0.6, -1.1]])
R_IB = rot_from_euler_zyx(0.05, -0.08, 0.1)       # roll, pitch, yaw


def unit_rows(X):
    return X / np.linalg.norm(X, axis=1, keepdims=True)


@pytest.mark.parametrize('t_BC', [(0.08, 0.0, 0.05), (0.0, -0.04, 0.0), (0.1, 0.03, -0.06)])
def test_window_corners_from_the_body_equal_the_bearings_from_its_origin(t_BC):
    xi = np.array([-2.0, 0.1, -1.82])
    t_I = R_IB @ np.array(t_BC)
    from_camera = unit_rows(CORNERS - (xi + t_I))
    eta, d_o = window_plane(from_camera, r_w=1.2)
    assert np.allclose(eta, [1.0, 0.0, 0.0], atol=1e-9)
    assert d_o == pytest.approx(-0.5 - (xi + t_I)[0], abs=1e-9)     # the camera's distance
    got = window_corners_from_body(from_camera, t_I, r_w=1.2)
    assert np.allclose(got, unit_rows(CORNERS - xi), atol=1e-9)


def test_a_down_camera_eight_centimetres_off_sees_the_pad_from_the_centre_after_correction():
    pad = load_pad_layout()
    groups = [g for g in pad.groups if g.name in ('B', 'C')]
    xi = np.array([0.02, -0.03, -0.9])                   # 0.9 m above the pad
    t_I = R_IB @ np.array([0.08, 0.0, 0.02])
    points = np.concatenate([g.marker_centres_I() for g in groups])
    from_camera = unit_rows(points - (xi + t_I))
    half_sides = {g.name: g.c for g in pad.groups}
    got = pad_landmarks_from_body(from_camera, [g.name for g in groups], half_sides, t_I)
    assert np.allclose(got, unit_rows(points - xi), atol=1e-9)
    # the centroid the landing law regulates: the camera's is ~8 cm off, the corrected none
    c_cam = from_camera.mean(axis=0)
    c_body = got.mean(axis=0)
    assert abs(c_cam[0] / c_cam[2] * 0.9 - c_body[0] / c_body[2] * 0.9) > 0.05


def test_the_floor_flow_scales_with_the_cameras_height_over_the_bodys():
    v = np.array([0.3, -0.1, 0.2])
    h_body, t_I = 0.5, np.array([0.0, 0.0, 0.06])         # the camera 6 cm below the centre
    phi_camera = v / (h_body - 0.06)                      # v / d of the camera
    got = flow_from_body(phi_camera, np.array([0.0, 0.0, 1.0]), h_body - 0.06, t_I)
    assert np.allclose(got, v / h_body)


def test_a_rotating_body_carries_the_camera_and_its_flow_is_removed():
    """The camera's velocity by finite differences of its position xi(t) + R(t) t_BC while the
    body turns at omega and moves at v (no formula of the module): the camera's flow is
    v_C / d_C; from the body origin, with the rate given, the flow is v / d_body again; without
    it, off by the rotation's part (0.5 rad/s x 10 cm here, 5 cm/s of 0.4 m/s)."""
    from ibvs_common.core.frames import exp_so3
    v = np.array([0.4, 0.05, 0.1])                       # the wall ahead at x = 0, {I}
    omega_B = np.array([0.1, -0.3, 0.4])
    t_BC = np.array([0.1, 0.02, 0.03])
    xi0, eta = np.array([-2.0, 0.1, -1.5]), np.array([1.0, 0.0, 0.0])

    def camera(t):
        return xi0 + v * t + (R_IB @ exp_so3(omega_B * t)) @ t_BC
    dt = 1e-6
    v_C = (camera(dt) - camera(-dt)) / (2 * dt)
    t_I = R_IB @ t_BC
    d_C, d_body = -camera(0.0)[0], -xi0[0]
    omega_I = R_IB @ omega_B
    got = flow_from_body(v_C / d_C, eta, d_C, t_I, omega_I)
    assert np.allclose(got, v / d_body, atol=1e-8)
    without = flow_from_body(v_C / d_C, eta, d_C, t_I)
    assert np.linalg.norm(without - v / d_body) * d_body > 0.02     # the rotation's part
    assert np.allclose(flow_from_body(v / d_body, eta, d_body, np.zeros(3), omega_I),
                       v / d_body)                                  # no lever arm: unchanged


def test_no_lever_arm_changes_nothing_and_bad_geometry_is_refused():
    assert not has_lever_arm(np.zeros(3)) and has_lever_arm(np.array([0.0, 0.01, 0.0]))
    q = unit_rows(CORNERS - np.array([-2.0, 0.1, -1.82]))
    assert np.allclose(plane_bearings_from_body(q, np.array([1.0, 0, 0]), 1.5, np.zeros(3)), q)
    with pytest.raises(ValueError):
        plane_bearings_from_body(q, np.array([-1.0, 0, 0]), 1.5, np.zeros(3))   # behind
    with pytest.raises(ValueError):
        flow_from_body(np.ones(3), np.array([0.0, 0, 1.0]), 0.05, np.array([0, 0, -0.1]))
