"""The ibvs_perception nodes in-process with real rclpy: rendered images in, messages out.

Each test owns an rclpy context, fake publishers/subscribers with unique names, and spins a
SingleThreadedExecutor with a deadline.
"""
import os
import time
from unittest import mock

import cv2
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point32, PolygonStamped, Vector3Stamped
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import Float32, Header

from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_common.core.modes import Mode
from ibvs_common.node_common import (LateImuReport, superseded_from_msg, SUPERSEDED_TOPIC,
                                     supervisor_status_msg)
from ibvs_sim.core.world import load_world
from ibvs_control.core.frame_inputs import is_no_flow
from ibvs_perception.optical_flow_node import OpticalFlowNode
from ibvs_perception.pad_detector_node import PadDetectorNode
from ibvs_perception.core.latest_only import MIN_IMAGES
from ibvs_perception.image_diagnostics import image_status_name
from ibvs_perception.window_detector_node import WindowDetectorNode
from ibvs_sim.core.render import SceneRenderer

VEHICLE = load_vehicle()
WORLD = load_world()
PAD = load_pad_layout()
TAG = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
START = np.array([-2.0, 0.1, -1.82])
DT = 0.02


@pytest.fixture(scope='module')
def renderers():
    return {n: SceneRenderer(WORLD, PAD, VEHICLE.cameras[n]) for n in ('front', 'down')}


@pytest.fixture()
def ctx():
    context = rclpy.context.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    yield context, executor, nodes
    executor.shutdown()
    for n in nodes:
        n.destroy_node()
    rclpy.try_shutdown(context=context)


