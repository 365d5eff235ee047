"""ibvs_common.core.params: a parameter file read as a node reads it, and the declaration rules."""
from dataclasses import dataclass

import pytest

from ibvs_common.core import params
from ibvs_common.core.params import group, param


@dataclass(frozen=True)
class Gains:
    kp: float = param(1.0, '1/s^2, gain', 0.0, 10.0)


@dataclass(frozen=True)
class NodeConfig:
    name: str = param('a', 'a name')
    count: int = param(3, 'frames', 1)
    flag: bool = param(True, 'a switch')
    values: list = param([0.0, 0.0], 'm, two numbers')
    words: list = param(['x'], 'names')
    gains: Gains = group(Gains, 'gains.')


def test_file_values_apply_the_matching_entries_in_file_order():
    data = {'/**': {'ros__parameters': {'count': 5, 'name': 'all'}},
            'node': {'ros__parameters': {'count': 7}},
            'other': {'ros__parameters': {'count': 9}}}
    assert params.file_values(data, 'node') == {'count': 7, 'name': 'all'}
    assert params.file_values(data, 'other') == {'count': 9, 'name': 'all'}
    assert params.file_values(data, 'third') == {'count': 5, 'name': 'all'}
    # rcl applies the entries in file order: a /** block after a section wins over it
    late = {'/node': {'ros__parameters': {'count': 7}},
            '/*': {'ros__parameters': {'count': 5}}}
    assert params.file_values(late, 'node') == {'count': 5}
    for empty in (None, [], {}, {'node': None}, {'node': {'ros__parameters': None}}):
        assert params.file_values(empty, 'node') == {}


def test_node_values_are_the_defaults_under_what_the_file_gives_the_node():
    data = {'node': {'ros__parameters': {'count': 4, 'gains.kp': 2.0}},
            '/**': {'ros__parameters': {'name': 'b', 'not_declared_here': 1}}}
    values = params.node_values(NodeConfig, data, 'node')
    assert values == {**params.defaults(NodeConfig), 'count': 4, 'gains.kp': 2.0, 'name': 'b'}
    cfg = params.build(NodeConfig, values)
    assert (cfg.count, cfg.gains.kp, cfg.name) == (4, 2.0, 'b')
    with pytest.raises(ValueError, match='parameter count: 0 outside'):
        params.node_values(NodeConfig, {'node': {'ros__parameters': {'count': 0}}}, 'node')


@pytest.mark.parametrize('name, value, why', [
    ('count', 2.0, 'integer expected, got double'),
    ('count', True, 'integer expected, got bool'),
    ('flag', 1, 'bool expected, got integer'),
    ('gains.kp', 1, 'double expected, got integer'),   # rclpy refuses an integer for a double
    ('gains.kp', 11.0, 'outside'),
    ('values', [1, 2], 'double[] expected, got integer[]'),
    ('values', [1.0, 'a'], 'mixed[]'),
    ('words', [], 'string[] expected, got any[]'),
    ('name', None, 'string expected, got NoneType'),
])
def test_a_value_the_node_would_refuse_is_named(name, value, why):
    default, spec = params.parameters(NodeConfig)[name]
    assert why in params.value_error(name, default, spec, value)
    with pytest.raises(ValueError, match=name):
        params.check(NodeConfig, {name: value})


def test_values_the_node_takes_and_unknown_names():
    for name, value in (('count', 1), ('gains.kp', 10.0), ('values', [1.0, -2.0]),
                        ('words', ['a', 'b']), ('flag', False), ('name', '')):
        default, spec = params.parameters(NodeConfig)[name]
        assert params.value_error(name, default, spec, value) is None, name
    assert params.value_error('gains.kp', 1.0, params.ParamSpec('k', 0.0, 10.0), 2,
                              int_as_double=True) is None
    params.check(NodeConfig, {'gains.kp': 2, 'values': [1, 2]}, int_as_double=True)
    with pytest.raises(ValueError, match=r"not parameters of NodeConfig: \['kp'\]"):
        params.check(NodeConfig, {'kp': 1.0})
