"""The controller's and the supervisor's core configurations from params.yaml, as the nodes.

For the ROS-free feature-level loop (``run_scenario --feature-level``, the campaigns).

force_controller: its gains, ``crossing_law``, ``disturbance_law`` and their groups; r_w from
its ``window_layout_file`` and the group sizes from its ``pad_layout_file`` ('' = installed).
mode_supervisor: its core thresholds (timing and file parameters belong to the node), r_w and
the group sizes from its own files. One place, so that a feature-level run flies what the
nodes would fly.
"""
from __future__ import annotations

import dataclasses

from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
from ibvs_control.core.controller import ControllerConfig
from ibvs_control.core.supervisor import SupervisorConfig


def section(params: dict, node: str) -> dict:
    """Return the ``ros__parameters`` of ``node`` in a params.yaml dict (a copy; {} if none)."""
    return dict((params.get(node) or {}).get('ros__parameters') or {})


def controller_config(params: dict, overrides: tuple = ()) -> ControllerConfig:
    """Return the force controller's ControllerConfig; ``overrides``: (name, value) pairs.

    Raises ValueError (GainError, ConfigError) for a bad value or an unknown override.
    """
    p = section(params, 'force_controller')
    for name, value in overrides:
        if name not in p:
            raise ValueError(f'override {name!r}: no such force_controller parameter')
        p[name] = value
    window = load_window_layout(p.get('window_layout_file') or None)
    pad = load_pad_layout(p.get('pad_layout_file') or None)
    vehicle = load_vehicle(p.get('vehicle_file') or None)
    return ControllerConfig.from_params(p, vehicle, window.width, pad)


def supervisor_config(params: dict) -> SupervisorConfig:
    """Return the mode supervisor's SupervisorConfig (core thresholds, r_w, group sizes)."""
    p = section(params, 'mode_supervisor')
    core = {f.name for f in dataclasses.fields(SupervisorConfig)}
    values = {k: v for k, v in p.items() if k in core}
    values['r_w'] = load_window_layout(p.get('window_layout_file') or None).width
    pad = load_pad_layout(p.get('pad_layout_file') or None)
    values['group_half_sides'] = {g.name: g.c for g in pad.groups}
    return SupervisorConfig.from_params(values)
