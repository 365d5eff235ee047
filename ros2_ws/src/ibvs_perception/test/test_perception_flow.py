"""Translational optical flow, IMU attitude buffer and image decoding of ibvs_perception.

Flow ground truth: phi = v / d from the rendered poses (d at mid-interval), docs/spec.md planes.
"""
import cv2
import numpy as np
import pytest

from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.attitude_buffer import AttitudeBuffer, AttitudeBufferConfig
from ibvs_perception.core.flow import (flow_residuals, FlowConfig, FlowEstimator,
                                       inside_spherical_polygon,
                                       joint_grid_start, LK_MOTION_MARGIN, mid_bearings,
                                       pyramid_levels_for, second_plane_ratio, solve_flow_axis,
                                       solve_flow_c, solve_translational_flow,
                                       wall_normal_from_corners)
from ibvs_perception.core.image import ImageFormatError, image_to_mono8
from ibvs_perception.core.window import WindowDetector, WindowDetectorConfig
from ibvs_sim.core.render import SceneRenderer

DT = 0.02   # s, 50 Hz cameras


@pytest.fixture(scope='module')
def scene():
    world, vehicle, pad = load_world(), load_vehicle(), load_pad_layout()
    return world, vehicle, {n: SceneRenderer(world, pad, vehicle.cameras[n])
                            for n in ('front', 'down')}


def random_motion(rng):
    v = rng.normal(size=3)
    v *= rng.uniform(0.1, 1.0) / np.linalg.norm(v)
    omega = rng.normal(size=3)
    omega *= rng.uniform(0.2, 1.0) / np.linalg.norm(omega)
    return v, omega


def test_closed_form_flow_recovered_from_exact_bearings():
    """Bearings of plane points moved by v dt, no rotation: the LS solve returns v/d."""
    rng = np.random.default_rng(3)
    eta = frames.e3
    d, v = 1.3, np.array([0.4, -0.2, 0.1])
    S = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), np.full(200, d)])
    p0 = S / np.linalg.norm(S, axis=1, keepdims=True)
    dt = 1e-4
    P1 = S - v * dt
    p1 = P1 / np.linalg.norm(P1, axis=1, keepdims=True)
    phi = solve_translational_flow(p0, p1, dt, eta, np.ones(200))
    np.testing.assert_allclose(phi, v / d, rtol=2e-3, atol=1e-5)


@pytest.mark.parametrize('angle', [0.0, 1e-3, -2e-3])
def test_flow_and_a_rotation_about_the_optical_axis_recovered_from_exact_bearings(angle):
    """Wall points (the front camera's view, axis a = e1) seen after a translation v dt and
    a turn of the camera by ``angle`` about a (Rodrigues): phi = v/d, and omega = -angle/dt,
    the bearings turning the other way about a (right-handed), as the sign test shows."""
    rng = np.random.default_rng(4)
    a, d, v, dt = frames.e1, 2.3, np.array([0.05, 0.1, -0.05]), 0.02
    S = np.column_stack([np.full(300, d), rng.uniform(-2, 2, 300), rng.uniform(-1.5, 1.5, 300)])
    p0 = S / np.linalg.norm(S, axis=1, keepdims=True)
    # the camera turned by R_turn: a world point's bearing is R_turn^T (X - c)
    P1 = (S - v * dt) @ frames.exp_so3(angle * a)
    p1 = P1 / np.linalg.norm(P1, axis=1, keepdims=True)
    p_mid = mid_bearings(p0, p1)
    phi, omega = solve_flow_axis(p_mid, (p1 - p0) / dt, p_mid @ a, np.ones(300), a)
    np.testing.assert_allclose(phi, v / d, rtol=1e-3, atol=1e-4)
    assert omega == pytest.approx(-angle / dt, abs=1e-4)
    # the sign: a bearing on the +y side, turned anticlockwise about +x (omega > 0) moves +z
    p_y = np.array([[0.0, 1.0, 0.0]])
    assert np.cross(a, p_y)[0] @ frames.e3 > 0


