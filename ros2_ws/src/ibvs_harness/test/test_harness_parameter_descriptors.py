"""Parameters are declared with descriptors, read-only, and validated at start.

Every flight-path node declares its parameters through ibvs_common.param_descriptors: a
description (unit, clock), a range for every integer and double (step 0) and read_only (no
node reads a parameter after start). A value out of range or of the wrong type stops the node
with an error naming the parameter; a runtime set_parameters is refused.
"""
import os
import socket
import subprocess
import sys
import time

import pytest
import rclpy
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu

from ibvs_harness import bag
from ibvs_harness.bag_player_node import BagPlayerNode, BagPlayerNodeConfig
from ibvs_harness.recorder_node import RecorderNode, RecorderNodeConfig
from ibvs_common.core import params
from ibvs_common.core.mavlink_connection import free_udp_port
from ibvs_control.force_controller_node import ForceControllerNode
from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode
from ibvs_control.mode_supervisor_node import ModeSupervisorNode
from ibvs_common.param_descriptors import declare, declare_all, descriptor
from ibvs_perception.optical_flow_node import OpticalFlowNode
from ibvs_perception.pad_detector_node import PadDetectorNode
from ibvs_perception.window_detector_node import WindowDetectorNode
from ibvs_sim.px4_sim_node import Px4SimNode
from ibvs_sim.sim_node import SimNode

TAG = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
ROS_OWN = {'use_sim_time', 'start_type_description_service'}   # declared by rclpy itself


def bridge_overrides():
    """The bridge sends to a free local port nobody answers (no socket bound to 14540)."""
    return [Parameter('url', value=f'udpout:127.0.0.1:{free_udp_port()}')]


NODES = {  # name -> (class, overrides factory)
    'window_detector': (WindowDetectorNode, list),
    'pad_detector': (PadDetectorNode, list),
    'front_optical_flow': (OpticalFlowNode, lambda: [Parameter('camera', value='front')]),
    'down_optical_flow': (OpticalFlowNode, lambda: [Parameter('camera', value='down')]),
    'mode_supervisor': (ModeSupervisorNode, list),
    'force_controller': (ForceControllerNode, list),
    'mavlink_bridge': (MavlinkBridgeNode, bridge_overrides),
    'sim': (SimNode, lambda: [Parameter('mavlink_url',
                                        value='udpin:127.0.0.1:0')]),
    'px4_sim': (Px4SimNode, lambda: [Parameter('state_url',
                                               value='udpin:127.0.0.1:0')]),
}


def make(name, context, extra=()):
    cls, overrides = NODES[name]
    return cls(f'{name}_pd_{TAG}', context=context,
               parameter_overrides=overrides() + list(extra))


def check_descriptors(node):
    """Return parameter -> what its descriptor lacks, for the node's own parameters."""
    names = own_parameters(node)
    assert len(names) >= 3
    bad = {}
    for pname, d in zip(names, node.describe_parameters(names)):
        why = []
        if not d.description.strip():
            why.append('no description')
        if not d.read_only:
            why.append('not read-only')
        if d.type == ParameterType.PARAMETER_INTEGER:
            if len(d.integer_range) != 1 or d.integer_range[0].step != 0:
                why.append('integer without a range (step 0)')
        elif d.type == ParameterType.PARAMETER_DOUBLE:
            if len(d.floating_point_range) != 1 or d.floating_point_range[0].step != 0.0:
                why.append('double without a range (step 0)')
        if why:
            bad[pname] = why
    return bad


def own_parameters(node):
    return sorted(set(node.list_parameters([], 0).names) - ROS_OWN)


@pytest.mark.parametrize('name', sorted(NODES))
def test_every_parameter_is_described_ranged_and_read_only(name, context):
    node = make(name, context)
    try:
        bad = check_descriptors(node)
        assert not bad, f'{name}: {bad}'
    finally:
        node.destroy_node()


def test_tool_node_parameters_are_described(context, tmp_path):
    """The recorder and the bag player: every parameter of their config, described, ranged."""
    node = RecorderNode(context=context,
                        parameter_overrides=[Parameter('bag_path', value=str(tmp_path / 'b'))])
    try:
        assert not check_descriptors(node)
        assert own_parameters(node) == sorted(params.parameters(RecorderNodeConfig))
    finally:
        node.destroy_node()
    with bag.BagWriter(tmp_path / 'played') as w:          # the player needs a bag to start
        w.add_topic('imu/data', 'sensor_msgs/msg/Imu')
        w.write('imu/data', 1_000, serialize_message(Imu()))
    node = BagPlayerNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(tmp_path / 'played')), Parameter('rate', value=0.0)])
    try:
        assert not check_descriptors(node)
        assert own_parameters(node) == sorted(params.parameters(BagPlayerNodeConfig))
        assert node.config.rate == 1.0                     # 0: real time
    finally:
        node.destroy_node()


@pytest.mark.parametrize('node_class', [RecorderNode, BagPlayerNode])
def test_tool_node_bag_path_is_required(node_class, context):
    with pytest.raises(ValueError, match='bag_path is required'):
        node_class(context=context)


@pytest.mark.parametrize('name, parameter, value', [
    ('window_detector', 'threshold_offset', 10.0),
    ('pad_detector', 'roi_margin_px', 5),
    ('force_controller', 'window.kp', 2.0),
    ('mavlink_bridge', 'hold_last_s', 1.0),
])
def test_a_runtime_set_is_refused(name, parameter, value, context):
    node = make(name, context)
    try:
        before = node.get_parameter(parameter).value
        result, = node.set_parameters([Parameter(parameter, value=value)])
        assert not result.successful
        assert 'read-only' in result.reason
        assert node.get_parameter(parameter).value == before
    finally:
        node.destroy_node()


