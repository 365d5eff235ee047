"""params.yaml holds what a deployment sets, and every node reads it as meant (issue 50).

One source per parameter: each node's config dataclass holds the default, description, range
and unit (docs/parameters.md is generated from them); params.yaml only sets what a deployment
changes, per node, plus one ``/**`` block for what the nodes share. Checked here: every name
of the file is a parameter of its node (of at least one node for ``/**``) with a value of its
type and range, set in one place; the sections are nodes of graph.py; the per-run wiring is
not in it; and a node started with the file (as the launcher starts it) reads the file's
values, the code defaults for the rest, and the launcher's and a user's ``-p`` over both.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from ibvs_bringup import composed, graph
from ibvs_common.core import params
from ibvs_common.core.mavlink_connection import free_udp_port

PARAMS = Path(__file__).resolve().parents[1] / 'config' / 'params.yaml'
GRAPH_NODES = set(graph.SIM_NODE_NAMES) | set(graph.PX4_SIH_NODE_NAMES)
# the per-run wiring that graph.py and the test harness set: never in params.yaml
WIRING = {graph.SIM_MIN_IMAGE_SUBSCRIBERS, graph.BRIDGE_MIN_IMU_SUBSCRIBERS, graph.MAVLINK_URL,
          graph.BRIDGE_URL, graph.BRIDGE_ARM_ON_START, graph.SUPERVISOR_AUTO_START,
          graph.PX4_SIM_STATE_URL, graph.SIM_INITIAL_OVERRIDE, graph.SIM_INITIAL_POSITION,
          graph.SIM_INITIAL_YAW, graph.SIM_WIND, graph.SIM_REAL_TIME_FACTOR, 'use_sim_time'}


def load(path: Path = PARAMS) -> dict:
    return yaml.safe_load(path.read_text(encoding='utf-8'))


def node_sections(data: dict) -> dict:
    return {k: params.file_section(data, k) for k in data if k not in params.WILDCARDS}


def test_the_sections_are_nodes_of_the_graph_and_the_shared_block_comes_last():
    data = load()
    assert set(node_sections(data)) <= GRAPH_NODES, set(node_sections(data)) - GRAPH_NODES
    assert all(set(entry) == {params.SECTION_KEY} for entry in data.values())
    # rcl applies a file's entries in order and files a command line's -p under /**: last,
    # so the launcher's and a user's -p win over the node sections
    assert list(data)[-1] == params.WILDCARD


@pytest.mark.parametrize('node', sorted(node_sections(load())))
def test_every_name_of_a_section_is_a_parameter_of_its_node_of_its_type_and_range(node):
    params.check(graph.node_configs()[node], params.file_section(load(), node))


def test_every_name_of_the_shared_block_is_a_parameter_of_the_nodes_that_read_it():
    data = load()
    shared = params.file_section(data, params.WILDCARD)
    assert shared
    configs = graph.node_configs()
    for name, value in shared.items():
        readers = {node for node, cls in configs.items() if name in params.parameters(cls)}
        assert readers, f'/** {name}: a parameter of no node'
        for node in readers:
            assert params.value_error(name, *params.parameters(configs[node])[name],
                                      value) is None, (node, name, value)
    # a name is set in one place: /** or a node's section
    for node, section in node_sections(data).items():
        assert not set(section) & set(shared), (node, set(section) & set(shared))


def test_the_per_run_wiring_and_the_test_switches_are_not_in_the_file():
    data = load()
    names = {k for entry in data for k in params.file_section(data, entry)}
    assert not names & WIRING, names & WIRING
    assert not {n for n in names if n.startswith('fault_')}
    # what graph.py sets per run on a node that the file also sets: the same value
    opts = graph.GraphOptions(params_file=str(PARAMS), initial_position=(-2.2, 0.2, -1.5),
                              initial_yaw=0.1, wind=(0.1, 0.0, 0.0), crossing_law='seed',
                              auto_start_at_s=1.0, real_time_factor=0.5)
    specs = graph.sim_graph(opts) + graph.onboard_graph(graph.GraphOptions(
        params_file=str(PARAMS), use_sim_time=False)) + graph.px4_sih_graph(
        graph.GraphOptions(params_file=str(PARAMS), use_sim_time=False), 0)
    for spec in specs:
        given = params.file_values(data, spec.name)
        both = set(spec.overrides()) & set(given) - {graph.SIM_PACING}
        assert all(spec.overrides()[k] == given[k] for k in both), (spec.name, both)


def node_classes() -> dict:
    """Node name -> node class of every node of the graphs."""
    from ibvs_sim.px4_sim_node import Px4SimNode
    from ibvs_sim.sim_node import SimNode
    classes = {'sim': SimNode, graph.PX4_SIM_NAME: Px4SimNode}
    for spec in graph.onboard_graph(graph.GraphOptions(params_file=str(PARAMS))):
        classes[spec.name] = composed.node_class(spec.package, spec.executable)
    return classes


def free_ports() -> dict:
    """The wiring a node needs to start here: its UDP ports free (no autopilot answers)."""
    return {'sim': {graph.MAVLINK_URL: 'udpin:127.0.0.1:0'},
            graph.PX4_SIM_NAME: {graph.PX4_SIM_STATE_URL: 'udpin:127.0.0.1:0'},
            'mavlink_bridge': {graph.BRIDGE_URL: f'udpout:127.0.0.1:{free_udp_port()}'}}


@pytest.mark.parametrize('node', sorted(GRAPH_NODES))
def test_a_node_started_with_the_file_reads_its_values_and_the_code_defaults(node, context):
    cls = graph.node_configs()[node]
    expected = params.node_values(cls, load(), node)      # code defaults, /**, its section
    wiring = free_ports().get(node, {})
    spec = graph.NodeSpec('pkg', 'exe', node, (str(PARAMS), wiring))
    built = node_classes()[node](node_name=node, context=context, cli_args=spec.ros_args())
    try:
        read = {k: built.get_parameter(k).value for k in expected}
        read = {k: list(v) if isinstance(expected[k], list) else v for k, v in read.items()}
        assert {k: v for k, v in read.items() if k not in wiring} == \
            {k: v for k, v in expected.items() if k not in wiring}
        for key, value in params.file_values(load(), node).items():
            if key in expected:
                assert built.get_parameter(key).value == value, key
    finally:
        built.destroy_node()


def test_the_launchers_overrides_win_over_the_files_section(context):
    """The sim's pacing: lockstep in params.yaml, realtime when the run asks for it."""
    from ibvs_sim.sim_node import SimNode
    assert params.file_section(load(), 'sim')[graph.SIM_PACING] == 'lockstep'
    spec, *_ = graph.sim_graph(graph.GraphOptions(params_file=str(PARAMS),
                                                  mavlink_port=free_udp_port(),
                                                  real_time_factor=0.5))
    sim = SimNode(node_name=spec.name, context=context, cli_args=spec.ros_args())
    try:
        assert sim.get_parameter(graph.SIM_PACING).value == 'realtime'
        assert sim.get_parameter(graph.SIM_REAL_TIME_FACTOR).value == 0.5
    finally:
        sim.destroy_node()


