"""Whole IBVS graph with the simulator (lockstep MAVLink, sim time): nodes from graph.py.

Usage: ros2 launch ibvs_bringup sim.launch.py [mavlink_port:=14560] [crossing_law:=closed]
       [params_file:=/path/params.yaml]
"""
from ibvs_bringup import graph, parent_death
from ibvs_common.dds_profile import dds_env_overrides
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration as Lc
from launch_ros.actions import Node


def _nodes(context):
    get = context.perform_substitution
    params = get(Lc('params_file')) or None
    law = get(Lc('crossing_law')) or None
    opts = graph.GraphOptions(params_file=params, use_sim_time=True,
                              mavlink_port=int(get(Lc('mavlink_port'))), crossing_law=law)
    env = dds_env_overrides()
    return [Node(package=s.package, executable=s.executable, name=s.name,
                 parameters=list(s.parameters), remappings=list(s.remappings), output='screen',
                 additional_env=env, prefix=parent_death.launch_prefix(), respawn=s.respawn,
                 respawn_delay=graph.RESPAWN_DELAY_S)
            for s in graph.sim_graph(opts)]


def generate_launch_description():
    """Declare the arguments and build the node list of graph.sim_graph()."""
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value='',
                              description='parameter file (empty: installed params.yaml)'),
        DeclareLaunchArgument('mavlink_port', default_value=str(graph.DEFAULT_MAVLINK_PORT),
                              description='UDP port of the sim <-> bridge MAVLink link'),
        DeclareLaunchArgument('crossing_law', default_value='',
                              description='closed | intended | seed (empty: the parameter '
                                          "file's, else the code default)"),
        OpaqueFunction(function=_nodes),
    ])
