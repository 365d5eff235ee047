"""graph.py, the launch files and setup.py agree: one node list, existing executables."""
import ast
import importlib.util
import os
from pathlib import Path
import re
import shlex
import sys
import types

from ibvs_bringup import graph, parent_death
import pytest

SRC = Path(__file__).resolve().parents[2]      # ros2_ws/src
LAUNCH = SRC / 'ibvs_bringup' / 'launch'
PARAMS = str(SRC / 'ibvs_bringup' / 'config' / 'params.yaml')
EXPECTED_NODES = {'sim', 'window_detector', 'pad_detector', 'front_optical_flow',
                  'down_optical_flow', 'mode_supervisor', 'force_controller', 'mavlink_bridge'}


def console_scripts(package: str) -> set:
    """Console-script names declared in a package's setup.py (parsed, not imported)."""
    text = (SRC / package / 'setup.py').read_text()
    return set(re.findall(r"'(\w+)\s*=\s*[\w.]+:\w+'", text))


def test_sim_graph_is_the_whole_graph_with_unique_names():
    specs = graph.sim_graph(graph.GraphOptions(params_file=PARAMS))
    names = [s.name for s in specs]
    assert set(names) == EXPECTED_NODES and len(names) == len(set(names))
    assert [s.role for s in specs].count('sim') == 1
    flows = {s.name: s.overrides()['camera'] for s in specs if s.executable == 'optical_flow'}
    assert flows == {'front_optical_flow': 'front', 'down_optical_flow': 'down'}
    for s in specs:
        assert s.param_files() == [PARAMS]          # the onboard parameters, unchanged
        if s.role == 'onboard':
            assert s.overrides()['use_sim_time'] is True


def test_every_executable_is_a_console_script_of_its_package():
    specs = graph.sim_graph(graph.GraphOptions(params_file=PARAMS)) + [
        graph.tool_node('recorder', 'recorder'), graph.tool_node('bag_player', 'bag_player')]
    for s in specs:
        assert s.executable in console_scripts(s.package), (s.package, s.executable)
    assert {'runner', 'preflight'} <= console_scripts('ibvs_bringup')


def test_params_yaml_configures_every_node_and_each_has_a_config():
    """Its ``/**`` block reaches every node (test_bringup_params_file checks the rest)."""
    import yaml
    assert '/**' in yaml.safe_load(Path(PARAMS).read_text())
    assert list(graph.node_configs()) == ['sim', graph.PX4_SIM_NAME,
                                          *graph.ONBOARD_NODE_NAMES]


def test_flight_path_of_the_sim_graph_is_the_onboard_graph_on_another_clock():
    """Same files and overrides for every flight-path node; only the clock and URL differ."""
    sim = {s.name: s for s in graph.sim_graph(graph.GraphOptions(params_file=PARAMS))
           if s.role == 'onboard'}
    onboard = {s.name: s for s in graph.onboard_graph(graph.GraphOptions(
        params_file=PARAMS, use_sim_time=False, mavlink_url='udpin:0.0.0.0:14540'))}
    assert set(sim) == set(onboard)
    for name, spec in sim.items():
        assert spec.param_files() == onboard[name].param_files() == [PARAMS]
        a, b = spec.overrides(), onboard[name].overrides()
        differing = {k for k in set(a) | set(b) if a.get(k) != b.get(k)}
        # the sim scenario also asks the bridge to arm; onboard only the ibvs/arm service does
        assert differing <= {'use_sim_time', graph.BRIDGE_URL, graph.BRIDGE_ARM_ON_START}, \
            (name, differing)
    assert sim['mavlink_bridge'].overrides()[graph.BRIDGE_ARM_ON_START] is True
    assert graph.BRIDGE_ARM_ON_START not in onboard['mavlink_bridge'].overrides()


