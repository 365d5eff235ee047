"""One source per parameter: a config dataclass field carries its default, description and range.

A node's typed configuration is a frozen dataclass whose fields are declared with
:func:`param` (a ROS parameter: default, description, inclusive range, unit) or :func:`group`
(a nested config whose parameters are named with a prefix, e.g. ``imu_`` or ``landing.``).
Fields declared plainly are not parameters (values from files, derived values). The node
side (:func:`ibvs_common.param_descriptors.declare_config`) declares every parameter from
this and builds the dataclass from the values; documentation (docs/parameters.md) is
generated from it too. ROS-free.

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
