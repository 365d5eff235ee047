"""In-process imu/data (ibvs_common.intra_process) with real rclpy executors and nodes."""
import threading
import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Imu

from ibvs_common.intra_process import (IntraProcessSubscription, IntraProcessTopic,
                                       subscribe)
from ibvs_common.node_common import SENSOR_QOS
from ibvs_common.spin import make_executor

TAG = str(int(time.time() * 1000) % 100000)


def spin_until(executor, done, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        executor.spin_once(timeout_sec=0.01)
    return done()


def imu(sec: int, nanosec: int = 0) -> Imu:
    msg = Imu()
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
    msg.orientation.w = 1.0
    return msg


def test_messages_published_from_another_thread_are_taken_in_order_by_each_subscriber():
    """Pulled delivery: publish only keeps; each take hands over what came since, in order."""
    topic = IntraProcessTopic('imu/data', depth=10)
    a, b = [], []
    topic.publish(imu(0))                       # no subscriber yet: nothing kept
    assert topic.published == 0
    sub_a = topic.subscribe(lambda m: a.append(m.header.stamp.sec))
    sub_b = topic.subscribe(lambda m: b.append(m.header.stamp.sec))
    assert topic.subscriber_count == 2
    sender = threading.Thread(target=lambda: [topic.publish(imu(k)) for k in range(1, 6)],
                              name='reader')
    sender.start()
    sender.join()
    assert a == [] and b == []                  # nothing runs without a take
    assert sub_a.take() == 5 and a == [1, 2, 3, 4, 5]
    assert sub_a.take() == 0 and a == [1, 2, 3, 4, 5]       # each message once
    topic.publish(imu(6))
    assert sub_a.take() == 1 and a[-1] == 6
    assert sub_b.take() == 6 and b == [1, 2, 3, 4, 5, 6]    # independent cursors
    # keep-last: 15 published without a take -> the newest 10, the other 5 counted lost
    for k in range(10, 25):
        topic.publish(imu(k))
    assert sub_a.take() == 10 and a[6:] == list(range(15, 25))
    assert sub_a.lost == 5 and sub_a.taken == 16
    assert sub_b.take() == 10 and sub_b.lost == 5


def test_a_take_from_within_the_callback_hands_over_only_the_rest():
    topic = IntraProcessTopic('imu/data')
    got = []
    sub = None

    def on_imu(msg):
        got.append(msg.header.stamp.sec)
        if msg.header.stamp.sec == 2:
            topic.publish(imu(9))               # arrives meanwhile (the reader thread)
            sub.take()                          # e.g. a callback that takes again

    sub = topic.subscribe(on_imu)
    for k in range(1, 5):
        topic.publish(imu(k))
    sub.take()
    assert got == [1, 2, 3, 4, 9] and sub.taken == 5 and sub.lost == 0


def test_subscribe_falls_back_to_dds_and_refuses_another_topic(context):
    node = rclpy.create_node(f'ip_dds_{TAG}', context=context)
    try:
        sub = subscribe(node, Imu, 'imu/data', lambda m: None, SENSOR_QOS, None)
        assert sub.subscription.topic_name == '/imu/data'
        assert sub.take() == 0                  # the executor delivers DDS messages
        with pytest.raises(ValueError, match='imu/data'):
            subscribe(node, Imu, 'imu/other', lambda m: None, SENSOR_QOS,
                      IntraProcessTopic('imu/data'))
        local = subscribe(node, Imu, 'imu/data', lambda m: None, SENSOR_QOS,
                          IntraProcessTopic('imu/data'))
        assert isinstance(local, IntraProcessSubscription)
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
        assert bridge._bridge.setpoints.enabled
        # a sample handed over reaches each of the five at its next take, the object itself
        bridge._imu_local.publish(imu(7))
        subs = bridge._imu_local._subscriptions
        assert [s.take() for s in subs] == [1] * 5 and [s.take() for s in subs] == [0] * 5
    finally:
        for node in nodes:
            node.destroy_node()


def test_composed_nodes_take_the_imu_samples_at_the_start_of_their_own_callbacks(context):
    """Nothing runs per sample (an idle graph never wakes for the IMU); the supervisor's timer,
    a product, a status and an image each take every sample published before them first, so
    that the attitude at their stamps is there."""
    from ibvs_bringup import composed, graph
    from ibvs_common.core.modes import InputKind
    from sensor_msgs.msg import Image
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    nodes = composed.build_nodes(specs, context)
    try:
        by_name = {n.get_name(): n for n in nodes}
        topic = by_name['mavlink_bridge']._imu_local
        supervisor, controller = by_name['mode_supervisor'], by_name['force_controller']
        front_flow, window = by_name['front_optical_flow'], by_name['window_detector']
        for k in range(3):
            topic.publish(imu(100, k * 10_000_000))             # 100 Hz
        consumers = (supervisor._attitudes, controller._attitudes, front_flow.attitudes,
                     window.attitudes)
        assert [len(a) for a in consumers] == [0, 0, 0, 0]     # nothing delivered on publish
        supervisor._on_timer()
        controller._add(InputKind.FLOW_FRONT, 100_000_000_000, None, '')
        front_flow.process(Image())            # a bad image: dropped after the take
        window.process(Image())
        assert [len(a) for a in consumers] == [3, 3, 3, 3]
        assert supervisor._attitudes.newest_stamp == 100.02
        topic.publish(imu(100, 30_000_000))
        controller._on_status(DiagnosticArray())   # a malformed status: refused after the take
        assert controller._imu.taken == 4 and len(controller._attitudes) == 4
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
        assert not bridge._bridge.setpoints.enabled
        bridge._check_imu_consumers()
        assert bridge._bridge.setpoints.enabled
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


def test_a_users_ros_args_win_over_the_parameter_file_in_the_composed_layout(context):
    """``composed --ros-args -p x:=v``: v, as for the node's own process (not params.yaml's).

    rcl lets a node's own arguments (its parameter file) win over the global ones: passed as
    global arguments only, the override was silently ignored (the idle benchmark's cases ran
    with the file's values until 2026-12-02).
    """
    from ibvs_bringup import composed, graph
    specs = [s for s in graph.onboard_graph(graph.GraphOptions(mavlink_url='udpin:127.0.0.1:0'))
             if s.name in ('mavlink_bridge', 'window_detector')]
    from_file = {}
    nodes = composed.build_nodes(specs, context)
    try:
        from_file = {n.get_name(): n.get_parameter('use_sim_time').value for n in nodes}
        bridge = next(n for n in nodes if n.get_name() == 'mavlink_bridge')
        assert bridge.get_parameter('attitude_rate_hz').value == 100.0      # params.yaml
    finally:
        for node in nodes:
            node.destroy_node()
    nodes = composed.build_nodes(specs, context, user_ros_args=(
        '--ros-args', '-p', 'attitude_rate_hz:=25.0', '-p', 'max_corner_jump_px:=12.5'))
    try:
        by_name = {n.get_name(): n for n in nodes}
        assert by_name['mavlink_bridge'].get_parameter('attitude_rate_hz').value == 25.0
        assert by_name['window_detector'].get_parameter('max_corner_jump_px').value == 12.5
        assert {n.get_name(): n.get_parameter('use_sim_time').value for n in nodes} \
            == from_file                                    # the rest as the file says
    finally:
        for node in nodes:
            node.destroy_node()


def test_bridge_publishes_imu_through_dds_only_while_a_reader_is_matched(context):
    """Composed: no DDS reader -> the DDS publish is skipped (in process only) and the message
    is built only when a co-located node takes it; a recorder that subscribes gets every
    sample from its match on, as with rclcpp's intra-process publish."""
    from ibvs_control.mavlink.telemetry import ImuSample
    from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode

    def sample(sec: int) -> ImuSample:
        return ImuSample(sec * 1_000_000_000, np.array([1.0, 0.0, 0.0, 0.0]),
                         np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 9.81]))

    topic = IntraProcessTopic('imu/data')
    local = []
    sub = topic.subscribe(local.append)
    bridge = MavlinkBridgeNode(
        node_name=f'ip_skip_{TAG}', context=context, imu_local=topic,
        parameter_overrides=[Parameter('url', value='udpin:127.0.0.1:0')])
    recorder = rclpy.create_node(f'ip_recorder_{TAG}', context=context)
    executor = make_executor(context)
    executor.add_node(bridge)
    executor.add_node(recorder)
    built = []
    imu_msg = bridge._imu_msg
    bridge._imu_msg = lambda s: built.append(s.stamp_ns) or imu_msg(s)
    try:
        bridge._publish_imu(sample(1))
        assert bridge.imu_dds_skipped == 1 and built == []          # kept, not built
        assert sub.take() == 1 and len(local) == 1                  # in process regardless
        assert built == [1_000_000_000]                             # built by the take
        msg = local[0]
        assert isinstance(msg, Imu) and msg.header.stamp.sec == 1 and msg.header.frame_id
        assert msg.angular_velocity.z == 0.3 and msg.linear_acceleration.z == 9.81
        got = []
        recorder.create_subscription(Imu, 'imu/data', lambda m: got.append(m.header.stamp.sec),
                                     SENSOR_QOS)
        assert spin_until(executor, lambda: bridge._imu_pub.get_subscription_count() == 1, 5.0)
        for k in range(2, 5):
            bridge._publish_imu(sample(k))
        assert spin_until(executor, lambda: len(got) == 3, 2.0)
        assert sub.take() == 3 and len(local) == 4
        assert got == [2, 3, 4] and bridge.imu_dds_skipped == 1
        assert [m.header.stamp.sec for m in local] == [1, 2, 3, 4]
    finally:
        executor.shutdown()
        recorder.destroy_node()
        bridge.destroy_node()


