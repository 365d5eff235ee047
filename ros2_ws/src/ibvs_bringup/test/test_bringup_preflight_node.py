"""The preflight's GraphHealth with real rclpy: the keep-up check reads camera_info and corners."""
import time

import rclpy
from geometry_msgs.msg import Point32, PolygonStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import CameraInfo

from ibvs_bringup.preflight import GraphHealth, KEEP_UP_GRACE_S, KEEP_UP_MIN_FRAMES

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