def test_mavlink_port_and_options_reach_the_right_nodes():
    opts = graph.GraphOptions(params_file=PARAMS, mavlink_port=15001,
                              initial_position=(-2.2, 0.2, -1.5), wind=(0.0, 0.335, 0.0),
                              crossing_law='seed', auto_start_at_s=1.0)
    by_name = {s.name: s for s in graph.sim_graph(opts)}
    assert by_name['mode_supervisor'].overrides()[graph.SUPERVISOR_AUTO_START] == 1.0
    assert by_name['sim'].overrides()[graph.MAVLINK_URL] == 'udpin:127.0.0.1:15001'
    assert by_name['mavlink_bridge'].overrides()[graph.BRIDGE_URL] == 'udpout:127.0.0.1:15001'
    assert by_name['sim'].overrides()[graph.SIM_INITIAL_POSITION] == [-2.2, 0.2, -1.5]
    assert by_name['sim'].overrides()[graph.SIM_INITIAL_OVERRIDE] is True
    # wind given in {I} (y_I = side), sent in map ENU: x_ENU = y_I
    assert by_name['sim'].overrides()[graph.SIM_WIND] == [0.335, 0.0, 0.0]
    plain = {s.name: s for s in graph.sim_graph(graph.GraphOptions(params_file=PARAMS))}
    assert graph.SIM_INITIAL_OVERRIDE not in plain['sim'].overrides()
    assert graph.SUPERVISOR_AUTO_START not in plain['mode_supervisor'].overrides()
    assert by_name['force_controller'].overrides()[graph.CROSSING_LAW] == 'seed'
    assert graph.CROSSING_LAW not in by_name['mode_supervisor'].overrides()
    assert graph.SIM_WIND not in by_name['force_controller'].overrides()
    with pytest.raises(ValueError):
        graph.sim_graph(graph.GraphOptions(params_file=PARAMS, crossing_law='bogus'))
    with pytest.raises(ValueError):
        graph.sim_graph(graph.GraphOptions(params_file=PARAMS, mavlink_port=70000))


def test_onboard_graph_has_no_sim_and_uses_the_vehicle_url():
    specs = graph.onboard_graph(graph.GraphOptions(params_file=PARAMS, use_sim_time=False,
                                                   mavlink_url='udpout:10.0.0.2:14540'))
    assert {s.name for s in specs} == EXPECTED_NODES - {'sim'}
    bridge = next(s for s in specs if s.name == 'mavlink_bridge')
    assert bridge.overrides()[graph.BRIDGE_URL] == 'udpout:10.0.0.2:14540'
    assert all('use_sim_time' not in s.overrides() for s in specs)


def test_ros_args_are_what_ros2_run_expects():
    spec = graph.NodeSpec('p', 'e', 'n', ('/a.yaml', {'x': [1.0, -2.0], 'b': True, 'i': 3}),
                          (('imu/data', 'imu'),), 'onboard')
    assert spec.ros_args() == ['--ros-args', '-r', '__node:=n', '--params-file', '/a.yaml',
                               '-p', 'x:=[1.0,-2.0]', '-p', 'b:=true', '-p', 'i:=3',
                               '-r', 'imu/data:=imu']
    with pytest.raises(ValueError):
        graph.NodeSpec('p', 'e', 'n', role='other')


# --- launch files -------------------------------------------------------------------------

def _fake_launch_modules():
    """Minimal stand-ins for launch/launch_ros that record what the launch file builds."""
    class Recorder:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    mods = {}
    for name, attrs in {'launch': ['LaunchDescription'],
                        'launch.actions': ['DeclareLaunchArgument', 'OpaqueFunction'],
                        'launch.substitutions': ['LaunchConfiguration'],
                        'launch_ros': [], 'launch_ros.actions': ['Node']}.items():
        mod = types.ModuleType(name)
        for a in attrs:
            setattr(mod, a, type(a, (Recorder,), {}))
        mods[name] = mod
    return mods


