"""Translational optical flow, IMU attitude buffer and image decoding of ibvs_perception.

Flow ground truth: phi = v / d from the rendered poses (d at mid-interval), SPEC.md planes.
"""
import cv2
import numpy as np
import pytest

from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.attitude_buffer import AttitudeBuffer, AttitudeBufferConfig
from ibvs_perception.core.flow import (FlowConfig, FlowEstimator, inside_spherical_polygon,
                                       solve_translational_flow, wall_normal_from_corners)
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
