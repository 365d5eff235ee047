"""One source per parameter: a config dataclass field carries its default, description and range.

A node's typed configuration is a frozen dataclass whose fields are declared with
:func:`param` (a ROS parameter: default, description, inclusive range, unit) or :func:`group`
(a nested config whose parameters are named with a prefix, e.g. ``imu_`` or ``landing.``).
Fields declared plainly are not parameters (values from files, derived values). The node
side (:func:`ibvs_common.param_descriptors.declare_config`) declares every parameter from
this and builds the dataclass from the values; documentation (docs/parameters.md) is
generated from it too. ROS-free.

A parameter file (params.yaml, loaded with ``yaml.safe_load``) sets only what a deployment
changes: :func:`node_values` reads it as a node does (the code defaults, then the file's
entries that match the node: ``/**`` and its section, in file order), :func:`check` and
:func:`value_error` apply the type and range rules of the node's declaration, for the
harness's ROS-free builds of the same cores and for the tests of the file.

Times say their clock in the description (ROS clock: sim time under ``use_sim_time``; or the
steady/wall clock).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields, is_dataclass, MISSING
from typing import Any

PARAM = 'ibvs_param'
GROUP = 'ibvs_group'


@dataclass(frozen=True)
class ParamSpec:
    """Description, unit and inclusive range of one parameter (None: unbounded side)."""

    description: str
    lo: float | None = None
    hi: float | None = None
    unit: str = ''
    read_only: bool = True

    @property
    def text(self) -> str:
        """The description as ``ros2 param describe`` shows it: unit first."""
        return f'{self.unit}: {self.description}' if self.unit else self.description

    def as_tuple(self, default: Any) -> tuple:
        """``(text,)`` or ``(text, lo, hi)`` for a numeric default (param_descriptors' spec)."""
        if is_numeric(default):
            return (self.text, self.lo, self.hi)
        return (self.text,)


def is_numeric(value: Any) -> bool:
    """Return True for an integer or double parameter value (bool is neither)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def param(default: Any, description: str, lo: float | None = None, hi: float | None = None,
          unit: str = '', read_only: bool = True) -> Any:
    """Declare a dataclass field that is a ROS parameter (see the module doc).

    A list default is copied per instance. ``read_only`` False: the node applies a new value
    at run time (it registers a callback for it).
    """
    spec = ParamSpec(description, lo, hi, unit, read_only)
    if isinstance(default, list):
        return field(default_factory=lambda: copy.copy(default), metadata={PARAM: spec})
    return field(default=default, metadata={PARAM: spec})


def group(cls: type, prefix: str = '') -> Any:
    """Declare a nested config field whose parameters are ``prefix + name``."""
    return field(default_factory=cls, metadata={GROUP: prefix})


def _default(f) -> Any:
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    raise TypeError(f'parameter field {f.name} has no default')


def parameters(cls: type, prefix: str = '') -> dict[str, tuple[Any, ParamSpec]]:
    """Return ``{full name: (default, spec)}`` of every parameter of ``cls``, in field order."""
    if not is_dataclass(cls):
        raise TypeError(f'{cls!r} is not a dataclass')
    out: dict[str, tuple[Any, ParamSpec]] = {}
    for f in fields(cls):
        if PARAM in f.metadata:
            out[prefix + f.name] = (_default(f), f.metadata[PARAM])
        elif GROUP in f.metadata:
            sub = f.default_factory if f.default_factory is not MISSING else type(f.default)
            for name, value in parameters(sub, prefix + f.metadata[GROUP]).items():
                if name in out:
                    raise TypeError(f'parameter {name} declared twice in {cls.__name__}')
                out[name] = value
    return out


def specs(cls: type, prefix: str = '') -> dict[str, tuple]:
    """Return ``{full name: (description[, lo, hi])}`` (param_descriptors' spec tuples)."""
    return {name: spec.as_tuple(default)
            for name, (default, spec) in parameters(cls, prefix).items()}


def defaults(cls: type, prefix: str = '') -> dict[str, Any]:
    """Return ``{full name: default}`` of every parameter of ``cls``."""
    return {name: default for name, (default, _) in parameters(cls, prefix).items()}


def build(cls: type, values: dict[str, Any], prefix: str = '', **fixed: Any) -> Any:
    """Build ``cls`` from parameter values keyed by full name (missing ones keep defaults).

    ``fixed``: values of fields that are not parameters (from files). A value of a double
    parameter given as an integer becomes a float. The dataclass's own checks
    (``__post_init__``) run as usual and raise ValueError.
    """
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        name = prefix + f.name
        if PARAM in f.metadata and name in values:
            value = values[name]
            if isinstance(_default(f), float) and is_numeric(value):
                value = float(value)
            elif isinstance(_default(f), list):
                value = list(value)
            kwargs[f.name] = value
        elif GROUP in f.metadata:
            sub = f.default_factory if f.default_factory is not MISSING else type(f.default)
            kwargs[f.name] = build(sub, values, prefix + f.metadata[GROUP])
    kwargs.update(fixed)
    return cls(**kwargs)


# --- parameter files (params.yaml) ------------------------------------------------------------

WILDCARD = '/**'                  # the block of a parameter file that applies to every node
WILDCARDS = (WILDCARD, '/*')      # '/*': every node of the root namespace (all of ours)
SECTION_KEY = 'ros__parameters'


def file_section(data: Any, key: str) -> dict[str, Any]:
    """Return the ``ros__parameters`` of entry ``key`` of a loaded parameter file ({} if none)."""
    entry = data.get(key) if isinstance(data, dict) else None
    values = entry.get(SECTION_KEY) if isinstance(entry, dict) else None
    return dict(values) if isinstance(values, dict) else {}


def file_values(data: Any, node: str) -> dict[str, Any]:
    """Return what a loaded parameter file gives node ``node`` (of the root namespace).

    Its entries that match the node (``/**``, ``/*``, ``node``, ``/node``) in file order, a
    later one winning for a name that two of them set, as rcl applies them (params.yaml sets
    each name in one entry only). Names the node does not declare are in it too: the node
    ignores them (no node allows undeclared parameters); see :func:`node_values`.
    """
    out: dict[str, Any] = {}
    if isinstance(data, dict):
        for key in data:
            if key in WILDCARDS or key in (node, '/' + node):
                out.update(file_section(data, key))
    return out


def type_name(value: Any) -> str:
    """Return the ROS parameter type of a value: bool, integer, double, string or ``<type>[]``.

    A list of mixed element types (which rcl refuses in a file) is ``mixed[]``, an empty one
    ``any[]``; any other Python type is named by its own name.
    """
    if isinstance(value, (list, tuple)):
        kinds = {type_name(v) for v in value}
        return (kinds.pop() if len(kinds) == 1 else 'any' if not kinds else 'mixed') + '[]'
    if isinstance(value, bool):
        return 'bool'
    if isinstance(value, int):
        return 'integer'
    if isinstance(value, float):
        return 'double'
    if isinstance(value, str):
        return 'string'
    return type(value).__name__


def value_error(name: str, default: Any, spec: ParamSpec, value: Any,
                int_as_double: bool = False) -> str | None:
    """Return why ``value`` cannot be parameter ``name`` at a node's start, or None if it can.

    The rules of rclpy's declaration: the type of the default (a double refuses an integer
    unless ``int_as_double``; a list wants a non-empty list of the default's element type) and
    the inclusive range of an integer or a double. The node's own checks (the dataclass's
    ``__post_init__``) come on top.
    """
    want, got = type_name(default), type_name(value)
    if int_as_double and want.startswith('double') and got.startswith('integer'):
        got = got.replace('integer', 'double')
    if want == 'any[]' and got.endswith('[]') and got != 'mixed[]':
        got = want                        # an empty default: any list the file can type
    if got != want:
        return f'parameter {name}: {want} expected, got {got} ({value!r})'
    if is_numeric(value):
        lo = -float('inf') if spec.lo is None else spec.lo
        hi = float('inf') if spec.hi is None else spec.hi
        if not lo <= value <= hi:
            return f'parameter {name}: {value!r} outside [{lo}, {hi}]'
    return None


def check(cls: type, values: dict[str, Any], int_as_double: bool = False) -> None:
    """Raise ValueError for a value of ``values`` that node config ``cls`` refuses at start.

    Names that are not parameters of ``cls`` are refused too (ValueError naming them): use it
    on what a node is meant to read (a section, overrides), not on a ``/**`` block.
    """
    known = parameters(cls)
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f'not parameters of {cls.__name__}: {unknown}')
    errors = [e for name, value in values.items()
              if (e := value_error(name, *known[name], value, int_as_double)) is not None]
    if errors:
        raise ValueError('; '.join(errors))


def node_values(cls: type, data: Any, node: str) -> dict[str, Any]:
    """Return every parameter of ``cls`` as node ``node`` reads it from a loaded parameter file.

    The code defaults, overridden by :func:`file_values` for the names ``cls`` declares (the
    others are ignored, as the node ignores them). Raises ValueError for a value the node would
    refuse (type, range). Build the config with ``build(cls, node_values(...))``.
    """
    known = parameters(cls)
    given = {k: v for k, v in file_values(data, node).items() if k in known}
    check(cls, given)
    return {**defaults(cls), **given}
