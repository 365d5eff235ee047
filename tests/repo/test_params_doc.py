"""docs/parameters.md is scripts/params_doc.py's output: the parameter reference cannot drift."""
from pathlib import Path
import sys

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / 'scripts'))
import params_doc  # noqa: E402


def test_the_committed_parameter_reference_is_the_generated_one():
    committed = (ROOT / params_doc.DOC).read_text(encoding='utf-8')
    assert committed == params_doc.render(ROOT), \
        'docs/parameters.md is out of date: run scripts/params_doc.py'


def test_every_node_of_the_graph_and_every_tool_has_its_table():
    from ibvs_bringup import graph
    from ibvs_common.core.params import parameters
    text = params_doc.render(ROOT)
    nodes = params_doc.doc_nodes(ROOT)
    assert [n for names, *_ in nodes for n in names] == \
        [*graph.node_configs(), 'recorder', 'bag_player']
    for names, _, _, cls in nodes:
        section = text[text.index(f'\n## {", ".join(names)}\n'):]
        for name in parameters(cls):
            assert f'\n| `{name}` |' in section, (names, name)


def test_the_cells_are_formatted_as_in_a_parameter_file():
    from ibvs_common.core.params import ParamSpec
    assert params_doc.format_value([True, 1, 0.5, 'a']) == "[true, 1, 0.5, 'a']"
    assert params_doc.format_range(2, ParamSpec('n', 1, None)) == '>= 1'
    assert params_doc.format_range(0.5, ParamSpec('x', 0.0, 1.0)) == '[0.0, 1.0]'
    assert params_doc.format_range(0.5, ParamSpec('x')) == 'any'
    assert params_doc.format_range('s', ParamSpec('s')) == ''
    assert params_doc.cell('a | b\n c') == 'a \\| b c'
    assert params_doc.anchor('front_optical_flow, down_optical_flow') == \
        'front_optical_flow-down_optical_flow'