def spin_until(executor, done, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        executor.spin_once(timeout_sec=0.01)
    return done()


def stamp(t):
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def image_msg(gray, t, encoding='mono8', step=None):
    msg = Image()
    msg.header.stamp = stamp(t)
    msg.height, msg.width = gray.shape
    msg.encoding = encoding
    data = gray if encoding == 'mono8' else cv2.cvtColor(
        gray, cv2.COLOR_GRAY2BGR if encoding == 'bgr8' else cv2.COLOR_GRAY2RGB)
    msg.step = step if step is not None else data.shape[1] * (1 if data.ndim == 2 else 3)
    msg.data = data.tobytes()
    return msg


def info_msg(name):
    model = VEHICLE.cameras[name].model
    msg = CameraInfo()
    msg.width, msg.height = model.width, model.height
    msg.k = model.K.reshape(-1).tolist()
    msg.d = model.D.tolist()
    msg.distortion_model = model.distortion_model
    return msg


def imu_msg(t, R_IB, omega_B=np.zeros(3)):
    q = frames.quat_wxyz_to_xyzw(frames.quat_from_rot(frames.rot_map_base_from_R_IB(R_IB)))
    w = frames.vec_frd_to_flu(omega_B)
    msg = Imu()
    msg.header.stamp = stamp(t)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = map(float, q)
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = map(float, w)
    return msg


def harness(context, nodes, inputs, outputs):
    """A helper node with publishers {topic: type} and collecting subscribers {topic: type}."""
    node = rclpy.create_node(f'perception_test_{TAG}_{len(nodes)}', context=context)
    nodes.append(node)
    pubs = {t: node.create_publisher(m, t, qos_profile_sensor_data if 'image' in t else 10)
            for t, m in inputs.items()}
    got = {t: [] for t in outputs}
    for t, m in outputs.items():
        node.create_subscription(m, t, got[t].append, 10)
    return node, pubs, got


def window_node(ctx, outputs):
    """A window detector fed by a helper with the front camera's image and CameraInfo."""
    context, executor, nodes = ctx
    node = WindowDetectorNode(f'window_detector_{TAG}', context=context)
    nodes.append(node)
    helper, pubs, got = harness(context, nodes,
                                {'front_camera/image_raw': Image,
                                 'front_camera/camera_info': CameraInfo}, outputs)
    for n in (node, helper):
        executor.add_node(n)
    return node, pubs, got


def test_window_detector_node(ctx, renderers):
    executor = ctx[1]
    node, pubs, got = window_node(ctx, {'window/corners': PolygonStamped,
                                        'window/edge_normals': PolygonStamped})
    img = renderers['front'].render(np.eye(3), START)
    # no CameraInfo yet: an empty polygon, no exception
    pubs['front_camera/image_raw'].publish(image_msg(img, 1.0))
    assert spin_until(executor, lambda: len(got['window/corners']) >= 1)
    assert len(got['window/corners'][-1].polygon.points) == 0
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    spin_until(executor, lambda: node.camera_info is not None)
    pubs['front_camera/image_raw'].publish(image_msg(img, 2.5, 'bgr8'))
    assert spin_until(executor, lambda: len(got['window/edge_normals']) >= 2)
    corners = got['window/corners'][-1]
    assert (corners.header.stamp.sec, corners.header.stamp.nanosec) == (2, 500_000_000)
    assert corners.header.frame_id == 'front_camera_optical_frame'
    b = np.array([[p.x, p.y, p.z] for p in corners.polygon.points])
    truth = frames.bearings_I_to_C(WORLD.window.corners_I() - START, np.eye(3),
                                   VEHICLE.cameras['front'].R_BC)
    truth /= np.linalg.norm(truth, axis=1, keepdims=True)
    assert b.shape == (4, 3) and np.max(np.linalg.norm(b - truth, axis=1)) < 3e-3
    assert len(got['window/edge_normals'][-1].polygon.points) == 4
    # wrong step and wrong encoding: empty polygons, never an exception
    pubs['front_camera/image_raw'].publish(image_msg(img, 3.0, step=100))
    assert spin_until(executor, lambda: len(got['window/corners']) >= 3)
    bad = image_msg(img, 3.1)
    bad.encoding = '16UC1'
    pubs['front_camera/image_raw'].publish(bad)
    assert spin_until(executor, lambda: len(got['window/corners']) >= 4)
    assert all(len(m.polygon.points) == 0 for m in got['window/corners'][2:])


def test_a_node_behind_computes_the_newest_image_waiting_and_skips_the_older(ctx, renderers):
    """Three images already waiting when the node gets to its camera: it takes them at once
    (latest only at the reader) and answers only the newest; the other two count as
    superseded, each reported on ibvs/frames_superseded for the supervisor's rate governor,
    and the executor's events of the two taken find nothing."""
    executor = ctx[1]
    node, pubs, got = window_node(ctx, {'window/corners': PolygonStamped,
                                        SUPERSEDED_TOPIC: Header})
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    spin_until(executor, lambda: node.camera_info is not None)
    img = renderers['front'].render(np.eye(3), START)
    for k in range(3):
        pubs['front_camera/image_raw'].publish(image_msg(img, 5.0 + 0.02 * k))
    time.sleep(0.3)                         # all three in the reader before the next spin
    assert spin_until(executor, lambda: len(got['window/corners']) >= 1)
    spin_until(executor, lambda: False, 0.3)
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in got['window/corners']] \
        == [(5, 40_000_000)]
    assert node.gated.counts.superseded == 2 and node.gated.counts.computed == 1
    assert sorted(superseded_from_msg(m) for m in got[SUPERSEDED_TOPIC]) == \
        [('front', 5_000_000_000), ('front', 5_020_000_000)]


def test_window_detector_node_tracks_through_a_fast_yaw_with_the_imu(ctx, renderers):
    """imu/data in, images of a 5 rad/s yaw swing: every frame detected (the gyro moves the
    tracked window before the 30 px gate); the node's rotation matches the attitudes sent."""
    context, executor, nodes = ctx
    node = WindowDetectorNode(f'window_detector_gyro_{TAG}', context=context)
    nodes.append(node)
    helper, pubs, got = harness(context, nodes,
                                {'front_camera/image_raw': Image,
                                 'front_camera/camera_info': CameraInfo, 'imu/data': Imu},
                                {'window/corners': PolygonStamped})
    for n in (node, helper):
        executor.add_node(n)
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    spin_until(executor, lambda: node.camera_info is not None)
    R_BC = VEHICLE.cameras['front'].R_BC
    yaw = [0.0, 0.1, 0.2, 0.3, 0.4]               # rad per 20 ms frame: 5 rad/s, ~37 px
    for k, psi in enumerate(yaw):
        t = 1.0 + 0.02 * k
        R_IB = frames.rot_z(psi)
        pubs['imu/data'].publish(imu_msg(t, R_IB, np.array([0.0, 0.0, 5.0])))
        assert spin_until(executor, lambda: (node.attitudes.newest_stamp or 0.0) >= t - 1e-9)
        if k:                                        # the rotation the node will apply
            d = np.array([0.3, -0.4, 0.87])          # a fixed direction in {I}
            b_prev = (frames.rot_z(yaw[k - 1]) @ R_BC).T @ d
            b_now = (R_IB @ R_BC).T @ d
            R_IC = node.attitudes.attitude_at(t) @ R_BC
            np.testing.assert_allclose((R_IC.T @ node.R_IC_prev) @ b_prev, b_now, atol=1e-9)
        pubs['front_camera/image_raw'].publish(
            image_msg(renderers['front'].render(R_IB, START), t))
        assert spin_until(executor, lambda: len(got['window/corners']) >= k + 1)
    assert all(len(m.polygon.points) == 4 for m in got['window/corners']), \
        [len(m.polygon.points) for m in got['window/corners']]


