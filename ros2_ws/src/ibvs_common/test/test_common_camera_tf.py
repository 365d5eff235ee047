"""The cameras' static transforms base_link -> optical frame: independent geometric facts.

The expected values are written by hand from the frames' definitions (base_link FLU, body
FRD, optical z along the axis, x right, y down), and the quaternions are applied with this
file's own q v q*, not with frames.py.
"""
import dataclasses

import numpy as np
import pytest

from ibvs_common.core.camera_tf import camera_transforms
from ibvs_common.core.config import load_vehicle
from ibvs_common.core.frames import bearings_C_to_I, vec_frd_to_flu

VEHICLE = load_vehicle()
RNG = np.random.default_rng(46)


def hamilton(a, b):
    """Hamilton product of (x, y, z, w) quaternions, written out here."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def rotate(q_xyzw, v):
    """Return q v q* for a unit quaternion (x, y, z, w): v's coordinates in the parent."""
    conj = np.array([-q_xyzw[0], -q_xyzw[1], -q_xyzw[2], q_xyzw[3]])
    return hamilton(hamilton(q_xyzw, [*v, 0.0]), conj)[:3]


def transform_of(child, cameras=None):
    tfs = camera_transforms((cameras or VEHICLE.cameras).values())
    return next(t for t in tfs if t.child == child)


def flu_by_hand(v_frd):
    """Body FRD -> base_link FLU: forward stays, right becomes -left, down becomes -up."""
    return np.array([v_frd[0], -v_frd[1], -v_frd[2]])


def random_rotation():
    q = RNG.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_one_transform_per_camera_from_base_link_to_its_optical_frame():
    tfs = camera_transforms(VEHICLE.cameras.values())
    assert [t.child for t in tfs] == [c.frame_id for c in VEHICLE.cameras.values()]
    assert {t.child for t in tfs} == {'down_camera_optical_frame',
                                      'front_camera_optical_frame'}
    assert all(t.parent == 'base_link' for t in tfs)


def test_the_down_cameras_optical_axis_points_down_in_base_link():
    q = transform_of('down_camera_optical_frame').q_xyzw
    assert np.allclose(rotate(q, [0.0, 0.0, 1.0]), [0.0, 0.0, -1.0])   # FLU: down is -z
    # the shipped mount: image x = body right (FRD +y) = base_link -y
    assert np.allclose(rotate(q, [1.0, 0.0, 0.0]), [0.0, -1.0, 0.0])


def test_the_front_cameras_axes_in_base_link():
    q = transform_of('front_camera_optical_frame').q_xyzw
    assert np.allclose(rotate(q, [0.0, 0.0, 1.0]), [1.0, 0.0, 0.0])    # looks forward
    assert np.allclose(rotate(q, [1.0, 0.0, 0.0]), [0.0, -1.0, 0.0])   # image x: right
    assert np.allclose(rotate(q, [0.0, 1.0, 0.0]), [0.0, 0.0, -1.0])   # image y: down
    # the ROS convention's well-known base_link -> camera optical quaternion
    assert np.allclose(q, [-0.5, 0.5, -0.5, 0.5])


def test_the_lever_arm_is_the_optical_centre_in_flu():
    cams = {name: dataclasses.replace(c, t_BC=np.array([0.05, 0.02, 0.03]))
            for name, c in VEHICLE.cameras.items()}
    axis_flu = {'down': [0.0, 0.0, -1.0], 'front': [1.0, 0.0, 0.0]}   # the optical axes
    for name, cam in cams.items():
        tf = transform_of(cam.frame_id, cams)
        assert np.allclose(tf.translation, [0.05, -0.02, -0.03])
        # a point 1 m ahead of the camera, in base_link: x = R(q) x_C + translation
        ahead = rotate(tf.q_xyzw, [0.0, 0.0, 1.0]) + tf.translation
        assert np.allclose(ahead, np.array([0.05, -0.02, -0.03]) + axis_flu[name])


def test_any_mount_unit_quaternion_rotates_as_the_mount_then_frd_to_flu():
    for k in range(20):
        R_BC = random_rotation()
        t_BC = RNG.uniform(-0.3, 0.3, size=3)
        cam = dataclasses.replace(VEHICLE.cameras['front'], name=f'c{k}',
                                  frame_id=f'c{k}_optical_frame', R_BC=R_BC, t_BC=t_BC)
        (tf,) = camera_transforms([cam])
        assert np.isclose(np.linalg.norm(tf.q_xyzw), 1.0, atol=1e-12) and tf.q_xyzw[3] >= 0.0
        assert np.allclose(tf.translation, flu_by_hand(t_BC))
        for v in RNG.normal(size=(5, 3)):
            assert np.allclose(rotate(tf.q_xyzw, v), flu_by_hand(R_BC @ v), atol=1e-12)
            # the same direction as the graph's derotation (bearings_C_to_I, level vehicle)
            assert np.allclose(rotate(tf.q_xyzw, v),
                               vec_frd_to_flu(bearings_C_to_I(v, np.eye(3), R_BC)), atol=1e-12)


def test_two_cameras_of_one_frame_id_are_refused():
    down = VEHICLE.cameras['down']
    twin = dataclasses.replace(VEHICLE.cameras['front'], frame_id=down.frame_id)
    with pytest.raises(ValueError, match='frame_id'):
        camera_transforms([down, twin])
