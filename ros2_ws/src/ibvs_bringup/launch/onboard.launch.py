"""Onboard IBVS nodes only (no sim), against a vehicle's MAVLink URL: nodes from graph.py.

Usage: ros2 launch ibvs_bringup onboard.launch.py [mavlink_url:=udpin:0.0.0.0:14540]
[layout:=composed|grouped|processes]
(default: PX4's companion port; ArduPilot: udpin on its SERIALn UDP port, or a serial port in
pymavlink's format, e.g. /dev/ttyUSB0,921600; docs/mavlink.md). ``layout``: the onboard nodes
in one process (``composed``, the default: ibvs_bringup.composed, respawned as a whole), in a
container per camera and one for control (``grouped``: composed.GROUPS, each respawned as a
whole; for two or more cores), or a process each (``processes``: the perception nodes
respawned alone); the same as ``runner onboard --layout`` (runner.LAYOUTS, docs/onboard.md).
"""
import os
import tempfile

from ibvs_bringup import composed, graph, parent_death
from ibvs_bringup.runner import DEFAULT_LAYOUT, LAYOUTS
from ibvs_common.dds_profile import dds_env_overrides
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration as Lc
from launch_ros.actions import Node

DEFAULT_MAVLINK_URL = 'udpin:0.0.0.0:14540'     # PX4's onboard (companion) MAVLink port


def _nodes(context):
    get = context.perform_substitution
    params = get(Lc('params_file')) or None
    law = get(Lc('crossing_law')) or None
    use_sim_time = get(Lc('use_sim_time')).lower() in ('1', 'true', 'yes')
    layout = get(Lc('layout'))
    if layout not in LAYOUTS:
        raise ValueError(f'layout must be one of {LAYOUTS}, got {layout!r}')
    opts = graph.GraphOptions(params_file=params, use_sim_time=use_sim_time,
                              mavlink_url=get(Lc('mavlink_url')), crossing_law=law)
    env = dds_env_overrides()
    prefix = parent_death.launch_prefix()     # each node ends with ros2 launch, as with the runner
    specs = graph.onboard_graph(opts)
    containers = _containers(layout, specs)
    in_containers = {s.name for members in containers.values() for s in members}
    nodes = []
    for group, members in containers.items():   # a container's node list in a file
        fd, path = tempfile.mkstemp(prefix=f'ibvs-{group}-', suffix='.json')
        os.close(fd)
        composed.write_specs(members, path)
        nodes.append(Node(package='ibvs_bringup', executable='composed',
                          arguments=['--specs', path], output='screen', additional_env=env,
                          prefix=prefix, respawn=True, respawn_delay=graph.RESPAWN_DELAY_S))
    return nodes + [Node(package=s.package, executable=s.executable, name=s.name,
                         parameters=list(s.parameters), remappings=list(s.remappings),
                         output='screen', additional_env=env, prefix=prefix,
                         respawn=s.respawn, respawn_delay=graph.RESPAWN_DELAY_S)
                    for s in specs if s.name not in in_containers]


def _containers(layout: str, specs: list) -> dict:
    """Return the composed containers of ``layout``: name -> their node specs (graph order)."""
    if layout == 'composed':
        return {'onboard': specs}
    if layout == 'grouped':
        groups = {group: [s for s in specs if s.name in names]
                  for group, names in composed.GROUPS.items()}
        return {group: members for group, members in groups.items() if members}
    return {}                       # processes: a process per node


def generate_launch_description():
    """Declare the arguments and build the node list of graph.onboard_graph()."""
    return LaunchDescription([
        DeclareLaunchArgument('mavlink_url', default_value=DEFAULT_MAVLINK_URL,
                              description="the autopilot's MAVLink URL (pymavlink format)"),
        DeclareLaunchArgument('params_file', default_value='',
                              description='parameter file (empty: installed params.yaml)'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        DeclareLaunchArgument('crossing_law', default_value='',
                              description='closed | intended | seed (empty: the parameter '
                                          "file's, else the code default)"),
        DeclareLaunchArgument('layout', default_value=DEFAULT_LAYOUT['onboard'],
                              description='composed (one process) | grouped (a container per '
                                          'camera, one for control) | processes (one per '
                                          'node)'),
        OpaqueFunction(function=_nodes),
    ])