def test_window_detector_node_refuses_a_nan_imu_sample_and_keeps_detecting(ctx, renderers):
    """A NaN attitude is dropped (throttled error), not buffered; the next image is answered."""
    context, executor, nodes = ctx
    node = WindowDetectorNode(f'window_detector_nan_{TAG}', context=context)
    nodes.append(node)
    helper, pubs, got = harness(context, nodes,
                                {'front_camera/image_raw': Image,
                                 'front_camera/camera_info': CameraInfo, 'imu/data': Imu},
                                {'window/corners': PolygonStamped})
    for n in (node, helper):
        executor.add_node(n)
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    spin_until(executor, lambda: node.camera_info is not None)
    pubs['imu/data'].publish(imu_msg(1.0, np.eye(3)))
    assert spin_until(executor, lambda: len(node.attitudes) == 1)
    bad = imu_msg(1.01, np.eye(3))
    bad.orientation.w = float('nan')
    pubs['imu/data'].publish(bad)
    pubs['front_camera/image_raw'].publish(
        image_msg(renderers['front'].render(np.eye(3), START), 1.02))
    assert spin_until(executor, lambda: len(got['window/corners']) >= 1)
    assert len(node.attitudes) == 1                          # the NaN sample was not kept
    assert len(got['window/corners'][0].polygon.points) == 4


def test_pad_detector_node(ctx, renderers):
    context, executor, nodes = ctx
    node = PadDetectorNode(f'pad_detector_{TAG}', context=context)
    nodes.append(node)
    helper, pubs, got = harness(context, nodes,
                                {'down_camera/image_raw': Image,
                                 'down_camera/camera_info': CameraInfo},
                                {'pad/landmarks': PolygonStamped, 'pad/groups': JointState})
    for n in (node, helper):
        executor.add_node(n)
    pubs['down_camera/camera_info'].publish(info_msg('down'))
    spin_until(executor, lambda: node.camera_info is not None)
    img = renderers['down'].render(np.eye(3), np.array([0.0, 0.0, -1.0]))
    pubs['down_camera/image_raw'].publish(image_msg(img, 7.25, 'rgb8'))
    assert spin_until(executor, lambda: len(got['pad/groups']) >= 1
                      and len(got['pad/landmarks']) >= 1)
    msg = got['pad/landmarks'][-1]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (7, 250_000_000)
    groups = got['pad/groups'][-1]           # stamped and framed like its landmarks
    assert groups.header == msg.header
    names = list(groups.name)
    assert names[0] == 'A' and len(msg.polygon.points) == 4 * len(names)
    # a wrong-size CameraInfo: empty landmarks, empty group list
    wrong = info_msg('down')
    wrong.width = 640
    pubs['down_camera/camera_info'].publish(wrong)
    spin_until(executor, lambda: node.camera_info.width == 640)
    pubs['down_camera/image_raw'].publish(image_msg(img, 8.0))
    assert spin_until(executor, lambda: len(got['pad/groups']) >= 2)
    assert len(got['pad/landmarks'][-1].polygon.points) == 0
    assert list(got['pad/groups'][-1].name) == []
    assert got['pad/groups'][-1].header == got['pad/landmarks'][-1].header


