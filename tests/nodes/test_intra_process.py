"""In-process imu/data (ibvs_common.intra_process) with real rclpy executors and nodes."""
import threading
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu

from ibvs_common.intra_process import IntraProcessTopic, subscribe
from ibvs_common.node_common import SENSOR_QOS
from ibvs_common.spin import make_executor

TAG = str(int(time.time() * 1000) % 100000)


def spin_until(executor, done, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        executor.spin_once(timeout_sec=0.01)
    return done()


def imu(sec: int) -> Imu:
    msg = Imu()
    msg.header.stamp.sec = sec
    msg.orientation.w = 1.0
    return msg


@pytest.mark.parametrize('kind', ['events', 'single'])
def test_messages_published_from_another_thread_arrive_in_the_executor_thread(context, kind):
    executor = (make_executor(context) if kind == 'events'
                else SingleThreadedExecutor(context=context))
    node = rclpy.create_node(f'ip_pub_{kind}_{TAG}', context=context)
    topic = IntraProcessTopic('imu/data')
    topic.attach_publisher(node)
    got, threads = [], set()

    def on_imu(msg):
        got.append(msg.header.stamp.sec)
        threads.add(threading.current_thread().name)

    assert subscribe(node, Imu, 'imu/data', on_imu, SENSOR_QOS, topic) is None
    assert topic.subscriber_count == 1
    topic.publish(imu(0))                       # node not spun yet: dropped, counted
    assert topic.dropped == 1
    executor.add_node(node)
    try:
        sender = threading.Thread(target=lambda: [topic.publish(imu(k)) for k in range(1, 6)],
                                  name='reader')
        sender.start()
        sender.join()
        assert spin_until(executor, lambda: len(got) == 5, 2.0)
        assert got == [1, 2, 3, 4, 5]                    # in order, each once
        assert threads == {threading.current_thread().name}
        # keep-last: 15 published while the executor does not run -> the newest 10
        for k in range(10, 25):
            topic.publish(imu(k))
        spin_until(executor, lambda: len(got) >= 15, 1.0)
        executor.spin_once(timeout_sec=0.05)
        assert got[5:] == list(range(15, 25)) and topic.dropped == 1 + 5
        assert topic.delivered == 15
    finally:
        executor.shutdown()
        node.destroy_node()


def test_subscribe_falls_back_to_dds_and_refuses_another_topic(context):
    node = rclpy.create_node(f'ip_dds_{TAG}', context=context)
    try:
        sub = subscribe(node, Imu, 'imu/data', lambda m: None, SENSOR_QOS, None)
        assert sub is not None and sub.topic_name == '/imu/data'
        with pytest.raises(ValueError, match='imu/data'):
            subscribe(node, Imu, 'imu/other', lambda m: None, SENSOR_QOS,
                      IntraProcessTopic('imu/data'))
        topic = IntraProcessTopic('imu/data')
        topic.attach_publisher(node)
        with pytest.raises(RuntimeError):
            topic.attach_publisher(node)
        with pytest.raises(ValueError):
            IntraProcessTopic('imu/data', depth=0)
    finally:
        node.destroy_node()


def test_composed_nodes_take_imu_in_process_and_the_bridge_counts_them(context):
    """build_nodes wires the five IMU consumers to the bridge without DDS subscriptions."""
    from ibvs_bringup import composed, graph
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    nodes = composed.build_nodes(specs, context)
    try:
        by_exe = {}
        for spec, node in zip(specs, nodes):
            by_exe.setdefault(spec.executable, []).append(node)
        bridge = by_exe['mavlink_bridge'][0]
        assert bridge._imu_local.subscriber_count == 5    # window, 2 flows, supervisor, ctrl
        for node in nodes:
            assert '/imu/data' not in [s.topic_name for s in node.subscriptions], node.get_name()
        # the setpoint stream's gate counts them: 5 >= min_imu_subscribers
        bridge._check_imu_consumers()
        assert bridge._bridge.stream_enabled
        # a sample handed over reaches the five through the executor, as the object itself
        executor = make_executor(context)
        for node in nodes:
            executor.add_node(node)
        try:
            bridge._imu_local.publish(imu(7))
            assert spin_until(executor, lambda: bridge._imu_local.delivered == 1, 2.0)
        finally:
            executor.shutdown()
    finally:
        for node in nodes:
            node.destroy_node()


def test_bridge_counts_in_process_subscribers_for_its_stream_gate(context):
    from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode
    topic = IntraProcessTopic('imu/data')
    topic.subscribe(lambda m: None)
    bridge = MavlinkBridgeNode(
        node_name=f'ip_bridge_{TAG}', context=context, imu_local=topic,
        parameter_overrides=[Parameter('url', value='udpin:127.0.0.1:0'),
                             Parameter('min_imu_subscribers', value=1)])
    try:
        assert not bridge._bridge.stream_enabled
        bridge._check_imu_consumers()
        assert bridge._bridge.stream_enabled
    finally:
        bridge.destroy_node()


def test_composed_nodes_get_their_own_parameters_and_remappings(context):
    """Each node's NodeSpec.ros_args() apply to it alone, as in its own process."""
    from ibvs_bringup import composed, graph
    specs = graph.sim_graph(graph.GraphOptions(mavlink_port=14998))
    onboard = [s for s in specs if s.role == 'onboard']
    detector = next(s for s in onboard if s.executable == 'window_detector')
    i = onboard.index(detector)
    onboard[i] = graph.NodeSpec(detector.package, detector.executable, detector.name,
                                detector.parameters + ({'max_corner_jump_px': 12.5},),
                                (('window/corners', 'elsewhere/corners'),))
    nodes = composed.build_nodes(onboard, context)
    try:
        by_name = {n.get_name(): n for n in nodes}
        det = by_name[detector.name]
        assert det.get_parameter('max_corner_jump_px').value == 12.5
        assert '/elsewhere/corners' in [p.topic_name for p in det.publishers]
        for node in nodes:
            assert node.get_parameter('use_sim_time').value is True     # the sim graph's
            if node is not det:
                assert '/elsewhere/corners' not in [p.topic_name for p in node.publishers]
                if node.has_parameter('max_corner_jump_px'):
                    assert node.get_parameter('max_corner_jump_px').value != 12.5
    finally:
        for node in nodes:
            node.destroy_node()


def test_bridge_publishes_imu_through_dds_only_while_a_reader_is_matched(context):
    """Composed: no DDS reader -> the DDS publish is skipped (in process only); a recorder
    that subscribes gets every sample from its match on, as with rclcpp's intra-process."""
    from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode
    topic = IntraProcessTopic('imu/data')
    local = []
    topic.subscribe(local.append)
    bridge = MavlinkBridgeNode(
        node_name=f'ip_skip_{TAG}', context=context, imu_local=topic,
        parameter_overrides=[Parameter('url', value='udpin:127.0.0.1:0')])
    recorder = rclpy.create_node(f'ip_recorder_{TAG}', context=context)
    executor = make_executor(context)
    executor.add_node(bridge)
    executor.add_node(recorder)
    try:
        bridge._publish_imu(imu(1))
        assert bridge.imu_dds_skipped == 1
        assert spin_until(executor, lambda: len(local) == 1, 2.0)   # in process regardless
        got = []
        recorder.create_subscription(Imu, 'imu/data', lambda m: got.append(m.header.stamp.sec),
                                     SENSOR_QOS)
        assert spin_until(executor, lambda: bridge._imu_pub.get_subscription_count() == 1, 5.0)
        for k in range(2, 5):
            bridge._publish_imu(imu(k))
        assert spin_until(executor, lambda: len(got) == 3 and len(local) == 4, 2.0)
        assert got == [2, 3, 4] and bridge.imu_dds_skipped == 1
    finally:
        executor.shutdown()
        recorder.destroy_node()
        bridge.destroy_node()
