"""THE node list of the IBVS graph, defined once for the launch files and the runner.

``sim_graph()`` is the whole graph with the simulator (lockstep, sim time); ``onboard_graph()``
is what runs on the vehicle's companion computer, against the autopilot's MAVLink URL. Both
return ``NodeSpec`` records; ``launch/*.launch.py`` turn them into ``launch_ros`` Node actions
and ``ibvs_bringup.runner`` into processes (``--ros-args`` built by ``NodeSpec.ros_args``).
Parameters: each node's code defaults (its config dataclass, :func:`node_configs`), what
``params.yaml`` sets for a deployment (keyed by node name, plus a ``/**`` block for all), and
the per-run overrides here (wiring: URLs, subscriber counts, arming, start, faults).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
import sys
from typing import Any, Sequence

from ibvs_common.core import frames
import numpy as np

CONFIG_PACKAGE = 'ibvs_bringup'
TOOLS_PACKAGE = 'ibvs_harness'     # the recorder and the bag player
PARAMS_FILE_NAME = 'params.yaml'
DEFAULT_MAVLINK_PORT = 14560
CROSSING_LAWS = ('closed', 'intended', 'seed')
ROLES = ('sim', 'onboard', 'tool')

# Names of the per-run parameters (the rest: code defaults and params.yaml). Owned by the node
# packages; collected here so that a rename is one edit.
SIM_INITIAL_OVERRIDE = 'initial_override'    # true: use the two below, not world.yaml's
SIM_INITIAL_POSITION = 'initial_position_I'   # [x, y, z] in the paper frame {I}, m
SIM_INITIAL_YAW = 'initial_yaw'               # rad, {I}
SIM_MIN_IMAGE_SUBSCRIBERS = 'min_image_subscribers'   # frame 0 waits for these per camera
IMAGE_SUBSCRIBERS_PER_CAMERA = 2                # a detector and an optical_flow per camera
BRIDGE_MIN_IMU_SUBSCRIBERS = 'min_imu_subscribers'  # bridge: setpoint stream waits for these
IMU_SUBSCRIBERS = 4                             # both optical_flows, supervisor, controller
SIM_WIND = 'wind_force_map'                   # [fx, fy, fz] in map (ENU), N
SIM_PACING = 'pacing'                         # 'lockstep' | 'realtime' (free-running)
SIM_REAL_TIME_FACTOR = 'real_time_factor'     # free-running: sim s per wall s
MAVLINK_URL = 'mavlink_url'                   # sim: its MAVLink endpoint
BRIDGE_URL = 'url'                            # mavlink_bridge: the autopilot's URL
BRIDGE_ARM_ON_START = 'arm_on_start'          # mavlink_bridge: arm without ibvs/arm (sim only)
CROSSING_LAW = 'crossing_law'                 # force_controller: mode-2 law
SUPERVISOR_AUTO_START = 'auto_start_at_s'     # mode_supervisor: start by itself at this time
VEHICLE_FILE = 'vehicle_file'                 # every node: the vehicle YAML ('' = installed)
# Perception nodes are restarted when they die (launch_ros ``respawn``; the runner with
# backoff): a detector or flow that comes back is an input that comes back. The supervisor,
# controller and bridge are not: their death is handled by the safety policy (no statuses ->
# no forces -> the bridge hands the vehicle back; no bridge -> the autopilot's offboard loss).
# the names of the graph's nodes, in launch order (the sections of params.yaml). In one process
# (ibvs_bringup.composed) a camera's two nodes compute each image in this order, the product a
# mode waits for first: the window detector before the wall flow (IDLE waits for the window
# only), the floor flow before the pad detector (CROSSING waits for the floor flow only, the pad
# is its cue for LANDING: behind a whole-image pad search the flow missed the frame's deadline
# on a third of a core)
ONBOARD_NODE_NAMES = ('window_detector', 'front_optical_flow', 'down_optical_flow',
                      'pad_detector', 'mode_supervisor', 'force_controller', 'mavlink_bridge')
SIM_NODE_NAMES = ('sim',) + ONBOARD_NODE_NAMES
RESPAWN_DELAY_S = 1.0                         # s before the first restart (then doubled)


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph: what to run, under which name, with which parameters."""

    package: str
    executable: str
    name: str
    parameters: tuple = ()          # parameter-file paths (str) and override dicts, in order
    remappings: tuple = ()          # (from, to) pairs
    role: str = 'onboard'           # 'sim' | 'onboard' | 'tool'
    respawn: bool = False           # restart when it dies (launch_ros respawn)

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ValueError(f'node {self.name}: role must be one of {ROLES}, not {self.role!r}')

    def param_files(self) -> list[str]:
        """Return the parameter files, in order."""
        return [p for p in self.parameters if isinstance(p, str)]

    def overrides(self) -> dict:
        """Return the merged override dicts (later ones win)."""
        merged: dict = {}
        for p in self.parameters:
            if isinstance(p, dict):
                merged.update(p)
        return merged

    def ros_args(self) -> list[str]:
        """Return the ``--ros-args`` command-line tail that ``ros2 run`` would be given."""
        args = ['--ros-args', '-r', f'__node:={self.name}']
        for f in self.param_files():
            args += ['--params-file', f]
        for key, value in self.overrides().items():
            args += ['-p', f'{key}:={format_param_value(value)}']
        for src, dst in self.remappings:
            args += ['-r', f'{src}:={dst}']
        return args


