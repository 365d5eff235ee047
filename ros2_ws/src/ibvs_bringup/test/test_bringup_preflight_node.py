"""The preflight with real rclpy: keep-up, the autopilot's set-up, the pad, the command.

GraphHealth on a watcher node fed by a fake graph node: the keep-up check reads camera_info
and corners, the failsafe and armability checks the bridge's /diagnostics, the pad check the
down camera's images (rendered by the sim's renderer); the ``preflight`` command in its own
process prints the checklist and the go/no-go line, exits 1 on a no-go and publishes it.
"""
import itertools
import os
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
import rclpy
from geometry_msgs.msg import Point32, PolygonStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import CameraInfo, Image

from ibvs_bringup.preflight import (GraphHealth, KEEP_UP_GRACE_S, KEEP_UP_MIN_FRAMES,
                                    PAD_TRIES)
from ibvs_common.node_common import MODE_QOS, PREFLIGHT_TOPIC, preflight_verdict

TAG = str(int(time.time() * 1000) % 100000)
KEEP_UP = 'perception keeps up (window/corners per front frame)'
FRAMES = 30


def _spin(executor, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.002)


def _keep_up_after(context, answer: bool) -> tuple:
    """Publish FRAMES front frames (camera_info), each answered on window/corners or not."""
    executor = SingleThreadedExecutor(context=context)
    watcher = rclpy.create_node(f'preflight_watch_{TAG}', context=context)
    graph = rclpy.create_node(f'preflight_graph_{TAG}', context=context)
    health = GraphHealth(watcher)
    info_pub = graph.create_publisher(CameraInfo, 'front_camera/camera_info', 10)
    corners_pub = graph.create_publisher(PolygonStamped, 'window/corners', 10)
    for node in (watcher, graph):
        executor.add_node(node)
    try:
        deadline = time.monotonic() + 5.0
        while (info_pub.get_subscription_count() == 0
               or corners_pub.get_subscription_count() == 0) and time.monotonic() < deadline:
            _spin(executor, 0.01)
        for _ in range(FRAMES):
            stamp = graph.get_clock().now().to_msg()
            info = CameraInfo(width=752, height=480)
            info.header.stamp = stamp
            info_pub.publish(info)
            _spin(executor, 0.003)
            if answer:
                corners = PolygonStamped()
                corners.header.stamp = stamp
                corners.polygon.points = [Point32(x=1.0, y=0.0, z=0.0)] * 4
                corners_pub.publish(corners)
            _spin(executor, 0.007)
        _spin(executor, KEEP_UP_GRACE_S + 0.1)      # every frame old enough to be judged
        return next((c.ok, c.detail) for c in health.checklist() if c.name == KEEP_UP)
    finally:
        executor.shutdown()
        watcher.destroy_node()
        graph.destroy_node()


def test_keep_up_passes_when_every_front_frame_is_answered_at_once(context):
    ok, detail = _keep_up_after(context, answer=True)
    assert ok, detail
    answered, judged = (int(x) for x in detail.split(' frames answered')[0].split(' / '))
    assert judged >= KEEP_UP_MIN_FRAMES and answered >= 0.95 * judged, detail


def test_keep_up_fails_when_the_window_detector_is_silent(context):
    ok, detail = _keep_up_after(context, answer=False)
    assert not ok and detail.startswith('0 / ') and 'frames answered' in detail, detail


def _graph(context, name: str, **health_kw) -> tuple:
    """(executor, watcher with GraphHealth(**health_kw), fake graph node, health)."""
    executor = SingleThreadedExecutor(context=context)
    watcher = rclpy.create_node(f'preflight_watch_{name}_{TAG}', context=context)
    graph = rclpy.create_node(f'preflight_graph_{name}_{TAG}', context=context)
    health = GraphHealth(watcher, **health_kw)
    for node in (watcher, graph):
        executor.add_node(node)
    return executor, watcher, graph, health


def _wait_matched(executor, *pubs) -> None:
    deadline = time.monotonic() + 5.0
    while any(p.get_subscription_count() == 0 for p in pubs) and time.monotonic() < deadline:
        _spin(executor, 0.01)


def _check(health, name: str) -> tuple:
    return next((c.ok, c.skipped, c.detail) for c in health.checklist() if c.name == name)


FAILSAFE, ARMABLE, PAD = ('autopilot failsafe when the bridge stops', 'armed or armable',
                          'pad in view of the down camera')