def test_without_the_axis_rotation_a_camera_turn_is_left_in_the_residuals():
    """A turn of 2 mrad about the optical axis, no translation: the one-plane model alone
    leaves ~0.4-0.5 px at the image edges (the inlier gate is 0.5 px; flow.py's doc), the
    model with the rotation nothing."""
    rng = np.random.default_rng(4)
    a, d, dt, f_px = frames.e1, 2.3, 0.02, 367.0
    S = np.column_stack([np.full(300, d), rng.uniform(-2, 2, 300), rng.uniform(-1.5, 1.5, 300)])
    p0 = S / np.linalg.norm(S, axis=1, keepdims=True)
    P1 = S @ frames.exp_so3(2e-3 * a)
    p1 = P1 / np.linalg.norm(P1, axis=1, keepdims=True)
    phi = solve_translational_flow(p0, p1, dt, a, np.ones(300))
    without = f_px * flow_residuals(p0, p1, dt, a, phi)
    p_mid = mid_bearings(p0, p1)
    phi_a, omega = solve_flow_axis(p_mid, (p1 - p0) / dt, p_mid @ a, np.ones(300), a)
    with_axis = f_px * flow_residuals(p0, p1 - dt * omega * np.cross(a, p_mid), dt, a, phi_a)
    assert np.percentile(without, 90) > 0.4
    assert np.max(with_axis) < 0.01


def test_two_plane_model_recovers_the_wall_flow_and_the_distance_ratio():
    """Exact bearings of wall and floor points (SPEC planes), moved by v dt, no rotation.

    Independent values: phi = v / d_w and s = d_w / d_t from the geometry; the one-plane fit
    of the same points is biased by the floor (checked, so the test shows the difference).
    """
    rng = np.random.default_rng(4)
    d_w, d_t, v, dt = 3.0, 1.0, np.array([0.8, 0.3, -0.1]), 1e-3
    wall = np.column_stack([np.full(300, d_w), rng.uniform(-2, 2, 300), rng.uniform(-2, 1, 300)])
    floor = np.column_stack([rng.uniform(1.0, d_w, 200), rng.uniform(-2, 2, 200),
                             np.full(200, d_t)])
    S = np.vstack([wall, floor])
    p0 = S / np.linalg.norm(S, axis=1, keepdims=True)
    P1 = S - v * dt
    p1 = P1 / np.linalg.norm(P1, axis=1, keepdims=True)
    p_mid, p_dot = mid_bearings(p0, p1), (p1 - p0) / dt
    c1, c2 = p_mid @ frames.e1, np.maximum(p_mid @ frames.e3, 0.0)
    threshold = 1e-5                                  # rad over dt
    s = joint_grid_start(p_mid, p_dot, c1, c2, dt, threshold)
    assert 0.5 * d_w / d_t < s < 2.0 * d_w / d_t      # the grid's cell
    for _ in range(2):                                # alternate phi | s and s | phi
        phi = solve_flow_c(p_mid, p_dot, np.maximum(c1, s * c2), np.ones(len(p_mid)))
        s = second_plane_ratio(p_mid, p_dot, c1, c2, phi, dt, threshold)
    assert s == pytest.approx(d_w / d_t, rel=0.05)    # enough to tell the planes apart
    on_wall = c1 >= s * c2          # wrong only next to the wall's foot, where c1 ~ s c2
    assert on_wall[:300].mean() > 0.97 and on_wall[300:].mean() < 0.03
    phi = solve_flow_c(p_mid[on_wall], p_dot[on_wall], c1[on_wall], np.ones(int(on_wall.sum())))
    np.testing.assert_allclose(phi, v / d_w, rtol=0.01, atol=1e-4)
    one_plane = solve_translational_flow(p0, p1, dt, frames.e1, np.ones(len(p0)))
    assert np.linalg.norm(one_plane - v / d_w) > 0.1 * np.linalg.norm(v / d_w)
    # no floor in view: s = 0, the one-plane model
    p_w = p0[:300], p1[:300]
    pm, pd = mid_bearings(*p_w), (p_w[1] - p_w[0]) / dt
    phi_w = solve_flow_c(pm, pd, pm @ frames.e1, np.ones(300))
    assert second_plane_ratio(pm, pd, pm @ frames.e1, np.maximum(pm @ frames.e3, 0.0), phi_w,
                              dt, threshold) == 0.0


def gyro_like_error(rng, n, std_rad=(1.1e-3, 0.62e-3, 0.23e-3)):
    """Attitude errors (n, 3) rotation vectors in {B}: a random walk whose step over a frame
    has PX4 SIH's imu/data gyro error over 20 ms (roll, pitch, yaw; docs/px4_sih.md)."""
    return np.cumsum(rng.normal(size=(n, 3)) * np.asarray(std_rad), axis=0)