def test_a_lazy_message_is_built_once_for_every_subscriber():
    topic = IntraProcessTopic('imu/data')
    a, b, made = [], [], []
    sub_a, sub_b = topic.subscribe(a.append), topic.subscribe(b.append)
    topic.publish_lazy(lambda: made.append(1) or imu(5))
    assert made == []
    sub_a.take()
    sub_b.take()
    assert made == [1] and a[0] is b[0] and a[0].header.stamp.sec == 5


def _image_subscriptions(nodes, topic: str) -> int:
    return sum(s.topic_name == topic for node in nodes for s in node.subscriptions)


@pytest.mark.parametrize('intra_process', [True, False])
def test_composed_perception_nodes_take_each_camera_once(context, intra_process):
    """One image and one CameraInfo subscription per camera for its two nodes (composed); each
    node's own with ``intra_process=False``. An image published once reaches both nodes."""
    from ibvs_bringup import composed, graph
    from sensor_msgs.msg import CameraInfo, Image
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    # the perception nodes alone: with the supervisor's latched IDLE the wall flow would keep
    # the image unprocessed (mode gating), and this is about who receives it
    specs = [s for s in specs if s.package == 'ibvs_perception']
    nodes = composed.build_nodes(specs, context, intra_process=intra_process)
    sender = rclpy.create_node(f'camera_{TAG}', context=context)
    try:
        per_camera = 1 if intra_process else 2
        for cam in ('front', 'down'):
            for topic in (f'/{cam}_camera/image_raw', f'/{cam}_camera/camera_info'):
                assert _image_subscriptions(nodes, topic) == per_camera, topic
        by_name = {n.get_name(): n for n in nodes}
        front = (by_name['window_detector'], by_name['front_optical_flow'])
        executor = make_executor(context)
        for node in nodes + [sender]:
            executor.add_node(node)
        pub_info = sender.create_publisher(CameraInfo, 'front_camera/camera_info', SENSOR_QOS)
        pub_image = sender.create_publisher(Image, 'front_camera/image_raw', SENSOR_QOS)
        assert spin_until(executor, lambda: pub_image.get_subscription_count() == per_camera
                          and pub_info.get_subscription_count() == per_camera, 5.0)
        info = CameraInfo(width=8, height=6)
        image = Image(width=8, height=6, encoding='mono8', step=8, data=bytes(48))
        image.header.frame_id = 'front_camera_optical_frame'
        pub_info.publish(info)
        assert spin_until(executor, lambda: all(n.camera_info is not None for n in front), 5.0)
        pub_image.publish(image)
        assert spin_until(executor, lambda: all(n.gated.counts.computed == 1 for n in front),
                          5.0)
        spin_until(executor, lambda: False, 0.2)         # spin on: nothing comes twice
        assert [n.gated.counts.computed for n in front] == [1, 1]
        assert (front[0].camera_info is front[1].camera_info) == intra_process
        executor.shutdown()
    finally:
        sender.destroy_node()
        for node in nodes:
            node.destroy_node()