def flow_node(context, nodes, camera):
    node = OpticalFlowNode(f'{camera}_optical_flow_{TAG}', context=context,
                           parameter_overrides=[Parameter('camera', value=camera)])
    nodes.append(node)
    prefix = f'{camera}_camera'
    inputs = {f'{prefix}/image_raw': Image, f'{prefix}/camera_info': CameraInfo,
              'imu/data': Imu, 'window/corners': PolygonStamped}
    outputs = {f'{prefix}/translational_flow': Vector3Stamped,
               f'{prefix}/translational_flow_quality': Float32}
    return node, *harness(context, nodes, inputs, outputs)


def stamp_s(msg):
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def polygon_msg(t, n=4):
    msg = PolygonStamped()
    msg.header.stamp = stamp(t)
    msg.header.frame_id = 'front_camera_optical_frame'
    msg.polygon.points = [Point32(x=0.0, y=0.0, z=1.0) for _ in range(n)]
    return msg


def send_imu(executor, node, pubs, samples):
    """Publish IMU samples one by one (sensor-data QoS keeps only a few)."""
    for t, R in samples:
        n = len(node.attitudes)
        pubs['imu/data'].publish(imu_msg(t, R))
        assert spin_until(executor, lambda: len(node.attitudes) > n)
    assert spin_until(executor, lambda: node.camera_info is not None)


def test_down_optical_flow_node(ctx, renderers):
    context, executor, nodes = ctx
    node, helper, pubs, got = flow_node(context, nodes, 'down')
    for n in (node, helper):
        executor.add_node(n)
    pubs['down_camera/camera_info'].publish(info_msg('down'))
    v = np.array([0.3, -0.2, 0.1])
    xi0 = np.array([0.0, 0.1, -1.2])
    R = frames.rot_from_euler_zyx(0.05, -0.03, 0.4)
    send_imu(executor, node, pubs, [(9.99 + 0.01 * k, R) for k in range(6)])
    for k in range(2):
        img = renderers['down'].render(R, xi0 + v * DT * k)
        pubs['down_camera/image_raw'].publish(image_msg(img, 10.0 + DT * k))
        spin_until(executor, lambda: node.estimator is not None
                   and node.estimator.n_points > 0, 2.0)
    assert spin_until(executor, lambda: len(got['down_camera/translational_flow']) >= 1
                      and len(got['down_camera/translational_flow_quality']) >= 1)
    msg = got['down_camera/translational_flow'][-1]
    assert msg.header.frame_id == 'map'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (10, 20_000_000)
    phi_map = np.array([msg.vector.x, msg.vector.y, msg.vector.z])
    truth = frames.vec_I_to_map(v / (-(xi0[2] + v[2] * DT / 2)))
    assert np.linalg.norm(phi_map - truth) <= 0.1 * np.linalg.norm(truth)
    assert 0.0 < got['down_camera/translational_flow_quality'][-1].data <= 1.0
    # one message per image: the first image (no pair yet) got the all-NaN "no flow"
    first = got['down_camera/translational_flow'][0]
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (10, 0)
    assert is_no_flow([first.vector.x, first.vector.y, first.vector.z])
    # NaN IMU: dropped with a log; images after the buffer runs out: "no flow", no exception
    nan = imu_msg(10.05, R)
    nan.orientation.w = float('nan')
    pubs['imu/data'].publish(nan)
    n_before = len(got['down_camera/translational_flow'])
    for k in range(2, 4):                 # each answered before the next (latest only)
        img = renderers['down'].render(R, xi0 + v * DT * k)
        pubs['down_camera/image_raw'].publish(image_msg(img, 12.0 + DT * k))
        assert spin_until(executor, lambda: len(got['down_camera/translational_flow'])
                          == n_before + k - 1)
    for msg in got['down_camera/translational_flow'][n_before:]:
        assert is_no_flow([msg.vector.x, msg.vector.y, msg.vector.z])