def test_the_front_flow_at_a_hover_start_survives_a_real_gyros_attitude_error(scene):
    """The vehicle nearly still at the start (2.1-2.5 m from the wall, <= 0.2 m/s), each
    image's attitude off by a gyro-like error between frames (1.1 mrad over 20 ms about the
    front camera's axis): with the rotation about the optical axis fitted, at most 2 of the
    74 frames have no flow (1 measured: a still start estimates over 5-frame baselines, where
    the error across the view adds up) and the others are within 0.05 1/s of v/d (that error
    biases phi as a sideways translation would); without it, 4 x as many (10 measured; PX4
    SIH's "front_flow stale" at the start, docs/px4_sih.md)."""
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras['front'], renderers['front']
    counts = {}
    for fit in (True, False):
        nan, errors = 0, []
        for seed in (0, 1):
            rng = np.random.default_rng(seed)
            v = rng.normal(size=3)
            v *= rng.uniform(0.0, 0.2) / np.linalg.norm(v)
            xi0 = np.asarray(world.initial_position_I, float) + rng.uniform(-0.2, 0.2, 3)
            estimator = FlowEstimator(FlowConfig(fit_axis_rotation=fit), cam.model, cam.R_BC)
            detector = WindowDetector(WindowDetectorConfig())
            error_B = gyro_like_error(rng, 40)
            for k in range(40):
                t = k * DT
                R = frames.rot_from_euler_zyx(np.radians(1) * np.sin(3 * t + seed),
                                              np.radians(1) * np.sin(2.3 * t),
                                              world.initial_yaw + np.radians(1) * np.sin(1.7 * t))
                img = renderer.render(R, xi0 + v * t)
                img = np.clip(img + rng.normal(0.0, 1.5, img.shape), 0, 255).astype(np.uint8)
                R_est = R @ frames.exp_so3(error_B[k])
                window = detector.process(img, cam.model).detection
                assert window is not None
                eta, exclude = wall_normal_from_corners(window.bearings_C, R_est, cam.R_BC)
                result = estimator.process(img, t, R_est, eta, exclude, frames.e3)
                if k < 3:
                    continue
                if result.phi_I is None:
                    nan += 1
                    continue
                t_mid = t - estimator.last_baseline_frames * DT / 2.0
                errors.append(np.linalg.norm(
                    result.phi_I - v / (world.wall_x - (xi0[0] + v[0] * t_mid))))
        counts[fit] = nan
        if fit:
            assert np.percentile(errors, 95) < 0.05, np.percentile(errors, 95)
    assert counts[True] <= 2 and counts[False] >= 4 * max(counts[True], 1), counts


def test_rendered_front_flow_with_the_floor_in_view(scene):
    """2.5-4 m from the wall, 0.8-1.9 m up: the floor fills the lower image (~40 % of tracks).

    |v| = 1 m/s (>= 2 px per frame), |Omega| <= 1 rad/s. Measured (2026-11-25, seeds 5/6,
    20 poses each): one plane p95 13-26 %, two planes p95 1.0-2.8 %.
    """
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras['front'], renderers['front']
    rng = np.random.default_rng(21)
    errors = {False: [], True: []}
    for k in range(8):
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        omega = rng.normal(size=3)
        omega *= rng.uniform(0.2, 1.0) / np.linalg.norm(omega)
        xi0 = np.array([world.wall_x - rng.uniform(2.5, 4.0), rng.uniform(-0.3, 0.3),
                        -rng.uniform(0.8, 1.9)])
        R0 = frames.rot_from_euler_zyx(*rng.uniform(-0.08, 0.08, 3))
        R1 = R0 @ cv2.Rodrigues(omega * DT)[0]
        xi1 = xi0 + v * DT
        img0, img1 = renderer.render(R0, xi0), renderer.render(R1, xi1)
        window = WindowDetector(WindowDetectorConfig()).process(img1, cam.model).detection
        assert window is not None
        eta, exclude = wall_normal_from_corners(window.bearings_C, R1, cam.R_BC)
        truth = v / (world.wall_x - (xi0[0] + xi1[0]) / 2.0)
        for two in (False, True):
            estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
            eta2 = frames.e3 if two else None
            estimator.process(img0, 0.0, R0, eta, exclude, eta2)
            result = estimator.process(img1, DT, R1, eta, exclude, eta2)
            assert result is not None and result.phi_I is not None
            errors[two].append(np.linalg.norm(result.phi_I - truth) / np.linalg.norm(truth))
    assert max(errors[True]) <= 0.05, errors[True]
    assert max(errors[True]) < max(errors[False]), errors


