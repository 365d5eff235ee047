"""The cameras' mounts on /tf_static: the mode supervisor with real rclpy.

tf2_msgs has no PyPI wheel: in the venv it is absent, and the test that receives /tf_static
runs only on a Jazzy install (ros-jazzy-tf2-msgs). The others fake or hide the module.
"""
import os
from pathlib import Path
import sys
import time
import types

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter

from ibvs_common.core.camera_tf import camera_transforms
from ibvs_common.core.config import load_vehicle
from ibvs_control.camera_tf import (
    camera_transform_msgs, TF2_MSGS_MISSING, TF_STATIC_QOS, TF_STATIC_TOPIC)
from ibvs_control.mode_supervisor_node import ModeSupervisorNode

VEHICLE = load_vehicle()
TAG = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
SRC = Path(__file__).resolve().parents[2]


def supervisor(ctx, suffix, **params):
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'suptf{suffix}_{TAG}', context=context,
                             parameter_overrides=[Parameter(k, value=v)
                                                  for k, v in params.items()])
    nodes.append(sup)
    executor.add_node(sup)
    return sup


def hide_tf2_msgs(monkeypatch):
    """Make ``import tf2_msgs.msg`` fail, as on a machine without the package."""
    monkeypatch.setitem(sys.modules, 'tf2_msgs', None)
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)


def tf_static_publishers(node):
    return node.count_publishers(TF_STATIC_TOPIC)


def test_the_transforms_are_base_link_to_each_cameras_optical_frame(ctx, monkeypatch):
    hide_tf2_msgs(monkeypatch)
    sup = supervisor(ctx, 'msgs')
    msgs = camera_transform_msgs(sup, VEHICLE.cameras.values())
    assert [m.header.frame_id for m in msgs] == ['base_link'] * len(VEHICLE.cameras)
    assert [m.child_frame_id for m in msgs] == [c.frame_id for c in VEHICLE.cameras.values()]
    assert {m.child_frame_id for m in msgs} == {'down_camera_optical_frame',
                                                'front_camera_optical_frame'}
    for m, tf in zip(msgs, camera_transforms(VEHICLE.cameras.values())):
        t, r = m.transform.translation, m.transform.rotation
        assert np.allclose([t.x, t.y, t.z], tf.translation)
        assert np.allclose([r.x, r.y, r.z, r.w], tf.q_xyzw)
        assert np.isclose(r.x ** 2 + r.y ** 2 + r.z ** 2 + r.w ** 2, 1.0)
    front = msgs[[m.child_frame_id for m in msgs].index('front_camera_optical_frame')]
    r = front.transform.rotation
    assert np.allclose([r.x, r.y, r.z, r.w], [-0.5, 0.5, -0.5, 0.5])   # REP-103's optical


def test_the_node_publishes_one_message_with_every_camera_latched(ctx, monkeypatch):
    """tf2_msgs faked: the node's one publication, its topic and QoS."""
    published = []

    class FakeTFMessage:
        def __init__(self, transforms=()):
            self.transforms = list(transforms)

    class FakePublisher:
        def publish(self, msg):
            published.append(msg)

    real_create = ModeSupervisorNode.create_publisher
    wiring = []

    def create_publisher(node, msg_type, topic, qos, **kwargs):
        if topic == TF_STATIC_TOPIC:
            wiring.append((msg_type, qos))
            return FakePublisher()
        return real_create(node, msg_type, topic, qos, **kwargs)

    monkeypatch.setitem(sys.modules, 'tf2_msgs', types.ModuleType('tf2_msgs'))
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg',
                        types.SimpleNamespace(TFMessage=FakeTFMessage))
    monkeypatch.setattr(ModeSupervisorNode, 'create_publisher', create_publisher)
    supervisor(ctx, 'fake')
    assert wiring == [(FakeTFMessage, TF_STATIC_QOS)]
    assert (TF_STATIC_QOS.depth, TF_STATIC_QOS.reliability.name,
            TF_STATIC_QOS.durability.name, TF_STATIC_QOS.history.name) == (
                1, 'RELIABLE', 'TRANSIENT_LOCAL', 'KEEP_LAST')
    assert len(published) == 1
    assert sorted(m.child_frame_id for m in published[0].transforms) == [
        'down_camera_optical_frame', 'front_camera_optical_frame']
    assert {m.header.frame_id for m in published[0].transforms} == {'base_link'}


def test_without_tf2_msgs_the_node_starts_and_says_so_once(ctx, monkeypatch, capfd):
    hide_tf2_msgs(monkeypatch)
    sup = supervisor(ctx, 'absent')
    _, executor, _ = ctx
    executor.spin_once(timeout_sec=0.1)
    err = capfd.readouterr().err
    assert err.count(TF2_MSGS_MISSING) == 1, err
    assert 'ros-jazzy-tf2-msgs' in TF2_MSGS_MISSING
    assert tf_static_publishers(sup) == 0
    assert sup.count_publishers('ibvs/mode') == 1            # the node runs on


def test_publish_camera_tf_false_publishes_and_logs_nothing(ctx, monkeypatch, capfd):
    hide_tf2_msgs(monkeypatch)
    sup = supervisor(ctx, 'off', publish_camera_tf=False)
    assert TF2_MSGS_MISSING not in capfd.readouterr().err
    assert tf_static_publishers(sup) == 0


def test_a_late_subscriber_receives_the_cameras_on_tf_static(ctx):
    tf2_msgs_msg = pytest.importorskip(
        'tf2_msgs.msg', reason='tf2_msgs is not installed (no PyPI wheel; on a Jazzy install: '
        'ros-jazzy-tf2-msgs)')
    context, executor, nodes = ctx
    supervisor(ctx, 'real')
    listener = rclpy.create_node(f'tflisten_{TAG}', context=context)
    nodes.append(listener)
    executor.add_node(listener)
    got = []
    listener.create_subscription(tf2_msgs_msg.TFMessage, TF_STATIC_TOPIC, got.append,
                                 TF_STATIC_QOS)
    deadline = time.monotonic() + 5.0
    while not got and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    assert len(got) == 1
    assert sorted(m.child_frame_id for m in got[0].transforms) == [
        'down_camera_optical_frame', 'front_camera_optical_frame']
    assert {m.header.frame_id for m in got[0].transforms} == {'base_link'}


def test_only_the_supervisor_publishes_tf_static():
    # the sim (and every other node) must not publish the cameras a second time
    users = sorted(str(p.relative_to(SRC)) for p in SRC.glob('*/*/**/*.py')
                   if '/test/' not in str(p) and 'TFMessage' in p.read_text(encoding='utf-8'))
    assert users == ['ibvs_control/ibvs_control/camera_tf.py'], users