@pytest.mark.parametrize('name, parameter, value', [
    ('window_detector', 'detection_scale', 1.5),          # range (0.01, 1]
    ('window_detector', 'threshold_block_px', 1),         # range >= 3
    ('window_detector', 'threshold_block_px', 30),        # odd: __post_init__-type check
    ('window_detector', 'min_area_fraction', 0.99),       # > max_area_fraction
    ('pad_detector', 'adaptive_thresh_win_size_max', 11),  # < min (21)
    ('pad_detector', 'min_corner_distance_rate', -0.1),
    ('front_optical_flow', 'lk_window_px', 2),
    ('down_optical_flow', 'quality_level', 0.0),          # cv2 asserts > 0
    ('mode_supervisor', 'imu_timeout_s', -1.0),
    ('force_controller', 'landing.lateral_scale_min', 1.5),
    ('force_controller', 'window.kp', 1),                 # an integer for a double
    ('mavlink_bridge', 'max_tilt_rad', 4.0),
    ('mavlink_bridge', 'source_system', 256),
])
def test_a_bad_value_at_start_names_the_parameter(name, parameter, value, context):
    with pytest.raises(ValueError, match=parameter.split('.')[-1]):
        make(name, context, [Parameter(parameter, value=value)])


@pytest.mark.parametrize('module, node, parameter', [
    ('ibvs_perception.window_detector_node', 'wd', 'threshold_block_px:=30'),
    ('ibvs_perception.window_detector_node', 'wd', 'detection_scale:=2.0'),
    ('ibvs_control.mode_supervisor_node', 'ms', 'frame_deadline_s:=-0.1'),
])
def test_main_exits_1_with_a_fatal_log_naming_the_parameter(module, node, parameter):
    proc = subprocess.run(
        [sys.executable, '-c', f'from {module} import main; main()',
         '--ros-args', '-r', f'__node:={node}_{TAG}', '-p', parameter],
        env=dict(os.environ), capture_output=True, text=True, timeout=60)
    out = proc.stderr + proc.stdout
    assert proc.returncode == 1, out
    assert parameter.split(':=')[0] in out
    assert 'Traceback' not in out


@pytest.mark.parametrize('module, node, url_parameter', [
    ('ibvs_sim.sim_node', 'sim', 'mavlink_url'),
    ('ibvs_sim.px4_sim_node', 'px4_sim', 'state_url'),
])
def test_main_exits_1_with_a_fatal_log_when_its_udp_port_is_taken(module, node, url_parameter):
    """A sim whose MAVLink/state port another socket holds says so and exits: no traceback."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(('127.0.0.1', 0))
        port = holder.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, '-c', f'from {module} import main; main()',
             '--ros-args', '-r', f'__node:={node}_{TAG}',
             '-p', f'{url_parameter}:=udpin:127.0.0.1:{port}'],
            env=dict(os.environ), capture_output=True, text=True, timeout=60)
    out = proc.stderr + proc.stdout
    assert proc.returncode == 1, out
    assert 'cannot start' in out and f'UDP port {port} is already bound' in out, out
    assert 'Traceback' not in out


def test_descriptor_helper():
    d = descriptor('x_s', 0.5, ('s (ROS clock), x', 0.0, None))
    assert d.read_only and d.description == 's (ROS clock), x'
    r = d.floating_point_range[0]
    assert (r.from_value, r.to_value, r.step) == (0.0, float('inf'), 0.0)
    d = descriptor('n', 3, ('frames', 1, 10), read_only=False)
    assert not d.read_only
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (1, 10)
    d = descriptor('s', 'a', ('a string',))
    assert not d.integer_range and not d.floating_point_range
    with pytest.raises(TypeError):
        descriptor('x', 1.0, ('no range',))           # a double needs its range
    with pytest.raises(TypeError):
        descriptor('b', True, ('flag', 0, 1))         # a bool has none
    with pytest.raises(TypeError):
        descriptor('e', 'a', ('',))                   # empty description
    with pytest.raises(ValueError, match='outside'):
        descriptor('x', 2.0, ('x', 0.0, 1.0))         # default out of its own range


def test_declare_turns_rclpy_errors_into_value_errors(context):
    node = rclpy.create_node(f'pd_helper_{TAG}', context=context, parameter_overrides=[
        Parameter('x', value=5.0), Parameter('n', value='text')])
    try:
        with pytest.raises(ValueError, match='parameter x: .*out of range'):
            declare(node, 'x', 0.5, ('x', 0.0, 1.0))
        with pytest.raises(ValueError, match='parameter n: .*type'):
            declare(node, 'n', 1, ('n', 0, 10))
        assert declare(node, 'y', 0.25, ('y', 0.0, 1.0)) == 0.25
    finally:
        node.destroy_node()


def test_declare_all_wants_one_spec_per_parameter(context):
    node = rclpy.create_node(f'pd_all_{TAG}', context=context)
    try:
        with pytest.raises(KeyError, match=r"without a spec .*\['b'\]"):
            declare_all(node, {'a': 1.0, 'b': 2.0}, {'a': ('a', 0.0, None)})
        with pytest.raises(KeyError, match=r"specs of no parameter: \['c'\]"):
            declare_all(node, {'a': 1.0}, {'a': ('a', 0.0, None), 'c': ('c',)})
        assert declare_all(node, {'a': 1.0}, {'a': ('a', 0.0, None)}, prefix='p.') == {'a': 1.0}
        assert node.get_parameter('p.a').value == 1.0
    finally:
        node.destroy_node()
