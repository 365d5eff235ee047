"""Renderer of ibvs_sim: projection accuracy, occlusion and ArUco detectability."""
import cv2
import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.cv_compat import aruco_parameters, ArucoMarkerDetector
from ibvs_common.core.frames import bearings_I_to_C, rot_from_euler_zyx
from ibvs_sim.core.render import RenderError, SceneRenderer, TexturedPlane

DOT_SIGMA_M = 0.008


@pytest.fixture(scope='module')
def scene():
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    return {name: SceneRenderer(world, pad, vehicle.cameras[name])
            for name in ('front', 'down')}, world, pad, vehicle


def _predicted_pixel(renderer, R_IB, xi_I, P_I):
    """Independent prediction: the detectors' camera model applied to the 3-D point."""
    b_C = bearings_I_to_C((np.asarray(P_I) - xi_I)[None, :], R_IB, renderer.R_BC)
    uv, valid = renderer.camera.model.bearings_to_pixels(b_C)
    return uv[0], bool(valid[0])


def _dot_plane(P_I, edge_u_I, edge_v_I):
    """A black square centred on P_I with a Gaussian white dot at its centre."""
    n = 129
    half = (n - 1) / 2.0
    yy, xx = np.mgrid[0:n, 0:n]
    side = np.linalg.norm(edge_u_I)
    sigma_px = DOT_SIGMA_M / (side / n)
    tex = (255 * np.exp(-((xx - half) ** 2 + (yy - half) ** 2) / (2 * sigma_px ** 2)))
    corner = np.asarray(P_I) - 0.5 * np.asarray(edge_u_I) - 0.5 * np.asarray(edge_v_I)
    return TexturedPlane('dot', tex.astype(np.uint8), corner, edge_u_I, edge_v_I)


def _centroid(img, uv, radius=12):
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    win = img[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1].astype(float)
    win = np.where(win > 20, win, 0.0)
    vv, uu = np.mgrid[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    return np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()


@pytest.mark.parametrize('camera, xi, euler, P_I, normal', [
    # front camera, the paper's start, dot on the wall near a window corner (image edge)
    ('front', [-2.0, 0.1, -1.82], (0.0, 0.0, 0.0), [-0.51, 0.75, -2.2], 'x'),
    ('front', [-1.5, -0.3, -1.4], (0.1, -0.15, 0.3), [-0.51, -0.9, -0.9], 'x'),
    # down camera over the pad, dot on the floor far off-centre (strong distortion)
    ('down', [0.0, 0.0, -1.8], (0.0, 0.0, 0.0), [0.9, 1.6, -0.001], 'z'),
    ('down', [0.3, -0.2, -1.0], (-0.2, 0.1, 1.0), [-0.3, -0.4, -0.001], 'z'),
])
def test_point_lands_on_predicted_pixel(scene, camera, xi, euler, P_I, normal):
    renderers = scene[0]
    r = renderers[camera]
    R_IB = rot_from_euler_zyx(*euler)
    xi = np.array(xi)
    if normal == 'x':
        eu, ev = np.array([0.0, 0.4, 0.0]), np.array([0.0, 0.0, 0.4])
    else:
        eu, ev = np.array([0.0, 0.4, 0.0]), np.array([-0.4, 0.0, 0.0])
    r.overlay_planes = [_dot_plane(P_I, eu, ev)]
    try:
        img = r.render(R_IB, xi)
    finally:
        r.overlay_planes = []
    uv, valid = _predicted_pixel(r, R_IB, xi, P_I)
    assert valid
    err = np.linalg.norm(_centroid(img, uv) - uv)
    assert err < 0.5, f'dot at {_centroid(img, uv)}, predicted {uv}, error {err:.3f} px'


def _flat_shaded(renderer, floor_value, wall_value):
    """Replace the textures: floor (both halves) one grey, walls another (occlusion probe)."""
    for plane, value in ((renderer.floor_near, floor_value), (renderer.floor_far, floor_value),
                         (renderer.wall, wall_value), (renderer.back_wall, wall_value)):
        plane.pyramid = [np.full_like(level, value) for level in plane.pyramid]


@pytest.fixture()
def front_probe(scene):
    world, pad, vehicle = scene[1:]
    r = SceneRenderer(world, pad, vehicle.cameras['front'])
    _flat_shaded(r, 250, 5)
    r.markers = []
    return r


def test_wall_hides_floor_behind_it(front_probe):
    xi = np.array([-2.0, 0.0, -0.4])
    P_I = np.array([1.0, 0.0, 0.0])    # far floor; the line of sight meets the wall at z=-0.2
    uv, valid = _predicted_pixel(front_probe, np.eye(3), xi, P_I)
    assert valid
    img = front_probe.render(np.eye(3), xi)
    assert img[int(round(uv[1])), int(round(uv[0]))] < 30


def test_floor_seen_through_aperture(front_probe):
    xi = np.array([-2.0, 0.0, -2.0])
    P_I = np.array([2.0, 0.0, 0.0])    # the line of sight crosses x=-0.5 at z=-1.25 (aperture)
    uv, valid = _predicted_pixel(front_probe, np.eye(3), xi, P_I)
    assert valid
    img = front_probe.render(np.eye(3), xi)
    assert img[int(round(uv[1])), int(round(uv[0]))] > 220
    # while the wall beside the aperture is drawn in front of the floor behind it
    uv2, valid2 = _predicted_pixel(front_probe, np.eye(3), xi, np.array([-0.5, 1.0, -1.2]))
    assert valid2
    assert img[int(round(uv2[1])), int(round(uv2[0]))] < 30


def _detect(img):
    params = aruco_parameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = ArucoMarkerDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids = det.detect(img)
    found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(),
                                                                            corners)}
    return found


