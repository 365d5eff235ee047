"""Bags: rclpy CDR bytes -> MCAP rosbag2 (rosbags) -> back; recorder and player nodes."""
import time

from ibvs_harness import bag
import numpy as np
import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt8
import yaml


def _image(stamp_s: int, value: int) -> Image:
    msg = Image(height=2, width=3, encoding='mono8', step=3, data=bytes([value] * 6))
    msg.header.stamp.sec = stamp_s
    msg.header.frame_id = 'front_camera_optical_frame'
    return msg


def test_round_trip_of_rclpy_bytes_through_an_mcap_bag(tmp_path):
    path = tmp_path / 'bag'
    images = [_image(10 + i, i) for i in range(3)]
    with bag.BagWriter(path) as w:
        w.add_topic('front_camera/image_raw', 'sensor_msgs/msg/Image',
                    [bag.qos_profile(False, False)])
        w.add_topic('ibvs/mode', 'std_msgs/msg/UInt8', [bag.qos_profile(True, True, 1)])
        for i, m in enumerate(images):
            w.write('front_camera/image_raw', 1_000 + i, serialize_message(m))
        w.write('ibvs/mode', 1_500, serialize_message(UInt8(data=3)))
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == bag.BAG_VERSION and meta['storage_identifier'] == 'mcap'
    assert meta['message_count'] == 4
    assert [f['path'] for f in meta['files']] == ['bag.mcap'] and (path / 'bag.mcap').exists()
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
           for t in meta['topics_with_message_count']}
    assert 'durability: 1' in qos['/ibvs/mode']       # transient local, as rosbag2 spells it
    msgs = list(bag.read_messages(path))
    assert [(m[0], m[2]) for m in msgs] == [('/front_camera/image_raw', 1000),
                                            ('/front_camera/image_raw', 1001),
                                            ('/front_camera/image_raw', 1002),
                                            ('/ibvs/mode', 1500)]
    for (topic, msgtype, _, data), original in zip(msgs, images):
        back = deserialize_message(data, Image)           # rclpy reads what rosbags stored
        assert back == original
        rb = bag.deserialize(data, msgtype)                # and so does rosbags
        assert rb.header.stamp.sec == original.header.stamp.sec
        assert bytes(rb.data) == bytes(original.data) and rb.encoding == 'mono8'
    assert bag.deserialize(msgs[-1][3], 'std_msgs/msg/UInt8').data == 3
    assert bag.topic_counts(path) == {'/front_camera/image_raw': 3, '/ibvs/mode': 1}
    with pytest.raises(Exception):
        bag.BagWriter(path)                                # never overwrites


def _small_bag(path):
    with bag.BagWriter(path) as w:
        w.add_topic('ibvs/mode', 'std_msgs/msg/UInt8', [bag.qos_profile(True, True, 1)])
        w.write('ibvs/mode', 1_500, serialize_message(UInt8(data=3)))


@pytest.mark.parametrize('damage, message', [
    ('missing', 'does not exist'),
    ('file', 'is a file'),
    ('no metadata', 'has no metadata.yaml'),
    ('bad metadata', 'cannot be read')])
def test_a_folder_that_is_not_a_bag_gets_the_reason_not_a_traceback(tmp_path, damage, message):
    path = tmp_path / 'bag'
    _small_bag(path)
    if damage == 'missing':
        path = tmp_path / 'nothing'
    elif damage == 'file':
        path = path / 'bag.mcap'
    elif damage == 'no metadata':
        (path / 'metadata.yaml').unlink()
    else:
        (path / 'metadata.yaml').write_text('rosbag2_bagfile_information: {version: [}\n')
    for read in (bag.topic_counts, bag.topic_types, lambda p: list(bag.read_messages(p))):
        with pytest.raises(bag.BagError, match=message) as err:
            read(path)
        assert str(path) in str(err.value)


