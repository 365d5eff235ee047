"""Frames and camera model: round trips and independent geometric facts."""
import cv2
import numpy as np
import pytest

from ibvs_common.core import frames as fr
from ibvs_common.core.camera import CameraModel, CameraModelError

RNG = np.random.default_rng(7)


def random_rotation() -> np.ndarray:
    q = RNG.normal(size=4)
    return fr.rot_from_quat(q / np.linalg.norm(q))


def test_map_I_round_trip_and_axes():
    v = RNG.normal(size=(10, 3))
    assert np.allclose(fr.vec_map_to_I(fr.vec_I_to_map(v)), v)
    # docs/spec.md 1: x_ENU = y_I, y_ENU = x_I, z_ENU = -z_I (I is NED-type)
    assert np.allclose(fr.vec_I_to_map([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    # gravity (+e3 in I, down) points to -z in ENU
    assert fr.vec_I_to_map(fr.e3)[2] == -1.0


def test_frd_flu_round_trip():
    v = RNG.normal(size=(5, 3))
    assert np.allclose(fr.vec_flu_to_frd(fr.vec_frd_to_flu(v)), v)
    assert np.allclose(fr.vec_frd_to_flu([1.0, 1.0, 1.0]), [1.0, -1.0, -1.0])


def test_quaternion_round_trip_and_known_values():
    for _ in range(50):
        R = random_rotation()
        q = fr.quat_from_rot(R)
        assert np.isclose(np.linalg.norm(q), 1.0) and q[0] >= 0.0
        assert np.allclose(fr.rot_from_quat(q), R, atol=1e-12)
    # 90 deg about z: (cos 45, 0, 0, sin 45)
    assert np.allclose(fr.quat_from_rot(fr.rot_z(np.pi / 2)), [np.sqrt(.5), 0, 0, np.sqrt(.5)])
    assert np.allclose(fr.quat_xyzw_to_wxyz(fr.quat_wxyz_to_xyzw([1, 2, 3, 4])), [1, 2, 3, 4])
    with pytest.raises(ValueError):
        fr.rot_from_quat([np.nan, 0, 0, 1])


def test_euler_round_trip():
    for _ in range(20):
        rpy = RNG.uniform([-1, -1.2, -3], [1, 1.2, 3])
        assert np.allclose(fr.euler_zyx_from_rot(fr.rot_from_euler_zyx(*rpy)), rpy)


def test_ned_frd_to_enu_flu_matches_mavros_convention():
    # Level, nose north (NED yaw 0) = ENU yaw +90 deg (nose along +y_ENU), FLU body.
    q_enu = fr.quat_ned_frd_to_enu_flu(fr.quat_from_rot(np.eye(3)))
    R = fr.rot_from_quat(q_enu)
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])       # FLU x (nose) -> north = +y ENU
    assert np.allclose(R @ [0, 0, 1], [0, 0, 1])       # FLU z up -> ENU up
    # Nose east (NED yaw +90) -> ENU yaw 0.
    R2 = fr.rot_from_quat(fr.quat_ned_frd_to_enu_flu(fr.quat_from_rot(fr.rot_z(np.pi / 2))))
    assert np.allclose(R2, np.eye(3), atol=1e-12)
    for _ in range(20):
        q = fr.quat_from_rot(random_rotation())
        back = fr.quat_enu_flu_to_ned_frd(fr.quat_ned_frd_to_enu_flu(q))
        assert np.allclose(back, q) or np.allclose(back, -q)


def test_scalar_imu_conversions_equal_the_matrix_route():
    """The closed forms on the 100 Hz IMU path give what the rotation matrices give."""
    for _ in range(200):
        R_IB = random_rotation()
        q_ned = fr.quat_from_rot(R_IB) * RNG.uniform(0.9, 1.1)    # not unit: normalised
        R_map_base = fr.rot_map_base_from_R_IB(R_IB)
        q_enu = fr.quat_ned_frd_to_enu_flu(q_ned)
        assert q_enu[0] >= 0.0 and np.isclose(np.linalg.norm(q_enu), 1.0, atol=1e-15)
        assert np.allclose(fr.rot_from_quat(q_enu), R_map_base, atol=1e-12)
        assert np.allclose(fr.R_IB_from_quat_map_base(-q_enu * 1.05), R_IB, atol=1e-12)
        yaw, cos_tilt = fr.yaw_and_cos_tilt_from_quat(q_ned)
        assert np.isclose(yaw, fr.euler_zyx_from_rot(R_IB)[2], atol=1e-12)
        assert np.isclose(cos_tilt, (R_IB @ fr.e3) @ fr.e3, atol=1e-12)
    # nose north, level (NED identity): ENU quaternion = 90 deg about z
    assert np.allclose(fr.quat_ned_frd_to_enu_flu([1.0, 0, 0, 0]),
                       [np.sqrt(.5), 0, 0, np.sqrt(.5)])
    for bad in ([np.nan, 0, 0, 1], [0, 0, 0, 0], [np.inf, 0, 0, 0]):
        for f in (fr.quat_ned_frd_to_enu_flu, fr.R_IB_from_quat_map_base,
                  fr.yaw_and_cos_tilt_from_quat):
            with pytest.raises(ValueError):
                f(bad)


def test_is_rotation_rejects_reflections_non_orthonormal_and_nan():
    R = random_rotation()
    assert fr.is_rotation(R)
    assert not fr.is_rotation(R @ np.diag([1.0, 1.0, -1.0]))           # det -1
    assert not fr.is_rotation(R * 1.001)                               # scaled
    assert fr.is_rotation(R * (1 + 1e-7)) and not fr.is_rotation(R * (1 + 1e-5))
    bad = R.copy()
    bad[1, 2] = np.nan
    assert not fr.is_rotation(bad) and not fr.is_rotation(np.eye(2))


def test_rotated_vector_consistent_across_conventions():
    R_IB = random_rotation()
    v_B = RNG.normal(size=3)
    v_I = R_IB @ v_B
    R_map_base = fr.rot_map_base_from_R_IB(R_IB)
    assert np.allclose(R_map_base @ fr.vec_frd_to_flu(v_B), fr.vec_I_to_map(v_I))
    assert np.allclose(fr.R_IB_from_rot_map_base(R_map_base), R_IB)


def test_camera_mounts_of_spec():
    # down camera: optical z = body z, image x = body y, image y = -body x
    R = fr.R_BC_DOWN_DEFAULT
    assert np.allclose(R @ [0, 0, 1], [0, 0, 1])
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(R @ [0, 1, 0], [-1, 0, 0])
    # forward camera: optical z = body x, image x = body y, image y = body z
    R = fr.R_BC_FRONT_DEFAULT
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1])
    for R in (fr.R_BC_DOWN_DEFAULT, fr.R_BC_FRONT_DEFAULT):
        assert fr.is_rotation(R)