@dataclass(frozen=True)
class GraphOptions:
    """Per-run options of the graph (everything else: code defaults and the parameter file)."""

    params_file: str | None = None                  # None: the installed params.yaml
    use_sim_time: bool = True
    mavlink_port: int = DEFAULT_MAVLINK_PORT        # sim graph: UDP port on 127.0.0.1
    mavlink_url: str | None = None                  # onboard graph: the vehicle's MAVLink URL
    initial_position: tuple | None = None           # {I}, m; None: world.yaml's
    initial_yaw: float | None = None                # rad; None: world.yaml's
    wind: tuple | None = None                       # {I}, N (sent in map); None: the file's
    crossing_law: str | None = None                 # None: the file's (or the default)
    auto_start_at_s: float | None = None            # s; None: the file's (off: ibvs/start)
    real_time_factor: float | None = None           # sim graph: free-running at this factor
    #                                                 (None: the file's pacing, lockstep)
    extra_remappings: tuple = field(default_factory=tuple)
    extra_image_subscribers: int = 0                # e.g. 1 for a recorder of the images
    extra_imu_subscribers: int = 0                  # e.g. 1 for a recorder of imu/data
    bridge_overrides: tuple = ()                    # more (name, value) for the bridge
    sim_overrides: tuple = ()                       # more (name, value) for the sim (faults,
    #                                                 the camera model)
    vehicle_file: str | None = None                 # the onboard nodes' vehicle YAML, also the
    #                                                 calibration the sim publishes (None:
    #                                                 params.yaml's)