def test_a_shared_camera_hands_each_image_first_to_the_node_its_modes_wait_for(context):
    """Front: the window detector, then the wall flow (IDLE waits for the window only). Down:
    the floor flow, then the pad detector (CROSSING waits for the floor flow only; behind a
    whole-image pad search it missed the frame's deadline on a third of a core)."""
    from ibvs_bringup import composed, graph
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    specs = [s for s in specs if s.package == 'ibvs_perception']
    nodes = composed.build_nodes(specs, context)
    try:
        by_name = {n.get_name(): n for n in nodes}
        for first, second in (('window_detector', 'front_optical_flow'),
                              ('down_optical_flow', 'pad_detector')):
            shared = by_name[first].images
            assert by_name[second].images is shared
            assert shared.handlers == [by_name[first].gated.on_images,
                                       by_name[second].gated.on_images]
    finally:
        for node in nodes:
            node.destroy_node()


def test_nodes_remapped_apart_do_not_share_a_camera(context):
    from ibvs_bringup import composed, graph
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    i = next(k for k, s in enumerate(specs) if s.name == 'window_detector')
    s = specs[i]
    specs[i] = graph.NodeSpec(s.package, s.executable, s.name, s.parameters,
                              (('front_camera/image_raw', 'other_camera/image_raw'),))
    nodes = composed.build_nodes(specs, context)
    try:
        assert _image_subscriptions(nodes, '/front_camera/image_raw') == 1    # the flow's
        assert _image_subscriptions(nodes, '/other_camera/image_raw') == 1    # the detector's
        assert _image_subscriptions(nodes, '/front_camera/camera_info') == 2
    finally:
        for node in nodes:
            node.destroy_node()