def test_an_imu_sample_that_comes_after_its_image_is_reported_as_late(ctx, renderers):
    """An image beyond the newest IMU sample is answered at once (propagated attitude); the
    sample of its moment coming afterwards is warned about, and a sample after it is not."""
    context, executor, nodes = ctx
    node, helper, pubs, got = flow_node(context, nodes, 'down')
    for n in (node, helper):
        executor.add_node(n)
    node.log._logger = logger = mock.Mock()          # what the node logs, by level
    pubs['down_camera/camera_info'].publish(info_msg('down'))
    R = frames.rot_from_euler_zyx(0.05, -0.03, 0.4)
    send_imu(executor, node, pubs, [(9.99 + 0.01 * k, R) for k in range(5)])   # to 10.03
    img = renderers['down'].render(R, np.array([0.0, 0.1, -1.2]))
    pubs['down_camera/image_raw'].publish(image_msg(img, 10.04))
    assert spin_until(executor, lambda: len(got['down_camera/translational_flow']) >= 1)
    send_imu(executor, node, pubs, [(10.04, R), (10.05, R)])
    late = [(level, call.args[0]) for level in ('info', 'warning', 'error')
            for call in getattr(logger, level).call_args_list
            if LateImuReport.TEXT in call.args[0]]
    assert [level for level, _ in late] == ['warning'], logger.mock_calls
    assert 'sample of t = 10.040 s' in late[0][1] and '1 late sample(s) in all' in late[0][1]
    assert node.attitudes.late_samples == 1


def test_down_flow_is_computed_only_from_a_mode_that_uses_it(ctx, renderers):
    """Mode gating with real rclpy: no floor flow in WINDOW, then the images from T2 on.

    The switch to CROSSING at T2 releases the kept images stamped from T2 on at once; the
    one before primes the tracker, so the flow at T2 is already valid.
    """
    context, executor, nodes = ctx
    node, helper, pubs, got = flow_node(context, nodes, 'down')
    status_pub = helper.create_publisher(DiagnosticArray, 'ibvs/supervisor_status', 10)
    flows = got['down_camera/translational_flow']
    for n in (node, helper):
        executor.add_node(n)
    pubs['down_camera/camera_info'].publish(info_msg('down'))
    v = np.array([0.3, -0.2, 0.1])
    xi0 = np.array([0.0, 0.1, -1.2])
    R = frames.rot_from_euler_zyx(0.05, -0.03, 0.4)
    send_imu(executor, node, pubs, [(9.99 + 0.01 * k, R) for k in range(10)])

    def status(t, mode):
        n = len(node.gated.gate._changes)
        status_pub.publish(supervisor_status_msg(round(t * 1e9), int(mode), mode.name,
                                                 DiagnosticStatus.OK, {}))
        return spin_until(executor, lambda: len(node.gated.gate._changes) > n, 2.0)

    def image(k):
        pubs['down_camera/image_raw'].publish(
            image_msg(renderers['down'].render(R, xi0 + v * DT * k), 10.0 + DT * k))

    assert status(9.98, Mode.WINDOW)
    for k in range(3):                                  # 10.00, 10.02, 10.04: kept only
        image(k)
        spin_until(executor, lambda: False, 0.3)
    assert flows == [] and node.estimator is None
    assert status(10.04, Mode.CROSSING)                 # T2 at 10.04: 10.04 goes out at once
    assert spin_until(executor, lambda: len(flows) >= 1)
    image(3)
    assert spin_until(executor, lambda: len(flows) >= 2)
    assert [round(stamp_s(m), 2) for m in flows] == [10.04, 10.06]
    truth = frames.vec_I_to_map(v / (-(xi0[2] + v[2] * 1.5 * DT)))   # between 10.02, 10.04
    first = np.array([flows[0].vector.x, flows[0].vector.y, flows[0].vector.z])
    assert np.linalg.norm(first - truth) <= 0.1 * np.linalg.norm(truth)