@pytest.mark.parametrize('height, yaw, groups', [
    (1.8, 0.0, ('A', 'B')), (1.8, 0.7, ('A', 'B')), (0.2, 0.0, ('C', 'D')),
    (0.2, 3.0, ('C', 'D'))])
def test_aruco_finds_pad_markers(scene, height, yaw, groups):
    renderers, _, pad, _ = scene
    r = renderers['down']
    R_IB = rot_from_euler_zyx(0.0, 0.0, yaw)
    xi = np.array([0.0, 0.0, -height])
    found = _detect(r.render(R_IB, xi))
    for g in pad.groups:
        if g.name in groups:
            assert set(g.ids) <= set(found), f'group {g.name} incomplete: {sorted(found)}'


def test_aruco_corners_match_geometry_and_orientation(scene):
    """Detected corners (ArUco order TL, TR, BR, BL) = the documented marker orientation."""
    renderers, _, pad, _ = scene
    r = renderers['down']
    R_IB = rot_from_euler_zyx(0.0, 0.0, 0.3)
    xi = np.array([0.05, -0.05, -1.2])
    found = _detect(r.render(R_IB, xi))
    group = pad.groups[0]
    for mid, c in zip(group.ids, group.marker_centres_I()):
        h = group.side / 2
        # top edge faces +x_I, columns run along +y_I
        corners_I = c + np.array([[h, -h, 0], [h, h, 0], [-h, h, 0], [-h, -h, 0]])
        uv = np.array([_predicted_pixel(r, R_IB, xi, P)[0] for P in corners_I])
        assert mid in found
        assert np.max(np.linalg.norm(found[mid] - uv, axis=1)) < 1.0


def test_render_output_and_bad_pose(scene):
    r = scene[0]['front']
    img = r.render(np.eye(3), np.array([-2.0, 0.1, -1.82]))
    assert img.dtype == np.uint8 and img.shape == (r.height, r.width)
    assert img.std() > 20   # textured, not a blank frame
    with pytest.raises(RenderError):
        r.render(np.eye(3), np.array([np.nan, 0.0, -1.0]))


def _profile_edge(img, uv, normal, half=4.0, step=0.05):
    """Edge position (px along ``normal`` from ``uv``) of a dark -> light step, by area.

    The image is sampled bilinearly along the normal from -half (dark side) to +half; with
    the profile normalised to [0, 1] between its ends, the step lies at half - integral.
    """
    t = np.arange(-half, half + step / 2, step)
    pts = uv + t[:, None] * normal
    x0, y0 = np.floor(pts[:, 0]).astype(int), np.floor(pts[:, 1]).astype(int)
    fx, fy = pts[:, 0] - x0, pts[:, 1] - y0
    im = img.astype(float)
    prof = ((1 - fx) * (1 - fy) * im[y0, x0] + fx * (1 - fy) * im[y0, x0 + 1]
            + (1 - fx) * fy * im[y0 + 1, x0] + fx * fy * im[y0 + 1, x0 + 1])
    lo, hi = prof[:10].mean(), prof[-10:].mean()
    p = np.clip((prof - lo) / (hi - lo), 0.0, 1.0)
    return half - np.sum((p[1:] + p[:-1]) / 2) * step