def test_composed_nodes_take_the_shared_block_and_a_users_overrides_win(context, tmp_path):
    """ibvs_bringup.composed: /** reaches every node; ``--ros-args -p`` wins over the file."""
    from ibvs_common.core.config import default_config_path
    vehicle = default_config_path('vehicle.yaml')
    data = load()
    data[params.WILDCARD][params.SECTION_KEY]['vehicle_file'] = vehicle
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    specs = [s for s in graph.onboard_graph(graph.GraphOptions(
        params_file=str(path), use_sim_time=False,
        mavlink_url=f'udpout:127.0.0.1:{free_udp_port()}'))
        if s.name in ('front_optical_flow', 'mavlink_bridge')]
    nodes = composed.build_nodes(specs, context)
    try:
        assert {n.get_name(): n.get_parameter('vehicle_file').value for n in nodes} == {
            'front_optical_flow': vehicle,
            'mavlink_bridge': vehicle}
        assert {n.get_name(): n.get_parameter('camera').value for n in nodes
                if n.get_name() == 'front_optical_flow'} == {'front_optical_flow': 'front'}
    finally:
        for node in nodes:
            node.destroy_node()
    nodes = composed.build_nodes(specs, context, user_ros_args=(
        '--ros-args', '-p', 'autopilot:=px4', '-p', 'image_transport:=compressed'))
    try:
        by_name = {n.get_name(): n for n in nodes}
        assert by_name['mavlink_bridge'].get_parameter('autopilot').value == 'px4'  # a section's
        assert by_name['front_optical_flow'].get_parameter('image_transport').value == \
            'compressed'                                                      # a default's
    finally:
        for node in nodes:
            node.destroy_node()