def test_front_optical_flow_node_needs_a_window(ctx, renderers):
    context, executor, nodes = ctx
    node, helper, pubs, got = flow_node(context, nodes, 'front')
    for n in (node, helper):
        executor.add_node(n)
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    send_imu(executor, node, pubs, [(19.99 + 0.01 * k, np.eye(3)) for k in range(6)])
    for k in range(3):      # one image at a time, as a node that keeps up receives them
        img = renderers['front'].render(np.eye(3), START + np.array([0.3, 0.0, 0.0]) * DT * k)
        pubs['front_camera/image_raw'].publish(image_msg(img, 20.0 + DT * k))
        # no window detection: one all-NaN "no flow" per image, never a value
        assert spin_until(executor,
                          lambda: len(got['front_camera/translational_flow']) == k + 1)
    spin_until(executor, lambda: False, 0.3)
    flows = got['front_camera/translational_flow']
    assert [round(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, 6) for m in flows] == [
        round(20.0 + DT * k, 6) for k in range(3)]
    assert all(is_no_flow([m.vector.x, m.vector.y, m.vector.z]) for m in flows)
    # the wall plane of image t comes from the newest detection strictly older than t (the
    # same image's detection is computed in parallel: never waited for), within the age bound
    for k, t in enumerate((19.96, 19.98, 20.0)):   # best effort: one at a time
        pubs['window/corners'].publish(polygon_msg(t))
        assert spin_until(executor, lambda: len(node.window_msgs) == k + 1)
    assert stamp_s(node.window_before(20.0)) == pytest.approx(19.98)
    assert stamp_s(node.window_before(20.001)) == pytest.approx(20.0)
    assert node.window_before(19.96) is None
    # the clock steps back by 0.15 s: the detections of before are of another moment
    pubs['window/corners'].publish(polygon_msg(19.87))
    assert spin_until(executor, lambda: len(node.window_msgs) == 1)
    assert node.window_before(19.97) is not None and node.window_before(19.99) is not None
    assert stamp_s(node.window_before(19.99)) == pytest.approx(19.87)   # not 19.98


@pytest.mark.parametrize('name, value', [('max_window_age_frames', 0.5),
                                         ('imu_max_extrapolation_s', -0.1)])
def test_optical_flow_refuses_a_bad_timing_parameter(ctx, name, value):
    context, _, _ = ctx
    with pytest.raises(ValueError, match=name.removeprefix('imu_')):
        OpticalFlowNode(f'bad_flow_{TAG}', context=context,
                        parameter_overrides=[Parameter(name, value=value)])


FROZEN_CASES = {  # node -> (class, overrides, camera, image topic, output topic)
    'window_detector': (WindowDetectorNode, [], 'front', 'window/corners'),
    'pad_detector': (PadDetectorNode, [], 'down', 'pad/landmarks'),
    'front_optical_flow': (OpticalFlowNode, [Parameter('camera', value='front')], 'front',
                           'front_camera/translational_flow'),
    'down_optical_flow': (OpticalFlowNode, [Parameter('camera', value='down')], 'down',
                          'down_camera/translational_flow'),
}
OUTPUT_TYPES = {'window/corners': PolygonStamped, 'pad/landmarks': PolygonStamped,
                'front_camera/translational_flow': Vector3Stamped,
                'down_camera/translational_flow': Vector3Stamped}


@pytest.mark.parametrize('name', sorted(FROZEN_CASES))
def test_a_frozen_camera_gets_no_output_until_it_is_live_again(ctx, renderers, name):
    """The same image re-stamped: answered 3 times (frozen_after_frames), then nothing."""
    cls, overrides, camera, output = FROZEN_CASES[name]
    context, executor, nodes = ctx
    node = cls(f'{name}_frozen_{TAG}', context=context, parameter_overrides=overrides)
    nodes.append(node)
    prefix = f'{camera}_camera'
    helper, pubs, got = harness(context, nodes, {f'{prefix}/image_raw': Image,
                                                 f'{prefix}/camera_info': CameraInfo},
                                {output: OUTPUT_TYPES[output]})
    for n in (node, helper):
        executor.add_node(n)
    assert node.frozen.check.frozen_after_frames == 3          # params.yaml's default
    pubs[f'{prefix}/camera_info'].publish(info_msg(camera))
    assert spin_until(executor, lambda: node.camera_info is not None)
    xi = START if camera == 'front' else np.array([0.0, 0.0, -1.0])
    img = renderers[camera].render(np.eye(3), xi)
    stamps = [30.0 + DT * k for k in range(7)]
    for k in range(3):           # the image and 2 repeats: processed and answered
        pubs[f'{prefix}/image_raw'].publish(image_msg(img, stamps[k]))
        assert spin_until(executor, lambda: len(got[output]) == k + 1), (k, len(got[output]))
    for k in range(3, 6):        # 3, 4, 5 repeats: frozen, dropped, nothing published
        pubs[f'{prefix}/image_raw'].publish(image_msg(img, stamps[k]))
        assert spin_until(executor, lambda: node.frozen.dropped == k - 2), k
    spin_until(executor, lambda: False, 0.3)
    assert [round(stamp_s(m), 6) for m in got[output]] == [round(t, 6) for t in stamps[:3]]
    assert node.frozen.check.identical_frames == 5
    live = img.copy()
    live[240, 376] ^= 1          # one grey level of one pixel: a live frame again
    pubs[f'{prefix}/image_raw'].publish(image_msg(live, stamps[6]))
    assert spin_until(executor, lambda: len(got[output]) == 4)
    assert stamp_s(got[output][-1]) == pytest.approx(stamps[6])
    assert not node.frozen.check.frozen and node.frozen.dropped == 3