def test_tracked_front_flow_approaching_with_the_floor_filling_the_lower_image(scene):
    """Issue 51's sequences: 2.5-4 m from the wall, 0.8-1.1 m up (the floor fills the lower
    image), level within 4 deg, 0.2-0.7 m/s mostly towards the wall, 50 Hz with read noise,
    the window detector's wall normal each frame: |phi - v/d| / |v/d| p95 <= 10 % (the
    issue's target; measured here 2.5 % over 6 such sequences, one plane 6.3 %)."""
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras['front'], renderers['front']
    errors = []
    for seed in (2, 3):                            # the two slowest of the measured six
        rng = np.random.default_rng(100 + seed)
        speed = rng.uniform(0.2, 0.7)
        d = np.array([1.0, rng.uniform(-0.3, 0.3), rng.uniform(-0.15, 0.15)])
        v = speed * d / np.linalg.norm(d)
        xi0 = np.array([world.wall_x - rng.uniform(2.5, 4.0), rng.uniform(-0.3, 0.3),
                        -rng.uniform(0.8, 1.1)])
        estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
        detector = WindowDetector(WindowDetectorConfig())
        for k in range(45):
            t = k * DT
            R = frames.rot_from_euler_zyx(np.radians(4) * np.sin(3 * t + seed),
                                          np.radians(3) * np.sin(2.3 * t),
                                          np.radians(3) * np.sin(1.7 * t + seed))
            img = renderer.render(R, xi0 + v * t)
            img = np.clip(img + rng.normal(0.0, 1.5, img.shape), 0, 255).astype(np.uint8)
            window = detector.process(img, cam.model).detection
            assert window is not None
            eta, exclude = wall_normal_from_corners(window.bearings_C, R, cam.R_BC)
            result = estimator.process(img, t, R, eta, exclude, frames.e3)
            if k < 5 or result is None or result.phi_I is None:
                continue
            t_mid = t - estimator.last_baseline_frames * DT / 2.0
            truth = v / (world.wall_x - (xi0[0] + v[0] * t_mid))
            errors.append(np.linalg.norm(result.phi_I - truth) / np.linalg.norm(truth))
    assert len(errors) >= 70
    assert np.percentile(errors, 95) <= 0.10, np.percentile(errors, 95)


def wall_fraction(camera, R_IB, xi, wall_x):
    """Fraction of the image whose rays meet the wall (x = wall_x, behind) before the floor."""
    u, v = np.meshgrid(np.arange(8, camera.model.width, 16), np.arange(8, camera.model.height, 16))
    b_C = camera.model.pixels_to_bearings(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    b_I = b_C @ (R_IB @ camera.R_BC).T
    with np.errstate(divide='ignore', invalid='ignore'):
        t_floor = np.where(b_I[:, 2] > 0, -xi[2] / b_I[:, 2], np.inf)
        t_wall = np.where(b_I[:, 0] < 0, (wall_x - xi[0]) / b_I[:, 0], np.inf)
    return float(np.mean(t_wall < t_floor))


def test_rendered_down_flow_with_the_wall_in_view(scene):
    """Landing near the wall (0.3-0.8 m in front of it, 0.8-1.8 m up): the wall is in view.

    The down flow fits the floor alone; the wall's tracks (7-36 % of the image here) do not
    fit that plane and the robust fit leaves them out. Measured (2026-11-26, 3 x 20 poses,
    |v| 0.3-1 m/s, |Omega| <= 1 rad/s): p95 2.6-4.4 %, max 5.0 % (a second plane with the
    wall's normal known: p95 0.5-0.6 %, not wired: docs/perception.md).
    """
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras['down'], renderers['down']
    rng = np.random.default_rng(31)
    errors, in_view = [], []
    for k in range(8):
        v, omega = random_motion(rng)
        v *= max(1.0, 0.3 / np.linalg.norm(v))
        xi0 = np.array([world.wall_x + rng.uniform(0.3, 0.8), rng.uniform(-0.3, 0.3),
                        -rng.uniform(0.8, 1.8)])
        R0 = frames.rot_from_euler_zyx(*rng.uniform(-0.1, 0.1, 3))
        R1 = R0 @ cv2.Rodrigues(omega * DT)[0]
        xi1 = xi0 + v * DT
        in_view.append(wall_fraction(cam, R1, xi1, world.wall_x))
        estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
        estimator.process(renderer.render(R0, xi0), 0.0, R0, frames.e3, None)
        result = estimator.process(renderer.render(R1, xi1), DT, R1, frames.e3, None)
        assert result is not None and result.phi_I is not None
        truth = v / (-(xi0[2] + xi1[2]) / 2.0)
        errors.append(np.linalg.norm(result.phi_I - truth) / np.linalg.norm(truth))
    assert min(in_view) > 0.05, in_view            # the wall is in view in every pose
    assert max(errors) <= 0.10, errors


def test_slow_motion_is_estimated_over_a_longer_baseline(scene):
    """Down camera, 0.3-1.6 m up, |v| 0.03-0.3 m/s (0.3-3 px per frame), |Omega| <= 0.5 rad/s.

    The same 8 rendered sequences (8 frames, 50 Hz) through a frame-to-frame estimator and
    one with max_baseline_frames 5: the longer baseline is used when the image moves slowly
    and lowers the worst error. Measured (2026-11-25, seeds 3-4, 12 cases each): frame to
    frame up to 27 % at 0.5-1 px per frame, with baselines up to 5 frames <= 5.5 %.
    """
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras['down'], renderers['down']
    rng = np.random.default_rng(8)
    errors = {1: [], 5: []}
    baselines = []
    for case in range(8):
        v = rng.normal(size=3)
        v *= rng.uniform(0.03, 0.3) / np.linalg.norm(v)
        omega = rng.normal(size=3)
        omega *= rng.uniform(0.0, 0.5) / np.linalg.norm(omega)
        xi = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), -rng.uniform(0.3, 1.6)])
        R = frames.rot_from_euler_zyx(*rng.uniform(-0.05, 0.05, 3))
        estimators = {k: FlowEstimator(FlowConfig(max_baseline_frames=k), cam.model, cam.R_BC)
                      for k in errors}
        for k in range(8):
            img = renderer.render(R, xi)
            results = {n: e.process(img, k * DT, R, frames.e3) for n, e in estimators.items()}
            R, xi = R @ cv2.Rodrigues(omega * DT)[0], xi + v * DT
        truth = v / -(xi[2] - 2.5 * v[2] * DT)      # d at the longest baseline's middle
        for n, result in results.items():
            assert result is not None and result.phi_I is not None
            errors[n].append(np.linalg.norm(result.phi_I - truth) / np.linalg.norm(truth))
        speed_px = np.linalg.norm(truth) * DT * cam.model.K[0, 0]
        baselines.append((speed_px, estimators[5].last_baseline_frames))
        assert estimators[1].last_baseline_frames == 1
    assert max(errors[5]) <= 0.06, errors[5]
    assert max(errors[5]) < max(errors[1]), errors
    # slow: the longest baseline; >= 2 px per frame: frame to frame or nearly
    slow = [n for px, n in baselines if px < 0.4]
    fast = [n for px, n in baselines if px >= 2.0]
    assert slow and fast, baselines                  # both regimes are in the cases
    assert all(n == 5 for n in slow) and all(n <= 2 for n in fast), baselines


