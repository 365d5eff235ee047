"""The composed layouts (ibvs_bringup.composed): one process, or a few containers (GROUPS)."""
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