def _load_launch(path: Path, monkeypatch):
    for name, mod in _fake_launch_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location(path.stem.replace('.', '_'), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Context:
    def __init__(self, values):
        self.values = values

    def perform_substitution(self, sub):
        return self.values[sub.args[0]]


def _assert_ends_with_launch(node) -> None:
    """The node runs through parent_death with this (launch) process as the parent, as the
    runner's nodes do (test_bringup_runner: a killed runner takes its nodes with it)."""
    if not parent_death.supported():
        assert node.kwargs['prefix'] is None
        return
    words = shlex.split(node.kwargs['prefix'])
    assert words == [sys.executable, '-m', 'ibvs_bringup.parent_death', str(os.getpid()), '--']


@pytest.mark.parametrize('file_name, builder', [('sim.launch.py', 'sim_graph'),
                                                ('onboard.launch.py', 'onboard_graph')])
def test_launch_file_takes_its_node_list_from_graph(file_name, builder):
    tree = ast.parse((LAUNCH / file_name).read_text())
    calls = {n.func.attr for n in ast.walk(tree)
             if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)}
    assert builder in calls
    literals = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)}
    hard_coded = literals & (EXPECTED_NODES | {'ibvs_sim', 'ibvs_perception', 'ibvs_control'})
    assert not hard_coded, f'{file_name} must not list nodes itself: {hard_coded}'


@pytest.mark.parametrize('file_name, values', [
    ('sim.launch.py', {'params_file': PARAMS, 'mavlink_port': '14999', 'crossing_law': ''}),
    ('onboard.launch.py', {'params_file': PARAMS, 'mavlink_url': 'udpout:10.0.0.2:14540',
                           'use_sim_time': 'false', 'crossing_law': 'intended',
                           'layout': 'processes'})])
def test_launch_file_builds_the_graph_nodes(file_name, values, monkeypatch):
    module = _load_launch(LAUNCH / file_name, monkeypatch)
    ld = module.generate_launch_description()
    declared = {a.args[0] for a in ld.args[0] if type(a).__name__ == 'DeclareLaunchArgument'}
    assert declared == set(values)
    opaque = next(a for a in ld.args[0] if type(a).__name__ == 'OpaqueFunction')
    nodes = opaque.kwargs['function'](_Context(values))
    names = {n.kwargs['name'] for n in nodes}
    expected = EXPECTED_NODES if file_name.startswith('sim') else EXPECTED_NODES - {'sim'}
    assert names == expected
    for n in nodes:
        assert n.kwargs['executable'] in console_scripts(n.kwargs['package'])
        # launch_ros respawns the perception nodes, like the runner
        assert n.kwargs['respawn'] is (n.kwargs['package'] == 'ibvs_perception')
        assert n.kwargs['respawn_delay'] == graph.RESPAWN_DELAY_S
        assert n.kwargs['parameters'][0] == PARAMS
        _assert_ends_with_launch(n)
    urls = {n.kwargs['name']: n.kwargs['parameters'][-1].get(
        graph.BRIDGE_URL if n.kwargs['name'] == 'mavlink_bridge' else graph.MAVLINK_URL)
        for n in nodes if isinstance(n.kwargs['parameters'][-1], dict)}
    if file_name.startswith('sim'):
        assert urls['sim'] == 'udpin:127.0.0.1:14999'
    else:
        assert urls['mavlink_bridge'] == 'udpout:10.0.0.2:14540'


