"""One source of defaults: every node's code defaults equal its section of params.yaml.

Each node is built in-process with no parameter file; every key of its params.yaml section
must then read the same value. A node started without ``params_file`` (or by hand) therefore
flies exactly what the shipped configuration documents.
"""
import os
from pathlib import Path
import time

import pytest
from rclpy.parameter import Parameter
import yaml

from ibvs_perception.optical_flow_node import OpticalFlowNode
from ibvs_perception.pad_detector_node import PadDetectorNode
from ibvs_perception.window_detector_node import WindowDetectorNode
from ibvs_control.force_controller_node import ForceControllerNode
from ibvs_control.mode_supervisor_node import ModeSupervisorNode
from ibvs_sim.px4_sim_node import Px4SimNode
from ibvs_sim.sim_node import SimNode

PARAMS = Path(__file__).resolve().parents[1] / 'config' / 'params.yaml'
SECTIONS = yaml.safe_load(PARAMS.read_text())
TAG = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
# keys that differ per instance by design (set in params.yaml for each instance)
PER_INSTANCE = {'front_optical_flow': {'camera'}, 'down_optical_flow': {'camera'},
                'px4_sim': {'state_url'}}   # a free port here (the default's may be taken)
NODES = [('window_detector', WindowDetectorNode), ('pad_detector', PadDetectorNode),
         ('front_optical_flow', OpticalFlowNode), ('down_optical_flow', OpticalFlowNode),
         ('mode_supervisor', ModeSupervisorNode), ('force_controller', ForceControllerNode),
         ('sim', SimNode), ('px4_sim', Px4SimNode)]


@pytest.mark.parametrize('section, cls', NODES, ids=[n for n, _ in NODES])
def test_code_defaults_equal_params_yaml(section, cls, context):
    extra = ([Parameter('state_url', value='udpin:127.0.0.1:0')]
             if cls is Px4SimNode else [])
    node = cls(f'{section}_{TAG}', context=context, parameter_overrides=extra)
    try:
        expected = SECTIONS[section]['ros__parameters']
        differ = {}
        for key, value in expected.items():
            if key in PER_INSTANCE.get(section, ()):
                continue
            assert node.has_parameter(key), f'{section}: {key} in params.yaml is not declared'
            actual = node.get_parameter(key).value
            if isinstance(value, list):
                actual = list(actual)
            if actual != value:
                differ[key] = (actual, value)
        assert not differ, f'{section}: code default != params.yaml: {differ}'
    finally:
        node.destroy_node()