def test_a_shared_camera_applies_its_time_offset_once_and_refuses_another(context):
    import dataclasses
    from ibvs_common.core.config import load_vehicle
    from ibvs_perception.camera_input import SharedCameraInputs
    from sensor_msgs.msg import Image
    camera = dataclasses.replace(load_vehicle().cameras['front'], time_offset_s=0.004)
    node = rclpy.create_node(f'shared_cam_{TAG}', context=context)
    try:
        shared, got = SharedCameraInputs(), []

        def stamps(images, taken_ns):
            got.extend(m.header.stamp.nanosec for m in images)

        first = shared.attach(node, camera, 'raw', stamps, 'a')
        second = shared.attach(node, camera, 'raw', stamps, 'b')
        assert first is second and len(shared.inputs) == 1
        msg = Image()
        msg.header.frame_id = camera.frame_id
        msg.header.stamp.nanosec = 1_000_000
        first._deliver([msg])
        assert got == [5_000_000, 5_000_000]             # 1 ms + 4 ms, not + 8 ms
        other = dataclasses.replace(camera, time_offset_s=0.0)
        with pytest.raises(ValueError, match='time_offset_s 0.0, but a in the same process'):
            shared.attach(node, other, 'raw', stamps, 'c')
        assert shared.attach(node, other, 'compressed', stamps, 'd') is not first
    finally:
        node.destroy_node()


def test_a_shared_camera_second_node_computes_the_frames_the_first_computed(context):
    """The two nodes of a shared camera judge an image's age as it was taken, not at their turn.

    On a slow computer the first node's processing outlasts a frame period. Judged at its own
    turn, the second node found every image a period older than the camera delivers, took it
    as superseded by the next one and skipped it: the wall flow computed frames whose window
    never came (a sixth of a core: "window stale" in WINDOW, docs/journal/sensors.md).
    """
    import time
    from ibvs_common.core.config import load_vehicle
    from ibvs_common.core.modes import InputKind
    from ibvs_common.node_common import ns_to_stamp
    from ibvs_perception.camera_input import SharedCameraInputs
    from ibvs_perception.config import ImageInputConfig
    from ibvs_perception.gated_images import GatedImages
    from sensor_msgs.msg import Image
    camera = load_vehicle().cameras['front']
    node = rclpy.create_node(f'shared_age_{TAG}', context=context)
    period_ns, delivery_ns = 20_000_000, 30_000_000
    try:
        computed = {'first': [], 'second': []}
        busy = []                        # the first node outlasts a frame period once set

        def first_node(msg, publish):
            computed['first'].append(msg.header.stamp.nanosec)
            if busy:
                time.sleep(2.5 * period_ns / 1e9)

        def second_node(msg, publish):
            computed['second'].append(msg.header.stamp.nanosec)

        config = ImageInputConfig(mode_gating=False)
        nodes = [GatedImages(node, kind, fn, name, config, 'front', period_ns)
                 for kind, fn, name in ((InputKind.FLOW_FRONT, first_node, 'first'),
                                        (InputKind.WINDOW, second_node, 'second'))]
        shared = SharedCameraInputs()
        camera_in = shared.attach(node, camera, 'raw', nodes[0].on_images, 'first')
        shared.attach(node, camera, 'raw', nodes[1].on_images, 'second')
        for k in range(30):
            if k == 15:                  # the delivery floor is learnt: the first node slows
                busy.append(True)
            msg = Image()                # delivered 30 ms after its stamp
            msg.header.frame_id = camera.frame_id
            ns_to_stamp(node.get_clock().now().nanoseconds - delivery_ns, msg.header.stamp)
            camera_in._deliver([msg])
        assert len(computed['first']) == 30
        assert computed['second'] == computed['first']
        assert [g.counts.superseded for g in nodes] == [0, 0]
    finally:
        node.destroy_node()


def test_the_control_thread_takes_the_control_nodes_and_nothing_else(context):
    from ibvs_bringup import composed, graph
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                   mavlink_url='udpin:127.0.0.1:0'))
    nodes = composed.build_nodes(specs, context)
    try:
        assert composed.executor_groups(nodes, False) == [nodes]
        images, control = composed.executor_groups(nodes, True)
        assert sorted(n.get_name() for n in control) == sorted(composed.GROUPS['control'])
        assert sorted(n.get_name() for n in images) == sorted(
            composed.GROUPS['front'] + composed.GROUPS['down'])
    finally:
        for node in nodes:
            node.destroy_node()