@pytest.mark.parametrize('name', sorted(FROZEN_CASES))
def test_frozen_after_frames_is_validated(ctx, name):
    cls, overrides, _, _ = FROZEN_CASES[name]
    context, _, _ = ctx
    with pytest.raises(ValueError, match='frozen_after_frames'):
        cls(f'{name}_bad_frozen_{TAG}', context=context,
            parameter_overrides=overrides + [Parameter('frozen_after_frames', value=0)])


def test_window_detector_node_counts_lost_grid_frames_and_missing_attitudes_on_diagnostics(
        ctx, renderers):
    executor = ctx[1]
    node, pubs, got = window_node(ctx, {'window/corners': PolygonStamped,
                                        '/diagnostics': DiagnosticArray})
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    assert spin_until(executor, lambda: node.camera_info is not None)
    img = renderers['front'].render(np.eye(3), START)
    # 50 Hz grid frames 0, 1 and 4 of t = 1 s: frames 2 and 3 never come; no IMU at all
    for i, t in enumerate((1.00, 1.02, 1.08)):
        pubs['front_camera/image_raw'].publish(image_msg(img, t))
        assert spin_until(executor, lambda: len(got['window/corners']) >= i + 1)

    def status():
        mine = [s for m in got['/diagnostics'] for s in m.status
                if s.name == image_status_name('window_detector')]
        return {kv.key: kv.value for kv in mine[-1].values} if mine else None, \
            mine[-1].level if mine else None
    assert spin_until(executor, lambda: status()[0] is not None
                      and status()[0]['images_computed'] == '3', timeout_s=5.0)
    values, level = status()
    assert values['grid_frames_missed'] == '2' and values['images_off_grid'] == '0'
    assert values['images_without_attitude'] == '3'
    assert float(values['processing_median_ms']) > 0.0
    assert level == DiagnosticStatus.WARN


def test_window_detector_node_skips_an_image_superseded_by_the_next_one_queued(ctx, renderers):
    executor = ctx[1]
    node, pubs, got = window_node(ctx, {'window/corners': PolygonStamped})
    pubs['front_camera/camera_info'].publish(info_msg('front'))
    assert spin_until(executor, lambda: node.camera_info is not None)
    img = renderers['front'].render(np.eye(3), START)
    rng = np.random.default_rng(0)

    def send(age_s):                   # a live image (read noise), stamped age_s ago
        live = np.clip(img + rng.integers(0, 3, img.shape), 0, 255).astype(np.uint8)
        now = node.get_clock().now().nanoseconds / 1e9
        pubs['front_camera/image_raw'].publish(image_msg(live, now - age_s))
        return now - age_s
    for k in range(MIN_IMAGES):        # the camera's delivery: the node takes them at once
        send(0.0)
        assert spin_until(executor, lambda: len(got['window/corners']) == k + 1)
    # the node was busy: an image 200 ms old, and the next, fresh, behind it
    send(0.2)
    newest = send(0.0)
    assert spin_until(executor, lambda: len(got['window/corners']) > MIN_IMAGES)
    spin_until(executor, lambda: False, timeout_s=0.2)
    assert [stamp_s(m) for m in got['window/corners'][MIN_IMAGES:]] == \
        [pytest.approx(newest, abs=1e-6)]
    assert node.gated.counts.superseded == 1