def test_inside_spherical_polygon():
    corners = np.array([[-1, -1, 5.0], [1, -1, 5.0], [1, 1, 5.0], [-1, 1, 5.0]])
    corners /= np.linalg.norm(corners, axis=1, keepdims=True)
    p = np.array([[0, 0, 1.0], [0.5, 0, 1.0], [0, 0, -1.0]])
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    np.testing.assert_array_equal(inside_spherical_polygon(p, corners, 0.0), [True, False, False])


@pytest.mark.parametrize('camera', ['down', 'front'])
def test_rendered_flow_within_10_percent(scene, camera):
    """|phi - v/d| <= 10 % |v/d| for |v| >= 0.1 m/s and |Omega| <= 1 rad/s, 20 ms apart."""
    world, vehicle, renderers = scene
    cam, renderer = vehicle.cameras[camera], renderers[camera]
    rng = np.random.default_rng(11 if camera == 'down' else 12)
    errors = []
    for k in range(8):
        v, omega = random_motion(rng)
        if camera == 'down':    # reference descent over the pad, after the window
            xi0 = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2),
                            -rng.uniform(0.3, 1.6)])
        else:                   # reference approach, the window in view
            xi0 = np.array([rng.uniform(-2.0, -1.7), rng.uniform(-0.1, 0.1), -1.75])
        R0 = frames.rot_from_euler_zyx(*rng.uniform(-0.08, 0.08, 3))
        R1 = R0 @ cv2.Rodrigues(omega * DT)[0]
        xi1 = xi0 + v * DT
        img0, img1 = renderer.render(R0, xi0), renderer.render(R1, xi1)
        if camera == 'down':
            eta, exclude = frames.e3, None
            d = -(xi0[2] + xi1[2]) / 2.0
        else:
            window = WindowDetector(WindowDetectorConfig()).process(img1, cam.model).detection
            assert window is not None
            eta, exclude = wall_normal_from_corners(window.bearings_C, R1, cam.R_BC)
            assert np.degrees(np.arccos(eta @ frames.e1)) < 2.0
            d = world.wall_x - (xi0[0] + xi1[0]) / 2.0
        estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
        assert estimator.process(img0, 0.0, R0, eta, exclude) is None
        result = estimator.process(img1, DT, R1, eta, exclude)
        assert result is not None and result.phi_I is not None
        assert 0.0 <= result.inlier_ratio <= 1.0
        errors.append(np.linalg.norm(result.phi_I - v / d) / np.linalg.norm(v / d))
    assert max(errors) <= 0.10, errors


