"""Declare ROS parameters with descriptors: the one helper of every node.

A node's parameters are the :func:`~ibvs_common.core.params.param` fields of its config
dataclass (core/params.py: default, description, range, unit in one place);
:func:`declare_config` declares them all and returns the dataclass built from their values.
Underneath, a parameter's *spec* is a plain tuple: ``(description,)`` for a string, bool or
list parameter and ``(description, lo, hi)`` for an integer or a double one: its inclusive
range, ``None`` for an unbounded side.

:func:`declare` builds the :class:`ParameterDescriptor` (description, ``IntegerRange`` or
``FloatingPointRange`` with step 0, ``read_only``) and declares the parameter. Every node of
the flight path reads its parameters once, at start (no node registers an on-set-parameters
callback), so they are all read-only: rclpy rejects a runtime ``set_parameters`` on them, and
``ros2 param describe`` shows the description and the range. A value of the wrong type or out
of range (params.yaml, ``-p`` overrides) raises ValueError naming the parameter: each node's
``main()`` logs it as fatal and exits with status 1.
"""
from __future__ import annotations

from dataclasses import fields
import math
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node

from ibvs_common.core import params

INT64_MIN, INT64_MAX = -2 ** 63, 2 ** 63 - 1


is_numeric = params.is_numeric


def descriptor(name: str, default: Any, spec: tuple | str,
               read_only: bool = True) -> ParameterDescriptor:
    """Return the descriptor of parameter ``name`` from its default and its spec.

    Raises TypeError for a spec that does not fit the default (a numeric parameter without a
    range, a range on a string...) and ValueError for a default outside its own range: both
    are programming errors, found by the node tests.
    """
    description, *bounds = (spec,) if isinstance(spec, str) else tuple(spec)
    if not isinstance(description, str) or not description.strip():
        raise TypeError(f'parameter {name}: empty description')
    if is_numeric(default) != bool(bounds) or len(bounds) not in (0, 2):
        raise TypeError(f'parameter {name}: an integer or double needs (description, lo, hi), '
                        f'other types (description,) only; got {spec!r}')
    out = ParameterDescriptor(description=description, read_only=read_only)
    if bounds:
        lo, hi = bounds
        if isinstance(default, int):
            lo, hi = (INT64_MIN if lo is None else int(lo)), (INT64_MAX if hi is None else int(hi))
            out.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=0)]
        else:
            lo = -math.inf if lo is None else float(lo)
            hi = math.inf if hi is None else float(hi)
            out.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
        if not lo <= default <= hi:
            raise ValueError(f'parameter {name}: default {default} outside [{lo}, {hi}]')
    return out


def declare_config(node: Node, cls: type, prefix: str = '', **fixed: Any) -> Any:
    """Declare every parameter of config dataclass ``cls``; return it built from their values.

    ``fixed``: its fields that are not parameters (values from files). Raises ValueError
    naming the parameter for a value of the wrong type or out of range, and whatever the
    dataclass's own checks raise.
    """
    values = {name: declare(node, name, default, spec.as_tuple(default), spec.read_only)
              for name, (default, spec) in params.parameters(cls, prefix).items()}
    return params.build(cls, values, prefix, **fixed)


def declare(node: Node, name: str, default: Any, spec: tuple | str,
            read_only: bool = True) -> Any:
    """Declare ``name`` (read-only unless told, with its descriptor) on ``node``; return its value.

    Raises ValueError naming the parameter for a value of the wrong type or out of range.
    """
    try:
        return node.declare_parameter(name, default,
                                      descriptor(name, default, spec, read_only)).value
    except ParameterException as exc:     # str: '<message>: <name>', the name said first
        text = str(exc).removesuffix(f': {name}')
        raise ValueError(f'parameter {name}: {text}') from exc


def declare_all(node: Node, defaults: dict, specs: dict, prefix: str = '') -> dict:
    """Declare every ``prefix + name`` of ``defaults`` with ``specs[name]``; return name -> value.

    KeyError for a default without a spec (every parameter is documented) or a spec without a
    default (a stale one): the two dicts name the same parameters.
    """
    missing, stale = sorted(set(defaults) - set(specs)), sorted(set(specs) - set(defaults))
    if missing or stale:
        raise KeyError(f'parameters without a spec (description, range): {missing}; '
                       f'specs of no parameter: {stale}')
    return {name: declare(node, prefix + name, default, specs[name])
            for name, default in defaults.items()}


def dataclass_defaults(cls, exclude: tuple = ()) -> dict:
    """Return field name -> default of dataclass ``cls``, without the names in ``exclude``."""
    instance = cls()
    return {f.name: getattr(instance, f.name) for f in fields(cls) if f.name not in exclude}