@pytest.mark.parametrize('xi, euler', [
    ([-2.0, 0.1, -1.82], (0.0, 0.0, 0.0)),
    ([-1.7, -0.15, -1.5], (0.06, -0.05, 0.1)),
])
def test_aperture_edge_on_projected_true_edge(front_probe, scene, xi, euler):
    """The rendered aperture's edges lie on the projected true edges (sub-pixel, no bias)."""
    world = scene[1]
    r = front_probe                  # flat: wall 5, floor 250; light back wall, no pad
    r.back_wall.pyramid = [np.full_like(level, 250) for level in r.back_wall.pyramid]
    r.quiet_zones_I = []
    R_IB = rot_from_euler_zyx(*euler)
    xi = np.array(xi)
    img = r.render(R_IB, xi)
    corners = world.window.corners_I()
    centre = corners.mean(axis=0)
    errors = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        for s in np.linspace(0.15, 0.85, 8):
            P = a + s * (b - a)
            uv, ok = _predicted_pixel(r, R_IB, xi, P)
            # image normal of the edge: from two nearby points on it, towards the aperture
            uv2, ok2 = _predicted_pixel(r, R_IB, xi, P + 1e-3 * (b - a))
            inward, ok3 = _predicted_pixel(r, R_IB, xi, P + 1e-3 * (centre - P))
            assert ok and ok2 and ok3
            tangent = (uv2 - uv) / np.linalg.norm(uv2 - uv)
            normal = np.array([-tangent[1], tangent[0]])
            if normal @ (inward - uv) < 0:
                normal = -normal
            errors.append(_profile_edge(img, uv, normal))
    errors = np.array(errors)
    assert abs(np.mean(errors)) < 0.05, f'aperture edge bias {np.mean(errors):+.3f} px'
    assert np.max(np.abs(errors)) < 0.15, f'aperture edge error {np.max(np.abs(errors)):.3f} px'


def test_a_lever_arm_moves_the_image_as_the_geometry_says(scene):
    """The optical centre is xi + R_IB t_BC: a dot lands where a pinhole at that centre puts it.

    A distortion-free down camera (K only, so the projection is computed by hand) 0.12 m
    forward and 0.05 m right of the body origin (body FRD), the body yawed by 0.4 rad at 1.2 m:
    P_C = R_BC^T (R_IB^T (P - xi) - t_BC), u = fx X/Z + cx, v = fy Y/Z + cy.
    """
    from dataclasses import replace
    from ibvs_common.core.camera import CameraModel
    world, pad, vehicle = scene[1:]
    K = [366.667, 0.0, 375.5, 0.0, 366.667, 239.5, 0.0, 0.0, 1.0]
    pinhole = CameraModel.from_camera_info(752, 480, K, [0.0] * 5, 'plumb_bob')
    t_BC = np.array([0.12, 0.05, 0.0])
    cam = replace(vehicle.cameras['down'], model=pinhole, t_BC=t_BC)
    R_IB, xi = rot_from_euler_zyx(0.0, 0.0, 0.4), np.array([-1.0, 0.4, -1.2])
    P_I = np.array([-0.8, 0.3, -0.001])            # on the floor, near the image centre
    by_hand = []
    for lever in (t_BC, np.zeros(3)):
        P_C = cam.R_BC.T @ (R_IB.T @ (P_I - xi) - lever)
        by_hand.append(np.array([K[0] * P_C[0] / P_C[2] + K[2], K[4] * P_C[1] / P_C[2] + K[5]]))
    rendered = []
    for camera in (cam, replace(cam, t_BC=np.zeros(3))):
        r = SceneRenderer(world, pad, camera)
        r.overlay_planes = [_dot_plane(P_I, np.array([0.0, 0.4, 0.0]),
                                       np.array([-0.4, 0.0, 0.0]))]
        rendered.append(_centroid(r.render(R_IB, xi), by_hand[len(rendered)]))
    shift = np.linalg.norm(by_hand[0] - by_hand[1])
    assert shift > 10.0                            # the lever arm matters here: ~40 px
    for got, want in zip(rendered, by_hand):
        assert np.linalg.norm(got - want) < 0.5, (got, want)