def format_param_value(value: Any) -> str:
    """Format a parameter override for ``-p name:=value`` (YAML, floats kept as doubles)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(format_param_value(v) for v in value) + ']'
    return str(value)


AMENT_ENV = 'AMENT_PREFIX_PATH'


def ensure_ament_prefix_path(prefix: str = sys.prefix) -> None:
    """Put the install prefix of this Python (the venv) on AMENT_PREFIX_PATH if it is missing.

    ``make install`` installs the packages' share/ into the venv; a user who runs
    ``.venv/bin/runner`` without the Makefile's environment then still finds params.yaml.
    A sourced ROS install (AMENT_PREFIX_PATH set) is left as it is.
    """
    marker = os.path.join(prefix, 'share', 'ament_index', 'resource_index', 'packages',
                          CONFIG_PACKAGE)
    if not os.environ.get(AMENT_ENV) and os.path.exists(marker):
        os.environ[AMENT_ENV] = prefix


def default_params_file(name: str = PARAMS_FILE_NAME) -> str:
    """Return the installed ``share/ibvs_bringup/config/<name>`` (default: params.yaml)."""
    from ament_index_python.packages import get_package_share_directory
    return os.path.join(get_package_share_directory(CONFIG_PACKAGE), 'config', name)


def checked_params_file(path: str | None, node_names: Sequence[str]) -> str:
    """Return the parameter file to give every node; raise ValueError if it cannot be that.

    ``None`` or '' is the installed params.yaml. launch_ros only warns about a file that does
    not exist and then runs every node on its code defaults; a flight stack must not start on
    a typo. Refused: a missing or unreadable file, invalid YAML, and a file that configures
    none of the graph's nodes (neither a ``<node name>: ros__parameters: ...`` section nor a
    ``/**:`` block for every node, as in params.yaml).
    """
    import yaml
    resolved = path or default_params_file()
    try:
        with open(resolved, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise ValueError(f'parameter file {resolved!r} cannot be read ({exc.strerror}): give '
                         f'an existing file as params_file, or none for the installed '
                         f'{PARAMS_FILE_NAME}') from exc
    except yaml.YAMLError as exc:
        raise ValueError(f'parameter file {resolved!r} is not valid YAML: {exc}') from exc
    sections = set(data) if isinstance(data, dict) else set()
    configured = {n for n in node_names
                  if n in sections or f'/{n}' in sections or sections & {'/**', '/*'}}
    if not configured:
        raise ValueError(f'parameter file {resolved!r} configures none of the nodes '
                         f'{sorted(node_names)} (expected "<node name>: ros__parameters:" '
                         f'sections or a "/**:" block, as in the installed '
                         f'{PARAMS_FILE_NAME})')
    return resolved


def sim_mavlink_urls(port: int) -> tuple[str, str]:
    """Return (sim URL, bridge URL) of the lockstep MAVLink link on 127.0.0.1:port."""
    if not 0 < int(port) < 65536:
        raise ValueError(f'MAVLink port {port} out of range')
    return f'udpin:127.0.0.1:{int(port)}', f'udpout:127.0.0.1:{int(port)}'


def _floats(values: Sequence[float], n: int, what: str) -> list[float]:
    out = [float(v) for v in values]
    if len(out) != n:
        raise ValueError(f'{what} needs {n} values, got {len(out)}')
    return out


def _onboard_nodes(params: tuple, common: dict, opts: GraphOptions, mavlink_url: str,
                   bridge: dict | None = None) -> list:
    law = {}
    if opts.crossing_law is not None:
        if opts.crossing_law not in CROSSING_LAWS:
            raise ValueError(f'crossing law must be one of {CROSSING_LAWS}')
        law = {CROSSING_LAW: opts.crossing_law}
    start = {} if opts.auto_start_at_s is None else {
        SUPERVISOR_AUTO_START: float(opts.auto_start_at_s)}
    remap = tuple(opts.extra_remappings)
    if opts.vehicle_file is not None:
        common = {**common, VEHICLE_FILE: str(opts.vehicle_file)}

    def node(package: str, executable: str, name: str, *overrides: dict) -> NodeSpec:
        merged = dict(common)
        for o in overrides:
            merged.update(o)
        return NodeSpec(package, executable, name, params + ((merged,) if merged else ()),
                        remap, 'onboard', respawn=package == 'ibvs_perception')

    return [
        node('ibvs_perception', 'window_detector', 'window_detector'),
        node('ibvs_perception', 'optical_flow', 'front_optical_flow', {'camera': 'front'}),
        node('ibvs_perception', 'optical_flow', 'down_optical_flow', {'camera': 'down'}),
        node('ibvs_perception', 'pad_detector', 'pad_detector'),
        node('ibvs_control', 'mode_supervisor', 'mode_supervisor', start),
        node('ibvs_control', 'force_controller', 'force_controller', law),
        node('ibvs_control', 'mavlink_bridge', 'mavlink_bridge', {
            BRIDGE_URL: mavlink_url,
            BRIDGE_MIN_IMU_SUBSCRIBERS: IMU_SUBSCRIBERS + int(opts.extra_imu_subscribers)},
            bridge or {}, dict(opts.bridge_overrides)),
    ]


def sim_graph(opts: GraphOptions = GraphOptions()) -> list[NodeSpec]:
    """Return the whole graph with the simulator: sim first, then the onboard nodes.

    Every node reads the same ``params.yaml`` (or ``opts.params_file``) as onboard: the flight
    path has no simulator-only waits or timeouts; only the per-run overrides below (MAVLink
    port, initial condition, wind, ...) and ``use_sim_time`` differ.
    """
    params = (checked_params_file(opts.params_file, SIM_NODE_NAMES),)
    sim_url, bridge_url = sim_mavlink_urls(opts.mavlink_port)
    sim_over: dict = {
        MAVLINK_URL: sim_url,
        SIM_MIN_IMAGE_SUBSCRIBERS: (IMAGE_SUBSCRIBERS_PER_CAMERA
                                    + int(opts.extra_image_subscribers))}
    if opts.initial_position is not None or opts.initial_yaw is not None:
        sim_over[SIM_INITIAL_OVERRIDE] = True
    if opts.initial_position is not None:
        sim_over[SIM_INITIAL_POSITION] = _floats(opts.initial_position, 3, 'initial position')
    if opts.initial_yaw is not None:
        sim_over[SIM_INITIAL_YAW] = float(opts.initial_yaw)
    if opts.wind is not None:
        wind_map = frames.vec_I_to_map(np.array(_floats(opts.wind, 3, 'wind')))
        sim_over[SIM_WIND] = [float(x) + 0.0 for x in wind_map]
    if opts.real_time_factor is not None:
        rtf = float(opts.real_time_factor)
        if not 0.0 < rtf <= 10.0:
            raise ValueError(f'real-time factor must be in (0, 10], got {rtf}')
        sim_over[SIM_PACING], sim_over[SIM_REAL_TIME_FACTOR] = 'realtime', rtf
    if opts.vehicle_file is not None:
        sim_over[VEHICLE_FILE] = str(opts.vehicle_file)
    sim_over.update(dict(opts.sim_overrides))
    common = {'use_sim_time': True} if opts.use_sim_time else {}
    sim = NodeSpec('ibvs_sim', 'sim', 'sim', params + (sim_over,), tuple(opts.extra_remappings),
                   'sim')
    # the scenario asks the bridge to arm (on a vehicle only the ibvs/arm service does)
    return [sim] + _onboard_nodes(params, common, opts, bridge_url,
                                  {BRIDGE_ARM_ON_START: True})


PX4_SIM_NAME = 'px4_sim'                      # px4-sih mode: the renderer of PX4's truth
PX4_SIM_STATE_URL = 'state_url'               # px4_sim: where PX4 SIH sends its ground truth
PX4_SIH_NODE_NAMES = (PX4_SIM_NAME,) + ONBOARD_NODE_NAMES


def px4_urls(instance: int) -> tuple[str, str]:
    """Return (px4_sim's ground-truth URL, the bridge's URL) of PX4 SITL instance ``instance``.

    PX4 SIH sends HIL_STATE_QUATERNION to 127.0.0.1:19410 + i and the companion link to
    127.0.0.1:14540 + i (the documented PX4 companion URL is ``udpin`` on that port).
    """
    i = int(instance)
    if not 0 <= i <= 9:
        raise ValueError(f'PX4 instance must be 0-9, got {instance}')
    return f'udpin:127.0.0.1:{19410 + i}', f'udpin:127.0.0.1:{14540 + i}'


def px4_sih_graph(opts: GraphOptions, instance: int, px4_sim_overrides: dict | None = None
                  ) -> list[NodeSpec]:
    """Return the whole graph against PX4 SIH: px4_sim (renderer), then the onboard nodes.

    The onboard nodes run exactly as on a vehicle: the shipped params.yaml, the system clock
    (``opts.use_sim_time`` must be False: PX4 runs in real time), no auto start (the scenario
    calls ibvs/start), and the bridge arms only on ibvs/arm (not asked: the scenario harness,
    acting as the pilot's GCS, has armed PX4 and taken off).
    """
    if opts.use_sim_time:
        raise ValueError('the px4-sih graph runs on the system clock: use_sim_time false')
    params = (checked_params_file(opts.params_file, PX4_SIH_NODE_NAMES),)
    state_url, bridge_url = px4_urls(instance)
    over: dict = {PX4_SIM_STATE_URL: state_url}
    if opts.initial_position is not None:
        over[SIM_INITIAL_OVERRIDE] = True
        over[SIM_INITIAL_POSITION] = _floats(opts.initial_position, 3, 'initial position')
    over.update(px4_sim_overrides or {})
    sim = NodeSpec('ibvs_sim', 'px4_sim', PX4_SIM_NAME, params + (over,),
                   tuple(opts.extra_remappings), 'sim')
    return [sim] + _onboard_nodes(params, {}, opts, bridge_url)


def onboard_graph(opts: GraphOptions = GraphOptions(use_sim_time=False)) -> list[NodeSpec]:
    """Return the onboard nodes only, talking to the vehicle at ``opts.mavlink_url``."""
    params = (checked_params_file(opts.params_file, ONBOARD_NODE_NAMES),)
    url = opts.mavlink_url or sim_mavlink_urls(opts.mavlink_port)[1]
    common = {'use_sim_time': True} if opts.use_sim_time else {}
    return _onboard_nodes(params, common, opts, url)


def node_configs() -> dict[str, type]:
    """Return the config dataclass of every node of the graphs by node name, in graph order.

    ``sim``, ``px4_sim`` (the sim of the PX4 SIH graph), then ``ONBOARD_NODE_NAMES``. Each
    dataclass holds the node's parameters: default, description, range, unit
    (``ibvs_common.core.params``). Imported on call: the node list itself loads no node code.
    """
    from ibvs_control.config import ForceControllerNodeConfig, ModeSupervisorNodeConfig
    from ibvs_control.mavlink.config import MavlinkBridgeNodeConfig
    from ibvs_perception.config import (OpticalFlowNodeConfig, PadDetectorNodeConfig,
                                        WindowDetectorNodeConfig)
    from ibvs_sim.config import Px4SimNodeConfig, SimNodeConfig
    configs = {'sim': SimNodeConfig, PX4_SIM_NAME: Px4SimNodeConfig,
               'window_detector': WindowDetectorNodeConfig,
               'pad_detector': PadDetectorNodeConfig,
               'front_optical_flow': OpticalFlowNodeConfig,
               'down_optical_flow': OpticalFlowNodeConfig,
               'mode_supervisor': ModeSupervisorNodeConfig,
               'force_controller': ForceControllerNodeConfig,
               'mavlink_bridge': MavlinkBridgeNodeConfig}
    order = SIM_NODE_NAMES[:1] + (PX4_SIM_NAME,) + ONBOARD_NODE_NAMES
    if set(order) != set(configs):
        raise RuntimeError(f'node_configs out of date: {sorted(set(order) ^ set(configs))}')
    return {name: configs[name] for name in order}


def tool_node(executable: str, name: str, parameters: tuple = (),
              remappings: tuple = ()) -> NodeSpec:
    """Return a tool node of ibvs_harness (recorder, bag player), not part of the flight graph."""
    return NodeSpec(TOOLS_PACKAGE, executable, name, parameters, remappings, 'tool')
