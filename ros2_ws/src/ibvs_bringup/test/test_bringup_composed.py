"""The composed layouts (ibvs_bringup.composed): one process, or a few containers (GROUPS)."""
import pytest

from ibvs_bringup import composed, graph


def test_every_onboard_node_has_a_class_and_exactly_one_group():
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False))
    for spec in specs:
        assert composed.node_class(spec.package, spec.executable).__name__.endswith('Node')
    grouped = [name for names in composed.GROUPS.values() for name in names]
    assert sorted(grouped) == sorted(graph.ONBOARD_NODE_NAMES)
    assert len(grouped) == len(set(grouped))


def test_an_unknown_node_name_is_refused_before_anything_starts(capsys):
    assert composed.main(['--nodes', 'window_detector,no_such_node']) == 2
    assert "unknown node name(s) ['no_such_node']" in capsys.readouterr().err


def test_specs_round_trip_through_the_json_file(tmp_path):
    specs = graph.sim_graph(graph.GraphOptions(mavlink_port=14999, wind=(0.1, 0.0, 0.0),
                                               extra_remappings=(('a', 'b'),)))
    path = str(tmp_path / 'specs.json')
    composed.write_specs(specs, path)
    back = composed.read_specs(path)
    assert back == specs                                 # tuples, dicts, roles, respawn
    assert [s.ros_args() for s in back] == [s.ros_args() for s in specs]


def test_a_bad_specs_file_is_refused_with_its_path(tmp_path, capsys):
    bad = tmp_path / 'bad.json'
    bad.write_text('[{"package": "ibvs_control"}]')
    assert composed.main(['--specs', str(bad)]) == 2
    assert f'bad node spec file {bad}' in capsys.readouterr().err


def test_the_runner_composes_the_onboard_specs_only(tmp_path, monkeypatch):
    from ibvs_bringup.runner import COMPOSED_NAME, ProcessRunner
    started = []
    runner = ProcessRunner(log_dir=str(tmp_path))
    monkeypatch.setattr(runner, 'start', lambda name, argv, respawn=False:
                        started.append((name, argv)))
    specs = graph.sim_graph(graph.GraphOptions(mavlink_port=14999))
    runner.start_layout(specs, 'composed')
    names = [n for n, _ in started]
    assert names == ['sim', COMPOSED_NAME]
    argv = started[1][1]
    assert argv[1:4] == ['-m', 'ibvs_bringup.composed', '--specs']
    assert [s.name for s in composed.read_specs(argv[4])] == list(graph.ONBOARD_NODE_NAMES)


def test_onboard_default_layout_is_one_respawned_process(tmp_path, monkeypatch):
    from ibvs_bringup import runner as runner_mod
    started = []
    runner = runner_mod.ProcessRunner(log_dir=str(tmp_path))
    monkeypatch.setattr(runner, 'start', lambda name, argv, respawn=False:
                        started.append((name, respawn)))
    assert runner_mod.DEFAULT_LAYOUT == {'onboard': 'composed', 'sim': 'processes'}
    specs = graph.onboard_graph(graph.GraphOptions(use_sim_time=False))
    runner.start_layout(specs, runner_mod.DEFAULT_LAYOUT['onboard'], respawn_composed=True)
    assert started == [(runner_mod.COMPOSED_NAME, True)]
    started.clear()
    runner.start_layout(specs, 'processes')
    assert [name for name, _ in started] == list(graph.ONBOARD_NODE_NAMES)
    assert [name for name, respawn in started if respawn] == [
        s.name for s in specs if s.respawn]
    with pytest.raises(ValueError, match='layout'):
        runner.start_layout(specs, 'threads')


def test_the_grouped_layout_starts_a_respawned_container_per_group(tmp_path, monkeypatch):
    """--layout grouped: the sim alone, then one container per GROUPS entry, its nodes only."""
    from ibvs_bringup import runner as runner_mod
    started = []
    runner = runner_mod.ProcessRunner(log_dir=str(tmp_path))
    monkeypatch.setattr(runner, 'start', lambda name, argv, respawn=False:
                        started.append((name, argv, respawn)))
    specs = graph.sim_graph(graph.GraphOptions(mavlink_port=14999))
    runner.start_layout(specs, 'grouped', respawn_composed=True)
    assert [n for n, _, _ in started] == ['sim'] + [f'onboard_{g}' for g in composed.GROUPS]
    for (name, argv, respawn), (group, names) in zip(started[1:], composed.GROUPS.items()):
        assert name == runner_mod.container_name(group) and respawn is True
        assert [s.name for s in composed.read_specs(argv[4])] == [
            s.name for s in specs if s.name in names]
    # where a node's log is: its own process, the composed one, or its group's container
    assert runner_mod.process_names('mode_supervisor') == (
        'mode_supervisor', 'onboard', 'onboard_control')