def test_onboard_launch_composes_the_same_nodes_by_default(monkeypatch):
    """layout:=composed (the default): one respawned process running graph.onboard_graph."""
    from ibvs_bringup import composed
    module = _load_launch(LAUNCH / 'onboard.launch.py', monkeypatch)
    ld = module.generate_launch_description()
    layout = next(a for a in ld.args[0] if type(a).__name__ == 'DeclareLaunchArgument'
                  and a.args[0] == 'layout')
    assert layout.kwargs['default_value'] == 'composed'
    values = {'params_file': PARAMS, 'mavlink_url': 'udpout:10.0.0.2:14540',
              'use_sim_time': 'false', 'crossing_law': '', 'layout': 'composed'}
    opaque = next(a for a in ld.args[0] if type(a).__name__ == 'OpaqueFunction')
    (node,) = opaque.kwargs['function'](_Context(values))
    assert node.kwargs['package'] == 'ibvs_bringup'
    assert node.kwargs['executable'] == 'composed' in console_scripts('ibvs_bringup')
    assert 'name' not in node.kwargs          # a name would rename every node inside it
    assert node.kwargs['respawn'] is True
    assert node.kwargs['respawn_delay'] == graph.RESPAWN_DELAY_S
    _assert_ends_with_launch(node)
    flag, path = node.kwargs['arguments']
    assert flag == '--specs'
    specs = composed.read_specs(path)
    os.remove(path)
    expected = graph.onboard_graph(graph.GraphOptions(
        params_file=PARAMS, use_sim_time=False, mavlink_url='udpout:10.0.0.2:14540'))
    assert specs == expected
    with pytest.raises(ValueError, match='layout'):
        opaque.kwargs['function'](_Context({**values, 'layout': 'threads'}))


def test_onboard_launch_grouped_is_a_respawned_container_per_group(monkeypatch):
    """layout:=grouped: one composed container per composed.GROUPS entry, all nodes in one."""
    from ibvs_bringup import composed
    module = _load_launch(LAUNCH / 'onboard.launch.py', monkeypatch)
    ld = module.generate_launch_description()
    values = {'params_file': PARAMS, 'mavlink_url': 'udpout:10.0.0.2:14540',
              'use_sim_time': 'false', 'crossing_law': '', 'layout': 'grouped'}
    opaque = next(a for a in ld.args[0] if type(a).__name__ == 'OpaqueFunction')
    nodes = opaque.kwargs['function'](_Context(values))
    assert len(nodes) == len(composed.GROUPS)
    expected = graph.onboard_graph(graph.GraphOptions(
        params_file=PARAMS, use_sim_time=False, mavlink_url='udpout:10.0.0.2:14540'))
    for node, names in zip(nodes, composed.GROUPS.values()):
        assert node.kwargs['executable'] == 'composed' and 'name' not in node.kwargs
        assert node.kwargs['respawn'] is True
        _assert_ends_with_launch(node)
        flag, path = node.kwargs['arguments']
        specs = composed.read_specs(path)
        os.remove(path)
        assert specs == [s for s in expected if s.name in names]


def test_free_running_option_changes_only_the_sim():
    plain = graph.sim_graph(graph.GraphOptions(params_file=PARAMS))
    free = graph.sim_graph(graph.GraphOptions(params_file=PARAMS, real_time_factor=0.25))
    for a, b in zip(plain, free):
        if a.role == 'sim':
            assert b.overrides()[graph.SIM_PACING] == 'realtime'
            assert b.overrides()[graph.SIM_REAL_TIME_FACTOR] == 0.25
            assert graph.SIM_PACING not in a.overrides()
        else:
            assert a == b
    with pytest.raises(ValueError):
        graph.sim_graph(graph.GraphOptions(params_file=PARAMS, real_time_factor=0.0))


def test_only_perception_nodes_respawn():
    specs = {s.name: s for s in graph.onboard_graph(graph.GraphOptions(params_file=PARAMS))}
    assert {n for n, s in specs.items() if s.respawn} == {
        'window_detector', 'pad_detector', 'front_optical_flow', 'down_optical_flow'}


def test_the_venv_prefix_is_found_without_ament_prefix_path(tmp_path, monkeypatch):
    marker = tmp_path / 'share' / 'ament_index' / 'resource_index' / 'packages'
    marker.mkdir(parents=True)
    monkeypatch.delenv(graph.AMENT_ENV, raising=False)
    graph.ensure_ament_prefix_path(str(tmp_path))          # no ibvs_bringup marker: left unset
    assert graph.AMENT_ENV not in os.environ
    (marker / graph.CONFIG_PACKAGE).touch()
    graph.ensure_ament_prefix_path(str(tmp_path))
    assert os.environ[graph.AMENT_ENV] == str(tmp_path)
    graph.ensure_ament_prefix_path('/elsewhere')           # a set path is never changed
    assert os.environ[graph.AMENT_ENV] == str(tmp_path)