def test_bearings_round_trip_and_level_down_camera_sees_down():
    R_IB = random_rotation()
    b = RNG.normal(size=(6, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    back = fr.bearings_I_to_C(fr.bearings_C_to_I(b, R_IB, fr.R_BC_FRONT_DEFAULT), R_IB,
                              fr.R_BC_FRONT_DEFAULT)
    assert np.allclose(back, b)
    # level vehicle: the down camera's optical axis is +z_I (down)
    assert np.allclose(fr.bearings_C_to_I([0, 0, 1], np.eye(3), fr.R_BC_DOWN_DEFAULT), fr.e3)


SPEC_K = [366.667, 0.0, 375.5, 0.0, 366.667, 239.5, 0.0, 0.0, 1.0]


def plumb_bob_forward(x, y, D):
    """Independent radial-tangential distortion of normalised coordinates."""
    k1, k2, p1, p2, k3 = D
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def test_plumb_bob_against_independent_model():
    D = [-0.25, 0.06, 0.001, -0.0005, 0.0]
    cam = CameraModel.from_camera_info(752, 480, SPEC_K, D, 'plumb_bob')
    for _ in range(100):
        x, y = RNG.uniform(-1.2, 1.2), RNG.uniform(-0.7, 0.7)
        xd, yd = plumb_bob_forward(x, y, D)
        u, v = 366.667 * xd + 375.5, 366.667 * yd + 239.5
        b = cam.pixels_to_bearings(np.array([[u, v]]))[0]
        expected = np.array([x, y, 1.0]) / np.linalg.norm([x, y, 1.0])
        assert np.degrees(np.arccos(min(1.0, b @ expected))) < 1e-4
        uv, ok = cam.bearings_to_pixels(expected[None])
        assert np.allclose(uv[0], [u, v], atol=1e-6)


def test_equidistant_against_independent_model():
    D = [0.05, -0.01, 0.002, 0.0]
    cam = CameraModel.from_camera_info(752, 480, SPEC_K, D, 'equidistant')
    for theta in np.linspace(0.05, 1.2, 12):
        phi = RNG.uniform(-np.pi, np.pi)
        ray = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        th_d = theta * (1 + D[0] * theta ** 2 + D[1] * theta ** 4 + D[2] * theta ** 6
                        + D[3] * theta ** 8)
        u = 366.667 * th_d * np.cos(phi) + 375.5
        v = 366.667 * th_d * np.sin(phi) + 239.5
        b = cam.pixels_to_bearings(np.array([[u, v]]))[0]
        assert np.degrees(np.arccos(min(1.0, b @ ray))) < 1e-3


def test_principal_point_is_optical_axis_and_behind_is_invalid():
    cam = CameraModel.from_camera_info(752, 480, SPEC_K, [-0.25, 0.06, 0, 0, 0], 'plumb_bob')
    assert np.allclose(cam.pixels_to_bearings([[375.5, 239.5]]), [[0, 0, 1]])
    uv, ok = cam.bearings_to_pixels(np.array([[0, 0, -1.0], [0, 0, 1.0], [5.0, 0, 1.0]]))
    assert list(ok) == [False, True, False] and np.all(np.isnan(uv[0]))


def test_border_margin_is_the_closest_points_distance_to_the_image_edge():
    """Pinhole (no distortion): a bearing aimed at pixel (u, v) keeps min(u + 0.5, ...) px."""
    cam = CameraModel.from_camera_info(752, 480, SPEC_K, [], 'plumb_bob')
    fx, cx, cy = SPEC_K[0], SPEC_K[2], SPEC_K[5]

    def aimed_at(u, v):
        return [(u - cx) / fx, (v - cy) / fx, 1.0]

    assert cam.border_margin_px([aimed_at(375.5, 239.5)]) == pytest.approx(239.5 + 0.5)
    assert cam.border_margin_px([aimed_at(375.5, 239.5), aimed_at(700.0, 100.0)]) == \
        pytest.approx(751.5 - 700.0)
    assert cam.border_margin_px([aimed_at(375.5, -10.0)]) == pytest.approx(-9.5)   # outside
    assert cam.border_margin_px([[0.0, 0.0, -1.0]]) == -np.inf                        # behind
    assert cam.border_margin_px(np.zeros((0, 3))) == -np.inf


@pytest.mark.parametrize('kw', [
    dict(width=0), dict(k=[0] * 9), dict(k=[1.0] * 8), dict(d=[np.nan, 0, 0, 0, 0]),
    dict(distortion_model='fancy'), dict(distortion_model='equidistant'),
])
def test_degenerate_camera_info_is_refused(kw):
    args = dict(width=752, height=480, k=SPEC_K, d=[0.0] * 5, distortion_model='plumb_bob')
    args.update(kw)
    with pytest.raises(CameraModelError):
        CameraModel.from_camera_info(**args)


def test_opencv_agrees_on_a_random_projection():
    """Second method: cv2.projectPoints with a non-zero pose vs rotating first."""
    D = np.array([-0.25, 0.06, 0.0, 0.0, 0.0])
    cam = CameraModel.from_camera_info(752, 480, SPEC_K, D, 'plumb_bob')
    R = fr.rot_from_euler_zyx(0.1, -0.05, 0.2)
    P = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 1.5]])
    rvec, _ = cv2.Rodrigues(R)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, np.zeros(3), np.array(SPEC_K)
                               .reshape(3, 3), D)
    uv, _ = cam.bearings_to_pixels(P @ R.T)
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_so3_exp_log_against_rodrigues_and_round_trip():
    for _ in range(50):
        w = RNG.normal(size=3)
        w *= RNG.uniform(0.0, np.pi - 1e-3) / np.linalg.norm(w)
        R = fr.exp_so3(w)
        assert np.allclose(R, cv2.Rodrigues(w.reshape(3, 1))[0], atol=1e-12)
        assert np.allclose(fr.log_so3(R), w, atol=1e-9)
    assert np.allclose(fr.exp_so3(np.zeros(3)), np.eye(3))
    w = np.array([0.0, np.pi, 0.0])                      # the angle-pi branch
    assert np.allclose(fr.exp_so3(fr.log_so3(fr.exp_so3(w))), fr.exp_so3(w), atol=1e-9)
    w = np.array([1.0, -2.0, 0.5])
    w *= np.pi / np.linalg.norm(w)
    assert np.allclose(fr.exp_so3(fr.log_so3(fr.exp_so3(w))), fr.exp_so3(w), atol=1e-6)