def test_pyramid_levels_reach_twice_the_motion_left():
    assert LK_MOTION_MARGIN == 2.0
    assert pyramid_levels_for(None, 2.0, 3) == 3                 # unknown: every level
    assert pyramid_levels_for(float('nan'), 2.0, 3) == 3
    assert pyramid_levels_for(0.0, 2.0, 3) == 0
    assert pyramid_levels_for(1.0, 2.0, 3) == 0                  # reach 2 >= 2 x 1
    assert pyramid_levels_for(1.01, 2.0, 3) == 1                 # reach 4
    assert pyramid_levels_for(3.9, 2.0, 3) == 2                  # reach 8 >= 7.8
    assert pyramid_levels_for(50.0, 2.0, 3) == 3                 # capped
    assert pyramid_levels_for(50.0, 2.0, 0) == 0


def _sequence(renderer, R0, omega, xi0, v, n):
    """n images DT apart of a constant body rate omega (body FRD) and velocity v ({I})."""
    out, R, xi = [], R0, xi0
    for k in range(n):
        out.append((renderer.render(R, xi), k * DT, R))
        R, xi = R @ cv2.Rodrigues(omega * DT)[0], xi + v * DT
    return out


def test_a_pure_rotation_is_predicted_and_tracked_on_the_base_level(scene):
    """1 rad/s of yaw and pitch over the floor, no translation: the features move ~8 px a
    frame, the rotation predicts it all (what is left is LK's own noise), so after the first
    frames the search runs on the base level only, and phi stays ~0 as without prediction."""
    _, vehicle, renderers = scene
    cam = vehicle.cameras['down']
    frames_ = _sequence(renderers['down'], np.eye(3), np.array([0.0, 0.6, 0.8]),
                        np.array([0.0, 0.0, -1.2]), np.zeros(3), 12)
    results = {}
    for predict in (True, False):
        estimator = FlowEstimator(FlowConfig(lk_predict=predict), cam.model, cam.R_BC)
        phis, levels, left, raw = [], [], [], []
        for img, t, R in frames_:
            before = estimator._points.copy()
            r = estimator.process(img, t, R, frames.e3)
            if r is not None and r.phi_I is not None:
                phis.append(np.linalg.norm(r.phi_I))
            levels.append(estimator.last_pyramid_levels)
            left.append(estimator._rotation_motion_px)
            if len(before) and len(estimator._points):
                raw.append(np.median(np.linalg.norm(
                    estimator._points[:10] - before[:10], axis=1)))
        results[predict] = phis
        if predict:
            assert min(raw[2:]) > 5.0                    # the image moves ~8 px a frame
            assert max(x for x in left[3:]) < 0.5        # nearly all of it predicted
            assert levels[:2] == [None, 3] and set(levels[4:]) == {0}
            assert estimator.retracks == 0
        else:
            assert set(levels[1:]) == {3}
    assert len(results[True]) == len(results[False]) >= 10
    assert max(results[True]) < 0.02 and max(results[False]) < 0.02     # v = 0: phi ~ 0


def test_after_a_gap_the_flow_does_not_depend_on_the_frames_before_it(scene):
    """A gated flow computes a few frames, then none for a while (another mode), then again:
    what it estimates from there must be what a fresh estimator estimates (the replenishment
    cadence started from the frames before the gap shifted every later track set)."""
    _, vehicle, renderers = scene
    cam = vehicle.cameras['down']
    seq = _sequence(renderers['down'], np.eye(3), np.array([0.1, -0.2, 0.3]),
                    np.array([0.0, 0.0, -1.2]), np.array([0.3, 0.1, 0.0]), 14)
    before = [(img, t - 1.0, R) for img, t, R in seq[:3]]    # 1 s before: a gap >> 5 frames
    outputs = []
    for history in ([], before):
        estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
        for img, t, R in history:
            estimator.process(img, t, R, frames.e3)
        results = [estimator.process(img, t, R, frames.e3) for img, t, R in seq]
        outputs.append([r.phi_I for r in results if r is not None])
    assert len(outputs[0]) >= 10
    assert all(np.array_equal(a, b) for a, b in zip(*outputs)) and \
        len(outputs[0]) == len(outputs[1])


