"""The controller's and the supervisor's core configurations from a parameter file, as the nodes.

For the ROS-free feature-level loop (``run_scenario --feature-level``, the campaigns). Each
node's parameters are read as the node reads them (``ibvs_common.core.params.node_values``):
its config dataclass's defaults (``ForceControllerNodeConfig``, ``ModeSupervisorNodeConfig``),
then the file's ``/**`` block and the node's section; the core configuration is then built
by the same dataclass methods as in the node. force_controller: its gains, laws and their
groups, r_w from its ``window_layout_file``, the group sizes from its ``pad_layout_file`` and
mass and camera mounts from its ``vehicle_file`` ('' = installed). mode_supervisor: its core
thresholds, r_w and the group sizes from its own files. One place, so that a feature-level
run flies what the nodes would fly.
"""
from __future__ import annotations

from typing import Any

from ibvs_common.core import params
from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
from ibvs_control.config import ForceControllerNodeConfig, ModeSupervisorNodeConfig
from ibvs_control.core.controller import ControllerConfig
from ibvs_control.core.supervisor import SupervisorConfig

CONTROLLER_NODE = 'force_controller'
SUPERVISOR_NODE = 'mode_supervisor'


def checked_overrides(cls: type, overrides: tuple, node: str) -> dict[str, Any]:
    """Return ``overrides`` ((name, value) pairs) as a dict; ValueError for one ``cls`` refuses.

    Each name must be a parameter of the node (its config dataclass), each value of its type
    (an integer is taken for a double) and within its range.
    """
    values = dict(overrides)
    unknown = sorted(set(values) - set(params.parameters(cls)))
    if unknown:
        raise ValueError(f'override {", ".join(map(repr, unknown))}: no such {node} parameter')
    params.check(cls, values, int_as_double=True)
    return values


def controller_node_config(data: Any, overrides: tuple = ()) -> ForceControllerNodeConfig:
    """Return the force controller's node config from a loaded parameter file + overrides."""
    cls = ForceControllerNodeConfig
    values = params.node_values(cls, data, CONTROLLER_NODE)
    values.update(checked_overrides(cls, overrides, CONTROLLER_NODE))
    return params.build(cls, values)


def controller_config(data: Any, overrides: tuple = ()) -> ControllerConfig:
    """Return the force controller's ControllerConfig; ``overrides``: (name, value) pairs.

    ``data``: a loaded parameter file (``yaml.safe_load`` of params.yaml; None or {}: the code
    defaults). Raises ValueError (GainError, ConfigError) for a bad value or an unknown
    override.
    """
    cfg = controller_node_config(data, overrides)
    window = load_window_layout(cfg.window_layout_file or None)
    pad = load_pad_layout(cfg.pad_layout_file or None)
    vehicle = load_vehicle(cfg.vehicle_file or None)
    return cfg.controller_config(vehicle, window.width, pad)


def supervisor_config(data: Any) -> SupervisorConfig:
    """Return the mode supervisor's SupervisorConfig (core thresholds, r_w, group sizes)."""
    cls = ModeSupervisorNodeConfig
    cfg = params.build(cls, params.node_values(cls, data, SUPERVISOR_NODE))
    window = load_window_layout(cfg.window_layout_file or None)
    return cfg.supervisor_config(window.width, load_pad_layout(cfg.pad_layout_file or None))


def node_config(cls: type, data: Any, node: str) -> Any:
    """Return config dataclass ``cls`` of node ``node`` as it reads a loaded parameter file."""
    return params.build(cls, params.node_values(cls, data, node))