@pytest.mark.parametrize('d, model', [
    ([-0.25, 0.06, 0.0, 0.0, 0.0], 'plumb_bob'),
    ([0.1, -0.02, 0.001, -0.002, 0.003], 'plumb_bob'),
    ([0.1, -0.02, 0.001, -0.002], 'plumb_bob'),
    ([0.0] * 5, 'plumb_bob'),
    ([0.1, -0.02, 0.001, -0.002, 0.003, 0.05, 0.01, -0.001], 'rational_polynomial'),
])
def test_projection_is_opencvs_to_the_last_bit(d, model):
    """The written-out plumb_bob / rational map against cv2.projectPoints itself.

    Points at depths 0.05-20 m (not only z = 1: OpenCV scales by 1 / z), a skewed K (OpenCV
    ignores the skew when projecting, so must the model), and normalised coordinates through
    ``normalized_to_pixels``: every pixel equal to OpenCV's, bit for bit.
    """
    k = [366.7, 0.3, 375.5, 0.0, 366.7, 239.5, 0.0, 0.0, 1.0]
    cam = CameraModel.from_camera_info(752, 480, k, d, model)
    rng = np.random.default_rng(7)
    P = np.column_stack([rng.uniform(-1.5, 1.5, (5000, 2)), np.ones(5000)]) \
        * rng.uniform(0.05, 20.0, (5000, 1))
    expected, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                    np.array(k).reshape(3, 3), np.array(d, float))
    uv, _ = cam.bearings_to_pixels(P)
    np.testing.assert_array_equal(uv, expected.reshape(-1, 2))
    xy = P[:, :2] / P[:, 2:]
    expected, _ = cv2.projectPoints(np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3),
                                    np.zeros(3), np.zeros(3), np.array(k).reshape(3, 3),
                                    np.array(d, float))
    np.testing.assert_array_equal(cam.normalized_to_pixels(xy), expected.reshape(-1, 2))


def test_cross3_is_np_cross_to_the_bit_with_the_right_hand_sign():
    assert fr.cross3([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]).tolist() == [0.0, 0.0, 1.0]   # x ^ y = z
    assert fr.cross3([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).tolist() == [0.0, 1.0, 0.0]   # z ^ x = y
    rng = np.random.default_rng(5)
    for a, b in rng.normal(size=(2000, 2, 3)) * rng.uniform(1e-3, 1e3, (2000, 2, 1)):
        np.testing.assert_array_equal(fr.cross3(a, b), np.cross(a, b))