def test_a_translation_is_predicted_by_each_tracks_own_motion(scene):
    """0.5 m/s at 1.2 m over the floor, slow yaw: ~3 px a frame that the rotation does not
    predict; each track's last motion does (to a fraction of a px), so the search drops to
    the base level except just after new features (no motion yet), and phi is the same as
    without the prediction to 2e-3 relative (and within 5 % of v / d). The tracks of the two
    searches differ by their convergence (~0.01 px); with the rotation about the optical axis
    fitted too (one more unknown), phi moves with them 1.6e-3 at most (1e-3 without)."""
    _, vehicle, renderers = scene
    cam = vehicle.cameras['down']
    v = np.array([0.4, 0.3, 0.0])
    frames_ = _sequence(renderers['down'], np.eye(3), np.array([0.0, 0.0, 0.3]),
                        np.array([-0.3, -0.2, -1.2]), v, 16)
    phis = {}
    for predict in (True, False):
        estimator = FlowEstimator(FlowConfig(lk_predict=predict), cam.model, cam.R_BC)
        phis[predict], levels, by_motion, by_rotation = [], [], [], []
        for img, t, R in frames_:
            r = estimator.process(img, t, R, frames.e3)
            phis[predict].append(None if r is None else r.phi_I)
            levels.append(estimator.last_pyramid_levels)
            by_motion.append(estimator._motion_px)
            by_rotation.append(estimator._rotation_motion_px)
        if predict:
            assert min(by_rotation[3:]) > 2.0            # the translation, unpredicted
            assert max(by_motion[3:]) < 0.5              # predicted by the track's motion
            assert levels.count(0) >= 8 and estimator.retracks == 0
    for a, b in zip(phis[True][2:], phis[False][2:]):
        assert a is not None and b is not None
        assert np.linalg.norm(a - b) <= 2e-3 * np.linalg.norm(b)
        assert np.linalg.norm(a - v / 1.2) <= 0.05 * np.linalg.norm(v / 1.2)


def test_a_sudden_unpredicted_jump_is_tracked_again_with_every_level(scene):
    """After a still hover the search runs on the base level; an image 12 px away that no
    prediction saw coming loses most tracks there, so it is searched again with all levels
    (retracks), and the tracks survive it."""
    _, vehicle, renderers = scene
    cam = vehicle.cameras['down']
    estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
    xi = np.array([0.0, 0.0, -1.2])
    for k in range(6):
        estimator.process(renderers['down'].render(np.eye(3), xi), k * DT, np.eye(3),
                          frames.e3)
    assert estimator.last_pyramid_levels == 0 and estimator.retracks == 0
    n = estimator.n_points
    jumped = xi + np.array([12.0 * 1.2 / float(cam.model.K[0, 0]), 0.0, 0.0])   # ~12 px
    estimator.process(renderers['down'].render(np.eye(3), jumped), 6 * DT, np.eye(3),
                      frames.e3)
    assert estimator.retracks == 1 and estimator.last_pyramid_levels == 3
    assert estimator.n_points >= 0.8 * n


def test_flow_config_refuses_a_bad_capture():
    for bad in (0.0, -1.0, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='lk_capture_px'):
            FlowConfig(lk_capture_px=bad)


def test_flow_refuses_a_stale_or_unknown_attitude(scene):
    _, vehicle, renderers = scene
    cam = vehicle.cameras['down']
    img = renderers['down'].render(np.eye(3), np.array([0.0, 0.0, -1.0]))
    estimator = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
    estimator.process(img, 0.0, np.eye(3), frames.e3)
    assert estimator.process(img, DT, None, frames.e3) is None          # no attitude
    assert estimator.process(img, 5.0, np.eye(3), frames.e3) is None    # gap too long


def test_attitude_buffer_interpolates_and_propagates_a_constant_rate():
    omega = np.array([0.3, -0.5, 0.8])
    R0 = frames.rot_from_euler_zyx(0.1, -0.2, 0.5)

    def truth(t):
        return R0 @ cv2.Rodrigues(omega * t)[0]
    buf = AttitudeBuffer(AttitudeBufferConfig())
    for t in np.arange(0.0, 0.1, 0.01):
        buf.add(t, truth(t), omega)
    for t in (0.013, 0.0555, 0.09, 0.11):       # between samples, and 20 ms after the last
        np.testing.assert_allclose(buf.attitude_at(t), truth(t), atol=1e-9)
    assert buf.attitude_at(-0.01) is None and buf.attitude_at(0.3) is None
    with pytest.raises(ValueError):
        buf.add(0.2, np.full((3, 3), np.nan), omega)