def test_the_autopilot_set_up_is_judged_from_the_bridges_diagnostics(context):
    executor, watcher, graph, health = _graph(context, 'setup', autopilot_setup=True)
    diag = graph.create_publisher(DiagnosticArray, '/diagnostics', 10)
    try:
        _wait_matched(executor, diag)
        assert _check(health, FAILSAFE)[:2] == (False, False)       # nothing reported yet

        def bridge(action: str, armable: str) -> None:
            values = {'link': 'up', 'autopilot': 'px4', 'armed': 'False', 'armable': armable,
                      'source_system': '1', 'COM_OBL_RC_ACT': action, 'COM_OF_LOSS_T': '1'}
            diag.publish(DiagnosticArray(status=[DiagnosticStatus(
                name='mavlink_bridge: MAVLink link', level=DiagnosticStatus.OK,
                values=[KeyValue(key=k, value=v) for k, v in values.items()])]))
            _spin(executor, 0.2)
        bridge('0', 'False')                                        # PX4's default: Position
        ok, _, detail = _check(health, FAILSAFE)
        assert not ok and 'set COM_OBL_RC_ACT = 4' in detail, detail
        assert not _check(health, ARMABLE)[0]
        assert not health.healthy()
        bridge('4', 'True')
        assert _check(health, FAILSAFE)[0] and _check(health, ARMABLE)[0]
        # without the autopilot's set-up (a scripted run's gate) both are listed as skipped
        plain = GraphHealth(watcher)
        _spin(executor, 0.1)
        assert _check(plain, FAILSAFE)[1] and _check(plain, ARMABLE)[1]
        assert _check(plain, PAD)[1]
    finally:
        executor.shutdown()
        watcher.destroy_node()
        graph.destroy_node()


def _info_msg(camera) -> CameraInfo:
    model = camera.model
    msg = CameraInfo(width=model.width, height=model.height,
                     distortion_model=model.distortion_model)
    msg.k = model.K.reshape(-1).tolist()
    msg.d = model.D.tolist()
    return msg


def _image_msg(gray, stamp) -> Image:
    msg = Image(height=gray.shape[0], width=gray.shape[1], encoding='mono8',
                step=gray.shape[1], data=gray.tobytes())
    msg.header.stamp = stamp
    return msg


def _pad_check_after(context, name: str, gray, info) -> tuple:
    """Publish PAD_TRIES down images (and camera_info) to a pad-checking GraphHealth."""
    ticks = itertools.count(step=1.0)                # each image 1 s later: each one tried
    executor, watcher, graph, health = _graph(context, name, check_pad=True,
                                              clock=lambda: next(ticks))
    info_pub = graph.create_publisher(CameraInfo, 'down_camera/camera_info', 10)
    image_pub = graph.create_publisher(Image, 'down_camera/image_raw', 10)
    try:
        _wait_matched(executor, info_pub, image_pub)
        for _ in range(PAD_TRIES):
            stamp = graph.get_clock().now().to_msg()
            info.header.stamp = stamp
            info_pub.publish(info)
            _spin(executor, 0.02)
            image_pub.publish(_image_msg(gray, stamp))
            _spin(executor, 0.1)
        return _check(health, PAD)
    finally:
        executor.shutdown()
        watcher.destroy_node()
        graph.destroy_node()


def test_the_pad_check_searches_the_down_images_for_the_pad(context):
    from ibvs_common.core.config import load_pad_layout, load_vehicle
    from ibvs_sim.core.render import SceneRenderer
    from ibvs_sim.core.world import load_world
    camera = load_vehicle().cameras['down']
    renderer = SceneRenderer(load_world(), load_pad_layout(), camera)
    over_pad = renderer.render(np.eye(3), np.array([0.0, 0.0, -1.0]))   # 1 m above the pad
    ok, skipped, detail = _pad_check_after(context, 'pad', over_pad, _info_msg(camera))
    assert ok and not skipped, detail
    assert detail.startswith(f'complete groups in {PAD_TRIES} of the last {PAD_TRIES}')
    assert '(A' in detail, detail
    blank = np.full_like(over_pad, 128)                                  # no pad in view
    ok, _, detail = _pad_check_after(context, 'nopad', blank, _info_msg(camera))
    assert not ok and detail.startswith(f'complete groups in 0 of the last {PAD_TRIES}')
    wrong = _info_msg(camera)                                            # a wrong CameraInfo
    wrong.width = 640
    ok, _, detail = _pad_check_after(context, 'badinfo', over_pad, wrong)
    assert not ok and 'CameraInfo size 640x480 != image size' in detail, detail


def test_the_preflight_command_says_no_go_exits_1_and_publishes_its_verdict(context):
    """No graph at all: the checklist, the NO-GO line last, exit 1, ibvs/preflight latched."""
    node = rclpy.create_node(f'preflight_verdict_{TAG}', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    verdicts = []
    node.create_subscription(DiagnosticArray, PREFLIGHT_TOPIC, verdicts.append, MODE_QOS)
    try:
        proc = subprocess.Popen([sys.executable, '-m', 'ibvs_bringup.preflight', '--timeout',
                                 '2'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=dict(os.environ))
        deadline = time.monotonic() + 60.0
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        out = proc.communicate(timeout=10.0)[0]
        assert proc.returncode == 1, out
        lines = out.strip().splitlines()
        assert lines[-1].startswith('PREFLIGHT NO-GO: ') and lines[-1].endswith('(after 2 s)')
        assert f'  [FAIL] {FAILSAFE}: not reported' in out, out
        assert f'  [SKIP] {PAD}: not checked' in out, out
        assert _spin_until(executor, lambda: verdicts, 5.0)
        go, summary = preflight_verdict(verdicts[-1])
        assert go is False and lines[-1].startswith(summary), (summary, lines[-1])
    finally:
        executor.shutdown()
        node.destroy_node()


def _spin_until(executor, done, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    return bool(done())