def test_the_player_node_exits_1_with_the_reason_for_a_bag_without_metadata(tmp_path):
    import subprocess
    import sys
    path = tmp_path / 'bag'
    _small_bag(path)
    (path / 'metadata.yaml').unlink()
    out = subprocess.run([sys.executable, '-m', 'ibvs_harness.bag_player_node', '--ros-args',
                          '-p', f'bag_path:={path}'], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 1, out.stderr[-2000:]
    assert 'has no metadata.yaml' in out.stderr and 'Traceback' not in out.stderr, out.stderr


def _spin_until(executor, pred, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        executor.spin_once(timeout_sec=0.05)
    return pred()


def _publish_images_until(executor, rec, img_pub, n, timeout_s=10.0):
    """Publish images (stamps 100, 101, ..., values 0, 1, ...) until the recorder got n."""
    sent = 0
    deadline = time.monotonic() + timeout_s
    while rec.counts['front_camera/image_raw'] < n and time.monotonic() < deadline:
        img_pub.publish(_image(100 + sent, sent))
        sent += 1
        executor.spin_once(timeout_sec=0.02)


@pytest.fixture
def ros():
    rclpy.init()
    try:
        yield
    finally:
        rclpy.try_shutdown()


def test_recorder_then_player_reproduce_topics_and_stamps(tmp_path, ros):
    from ibvs_harness.bag_player_node import BagPlayerNode
    from ibvs_harness.recorder_node import RecorderNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    path = tmp_path / 'run_bag'
    src = rclpy.create_node('source')
    img_pub = src.create_publisher(Image, 'front_camera/image_raw',
                                   rclpy.qos.qos_profile_sensor_data)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    mode_pub = src.create_publisher(UInt8, 'ibvs/mode', latched)
    ev_pub = src.create_publisher(String, 'sim/events', latched)
    mode_pub.publish(UInt8(data=1))                        # before the recorder exists
    ex = SingleThreadedExecutor()
    ex.add_node(src)
    rec = None
    try:
        rec = RecorderNode(parameter_overrides=[
            Parameter('bag_path', value=str(path)), Parameter('image_every', value=2),
            Parameter('topics', value=['front_camera/image_raw', 'ibvs/mode', 'sim/events'])])
        ex.add_node(rec)
        assert _spin_until(ex, lambda: len(rec.subs) == 3, 10.0), rec.subs
        assert _spin_until(ex, lambda: rec.counts.get('ibvs/mode') == 1, 5.0)
        time.sleep(0.3)
        _publish_images_until(ex, rec, img_pub, 6)
        ev_pub.publish(String(data='{"type": "touchdown"}'))
        assert _spin_until(ex, lambda: rec.counts['sim/events'] == 1, 5.0)
    finally:
        if rec is not None:
            ex.remove_node(rec)
            rec.destroy_node()
    counts = bag.topic_counts(path)
    n_img = rec.counts['front_camera/image_raw']
    assert n_img >= 6 and counts['/front_camera/image_raw'] == (n_img + 1) // 2
    assert counts['/ibvs/mode'] == 1 and counts['/sim/events'] == 1
    recorded = [bag.deserialize(d, typ).header.stamp.sec
                for _, typ, _, d in bag.read_messages(path, ['front_camera/image_raw'])]
    assert recorded == sorted(recorded) and recorded[1] - recorded[0] == 2

    # replay: same bytes, original stamps, /clock from bag time
    got, clocks = [], []
    sink = rclpy.create_node('sink')
    sink.create_subscription(Image, 'front_camera/image_raw',
                             lambda m: got.append(m.header.stamp.sec),
                             rclpy.qos.qos_profile_sensor_data)
    sink.create_subscription(Clock, '/clock', lambda m: clocks.append(m.clock), 10)
    player = BagPlayerNode(parameter_overrides=[
        Parameter('bag_path', value=str(path)), Parameter('rate', value=1.0),
        Parameter('topics', value=['front_camera/image_raw']),
        Parameter('start_delay', value=1.0)])
    try:
        ex.add_node(sink)
        ex.add_node(player)
        done = _spin_until(ex, lambda: len(got) == len(clocks) == len(recorded), 15.0)
        assert done, (got, recorded, clocks)
        assert got == recorded
        bag_times = [t for _, _, t, _ in bag.read_messages(path, ['front_camera/image_raw'])]
        assert [c.sec * 10**9 + c.nanosec for c in clocks] == bag_times
    finally:
        for n in (player, sink, src):
            n.destroy_node()
    # images held image_delay_s after their place in the bag (the clock keeps its place)
    arrivals = {'image': [], 'clock': []}
    sink = rclpy.create_node('sink_delay')
    sink.create_subscription(Image, 'front_camera/image_raw',
                             lambda m: arrivals['image'].append(time.monotonic()),
                             rclpy.qos.qos_profile_sensor_data)
    sink.create_subscription(Clock, '/clock',
                             lambda m: arrivals['clock'].append(time.monotonic()), 10)
    player = BagPlayerNode(parameter_overrides=[
        Parameter('bag_path', value=str(path)), Parameter('rate', value=1.0),
        Parameter('topics', value=['front_camera/image_raw']),
        Parameter('start_delay', value=1.0), Parameter('image_delay_s', value=0.3)])
    try:
        ex.add_node(sink)
        ex.add_node(player)
        assert _spin_until(ex, lambda: len(arrivals['image']) == len(recorded), 15.0)
        delays = np.subtract(arrivals['image'], arrivals['clock'])
        assert np.all(delays >= 0.29) and np.all(delays < 0.6), delays
    finally:
        for n in (player, sink):
            n.destroy_node()


def test_recorder_stops_images_at_the_cap_and_records_the_rest(tmp_path, ros):
    from ibvs_harness.recorder_node import RecorderNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    path = tmp_path / 'capped'
    src = rclpy.create_node('capped_source')
    img_pub = src.create_publisher(Image, 'front_camera/image_raw',
                                   rclpy.qos.qos_profile_sensor_data)
    ev_pub = src.create_publisher(String, 'sim/events', 10)
    size = len(serialize_message(_image(100, 0)))
    ex = SingleThreadedExecutor()
    ex.add_node(src)
    rec = None
    try:
        rec = RecorderNode(parameter_overrides=[
            Parameter('bag_path', value=str(path)),
            Parameter('max_image_mb', value=2.5 * size / 1e6),      # room for 2 images
            Parameter('topics', value=['front_camera/image_raw', 'sim/events'])])
        ex.add_node(rec)
        assert _spin_until(ex, lambda: len(rec.subs) == 2, 10.0), rec.subs
        time.sleep(0.3)
        _publish_images_until(ex, rec, img_pub, 5)
        ev_pub.publish(String(data='{"type": "touchdown"}'))
        assert _spin_until(ex, lambda: rec.counts['sim/events'] == 1, 5.0)
    finally:
        if rec is not None:
            ex.remove_node(rec)
            rec.destroy_node()
        src.destroy_node()
    counts = bag.topic_counts(path)
    assert counts['/front_camera/image_raw'] == 2 and rec.image_bytes == 2 * size
    assert rec.images_over_cap == rec.counts['front_camera/image_raw'] - 2 >= 3
    assert counts['/sim/events'] == 1


def test_recorder_ends_the_recording_at_the_free_disk_floor_and_on_a_failed_write(
        tmp_path, ros, monkeypatch):
    """Below min_free_disk_mb the bag is closed and nothing more is written; a write that
    fails (a full disk) ends the recording the same way; neither raises."""
    from collections import namedtuple
    from ibvs_harness import recorder_node
    from ibvs_harness.recorder_node import RecorderNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    usage = namedtuple('usage', 'total used free')
    free = {'bytes': 10**12}
    monkeypatch.setattr(recorder_node.shutil, 'disk_usage',
                        lambda p: usage(2 * 10**12, 10**12, free['bytes']))
    src = rclpy.create_node('disk_source')
    ev_pub = src.create_publisher(String, 'sim/events', 10)
    ex = SingleThreadedExecutor()
    ex.add_node(src)
    rec = None
    try:
        rec = RecorderNode(parameter_overrides=[
            Parameter('bag_path', value=str(tmp_path / 'floor')),
            Parameter('min_free_disk_mb', value=100.0), Parameter('topics', value=['sim/events'])])
        ex.add_node(rec)
        assert _spin_until(ex, lambda: len(rec.subs) == 1, 10.0)
        time.sleep(0.3)
        ev_pub.publish(String(data='{"type": "a"}'))
        assert _spin_until(ex, lambda: rec.counts['sim/events'] == 1, 5.0)
        free['bytes'] = 99 * 10**6                            # the disk fills
        rec._check_disk()
        assert rec.stopped.startswith('99 MB free on the disk, below min_free_disk_mb (100)')
        ev_pub.publish(String(data='{"type": "b"}'))
        assert _spin_until(ex, lambda: rec.counts['sim/events'] == 2, 5.0)
        assert rec.not_written == 1
    finally:
        if rec is not None:
            ex.remove_node(rec)
            rec.destroy_node()
    assert bag.topic_counts(tmp_path / 'floor')['/sim/events'] == 1    # closed, readable

    def full_disk(*_):
        raise OSError(28, 'No space left on device')

    free['bytes'] = 10**12                                    # room again: a new recording
    rec = RecorderNode(parameter_overrides=[
        Parameter('bag_path', value=str(tmp_path / 'full')), Parameter('topics',
                                                                       value=['sim/events'])])
    try:
        ex.add_node(rec)
        assert _spin_until(ex, lambda: len(rec.subs) == 1, 10.0)
        time.sleep(0.3)
        monkeypatch.setattr(rec.writer, 'write', full_disk)
        ev_pub.publish(String(data='{"type": "c"}'))
        assert _spin_until(ex, lambda: bool(rec.stopped), 5.0)
        assert 'No space left on device' in rec.stopped
    finally:
        ex.remove_node(rec)
        rec.destroy_node()
        src.destroy_node()


def test_recorder_splits_the_recording_into_closed_parts(tmp_path, ros):
    """split_s: bag_path becomes a folder of bags, each closed and readable, with the same
    topics; together they hold every message once."""
    from ibvs_harness.recorder_node import RecorderNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    src = rclpy.create_node('split_source')
    ev_pub = src.create_publisher(String, 'sim/events', 10)
    ex = SingleThreadedExecutor()
    ex.add_node(src)
    rec = RecorderNode(parameter_overrides=[
        Parameter('bag_path', value=str(tmp_path / 'split')), Parameter('split_s', value=0.3),
        Parameter('topics', value=['sim/events'])])
    try:
        ex.add_node(rec)
        assert _spin_until(ex, lambda: len(rec.subs) == 1, 10.0)
        time.sleep(0.3)
        for k in range(12):                                  # ~1.2 s: 4 or 5 parts
            ev_pub.publish(String(data=f'{{"type": "e{k}"}}'))
            _spin_until(ex, lambda: rec.counts['sim/events'] == k + 1, 5.0)
            _spin_until(ex, lambda: False, 0.1)
    finally:
        ex.remove_node(rec)
        rec.destroy_node()
        src.destroy_node()
    parts = sorted(p for p in (tmp_path / 'split').iterdir())
    assert len(parts) >= 3 and parts[0].name == 'part_000'
    counts = [bag.topic_counts(p).get('/sim/events', 0) for p in parts]
    assert sum(counts) == 12 and sum(1 for c in counts if c) >= 3