def test_attitude_buffer_rate_at_interpolates_the_gyro_and_holds_the_newest():
    buf = AttitudeBuffer(AttitudeBufferConfig())
    for k, t in enumerate((0.0, 0.01, 0.02)):
        buf.add(t, np.eye(3), np.array([0.1 * k, -0.2, 0.0]))
    np.testing.assert_allclose(buf.rate_at(0.015), [0.15, -0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(buf.rate_at(0.01), [0.1, -0.2, 0.0])
    np.testing.assert_allclose(buf.rate_at(0.03), [0.2, -0.2, 0.0])       # held, 10 ms after
    assert buf.rate_at(-0.01) is None and buf.rate_at(0.5) is None and \
        buf.rate_at(float('nan')) is None


def test_image_decoding():
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 255                         # pure red
    padded = np.zeros((2, 10), np.uint8)      # step 10 > 3 x 3 bytes of padding
    padded[:, :9] = rgb.reshape(2, 9)
    grey = image_to_mono8(padded.tobytes(), 3, 2, 'rgb8', 10)
    assert grey.shape == (2, 3) and np.all(grey == 76)            # BT.601: 0.299 x 255
    bgr = image_to_mono8(rgb[..., ::-1].tobytes(), 3, 2, 'bgr8', 9)
    np.testing.assert_array_equal(bgr, grey)
    for args in ((b'\0' * 6, 3, 2, 'mono16', 6), (b'\0' * 5, 3, 2, 'mono8', 3),
                 (b'\0' * 6, 3, 2, 'mono8', 2), (b'', 0, 0, 'mono8', 0)):
        with pytest.raises(ImageFormatError):
            image_to_mono8(*args)


def test_image_decoding_with_alpha_ignores_the_alpha():
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, 7         # red, a stray alpha
    assert np.all(image_to_mono8(rgba.tobytes(), 3, 2, 'rgba8', 12) == 76)
    assert np.all(image_to_mono8(rgba[..., [2, 1, 0, 3]].tobytes(), 3, 2, 'bgra8', 12) == 76)


@pytest.mark.parametrize('encoding, luma_first', [
    ('yuv422_yuy2', True), ('yuyv', True), ('yuv422', False), ('uyvy', False)])
def test_yuv422_decodes_to_its_y_bytes(encoding, luma_first):
    rng = np.random.default_rng(3)
    y = rng.integers(16, 236, (4, 6), dtype=np.uint8)
    chroma = rng.integers(16, 241, (4, 6), dtype=np.uint8)      # U V U V ... per row
    pairs = np.stack([y, chroma] if luma_first else [chroma, y], axis=-1).reshape(4, 12)
    padded = np.zeros((4, 14), np.uint8)                         # 2 bytes of row padding
    padded[:, :12] = pairs
    grey = image_to_mono8(padded.tobytes(), 6, 4, encoding, 14)
    np.testing.assert_array_equal(grey, y)
    code = cv2.COLOR_YUV2GRAY_YUY2 if luma_first else cv2.COLOR_YUV2GRAY_UYVY   # 2nd method
    np.testing.assert_array_equal(grey, cv2.cvtColor(pairs.reshape(4, 6, 2), code))
    with pytest.raises(ImageFormatError, match='step'):
        image_to_mono8(pairs.tobytes(), 6, 4, encoding, 11)


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
def test_bayer_decodes_to_the_luma_of_the_colour_its_name_says(pattern):
    # a uniform colour, mosaicked as the ROS name reads (first row: pattern[0:2], second:
    # pattern[2:4]); red and blue differ, so a pattern read the wrong way round shows
    red, green, blue = 200, 100, 20
    value = {'r': red, 'g': green, 'b': blue}
    mosaic = np.zeros((8, 10), np.uint8)
    for dy in (0, 1):
        for dx in (0, 1):
            mosaic[dy::2, dx::2] = value[pattern[2 * dy + dx]]
    grey = image_to_mono8(mosaic.tobytes(), 10, 8, f'bayer_{pattern}8', 10)
    luma = 0.299 * red + 0.587 * green + 0.114 * blue              # BT.601: 121.0
    assert grey.shape == (8, 10)
    assert np.all(np.abs(grey[2:-2, 2:-2].astype(float) - luma) <= 1.0), grey
    with pytest.raises(ImageFormatError, match='2x2'):
        image_to_mono8(b'\0' * 3, 3, 1, f'bayer_{pattern}8', 3)