def test_onboard_window_size_agrees_with_the_sim_world():
    """The onboard nodes know the window from window_layout.yaml, never from the sim's world.

    r_w for the controller and supervisor, the aperture and band size for the window
    detector's band proportions: one file, the vehicle's belief, which world.yaml (the sim's
    truth) must match by default; no node keeps a size of its own in params.yaml.
    """
    import yaml
    from ibvs_common.core.config import load_window_layout
    from ibvs_common.core.params import file_values, parameters
    from ibvs_sim.core.world import load_world
    data = yaml.safe_load(Path(PARAMS).read_text())
    truth, belief = load_world().window, load_window_layout()
    assert (belief.width, belief.height, belief.frame_band) == \
        (truth.width, truth.height, truth.frame_band)
    configs = graph.node_configs()
    for node in ('mode_supervisor', 'force_controller', 'window_detector'):
        declared = parameters(configs[node])
        assert 'world_file' not in declared
        assert file_values(data, node).get('window_layout_file', '') == '', node
        assert not {'window_width_m', 'window_height_m', 'frame_band_m'} & set(declared), node


def test_the_node_name_table_is_the_graphs_node_list():
    onboard = graph.onboard_graph(graph.GraphOptions(params_file=PARAMS, use_sim_time=False))
    assert tuple(s.name for s in onboard) == graph.ONBOARD_NODE_NAMES
    sim = graph.sim_graph(graph.GraphOptions(params_file=PARAMS))
    assert tuple(s.name for s in sim) == graph.SIM_NODE_NAMES


@pytest.mark.parametrize('content, message', [
    (None, 'cannot be read'),
    ('window_detector: [unclosed', 'not valid YAML'),
    ('some_other_node:\n  ros__parameters:\n    x: 1\n', 'configures none of the nodes'),
    ('- a list\n', 'configures none of the nodes')])
def test_a_parameter_file_that_cannot_configure_the_graph_is_refused(tmp_path, content,
                                                                     message):
    """launch_ros only warns and runs on code defaults; the graph refuses with the reason."""
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    for build in (graph.sim_graph, graph.onboard_graph):
        with pytest.raises(ValueError, match=message) as err:
            build(graph.GraphOptions(params_file=str(path)))
        assert str(path) in str(err.value)


def test_a_parameter_file_for_some_nodes_or_wildcards_is_accepted(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    use_sim_time: false\n')
    assert graph.checked_params_file(str(path), graph.ONBOARD_NODE_NAMES) == str(path)
    path.write_text('force_controller:\n  ros__parameters:\n    crossing_law: closed\n')
    assert graph.checked_params_file(str(path), graph.ONBOARD_NODE_NAMES) == str(path)
    assert graph.checked_params_file(None, graph.ONBOARD_NODE_NAMES).endswith('params.yaml')


@pytest.mark.parametrize('content, fault', [
    ('width: 1.2\nheight: 1.0\n', "missing key 'frame_band'"),
    ('width: -1.2\nheight: 1.0\nframe_band: 0.08\n', 'must be > 0'),
    ('width: .nan\nheight: 1.0\nframe_band: 0.08\n', 'must be > 0'),
    ('width: wide\nheight: 1.0\nframe_band: 0.08\n', 'could not convert'),
])
def test_a_bad_window_layout_is_refused_with_the_file_and_the_reason(tmp_path, content, fault):
    from ibvs_common.core.config import ConfigError, load_window_layout
    path = tmp_path / 'window_layout.yaml'
    path.write_text(content)
    with pytest.raises(ConfigError, match=fault) as info:
        load_window_layout(path)
    assert str(path) in str(info.value)
