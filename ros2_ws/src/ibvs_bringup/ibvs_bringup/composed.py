"""The onboard nodes of graph.py in ONE process (like a component container).

Same node classes, names, parameter files and per-run overrides as the separate processes of
``graph.onboard_graph`` (the node list comes from there); only the process layout differs: one
Python interpreter, one DDS participant and rclpy ``EventsExecutor``s (one for the
perception nodes, one for the control nodes, below), so that the per-process and per-wake-up
costs are paid once (docs/performance.md measures the layouts). Python runs one thread at a
time: the per-frame work (detectors, flows, supervisor, controller) shares one core, OpenCV's
own threads and the interpreter's releases aside. The bridge's 100 Hz imu/data
reaches the nodes beside it in process, without DDS (``ibvs_common.intra_process``); it is
still published for everything else.

A node whose construction fails (bad parameter) ends the process with status 1, like the
node's own ``main``. A node cannot die alone here: the process is the unit that a supervisor
(systemd, launch) restarts.

``--nodes a,b`` runs only those onboard nodes (by name), so that the graph can also be
split into a few processes, e.g. one per camera plus one for control (GROUPS), each one
container of several nodes (docs/performance.md measures it).

Two executors: the control nodes (supervisor, controller, bridge) spin on an executor of
their own in a second thread, so that a product, a status or a force does not wait in one
executor's queue behind the images that arrived before it (on a slow computer the first
forces of a new mode came too late for the bridge's hold; docs/performance.md "The onboard
graph on a vehicle's sensors and computer"). ``--single-executor``: every node on one.

Usage: ``composed [--nodes NAMES] [--mavlink-url URL] [--params-file FILE] [--use-sim-time]
[--no-intra-process] [--single-executor] [--specs FILE] [--ros-args ...]`` (``--ros-args``
apply to every node).
Each node gets its own command-line tail (``NodeSpec.ros_args``: parameter files, overrides,
remappings), as its own process would. ``--specs``: the node list of a run, written by the
runner (``ProcessRunner.start_composed``), e.g. the onboard nodes of a sim or PX4 SIH run.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import sys
from typing import TYPE_CHECKING

from ibvs_bringup import graph

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.node import Node

#: a split of the onboard graph into three containers: one per camera, one for control
GROUPS = {'front': ('window_detector', 'front_optical_flow'),
          'down': ('pad_detector', 'down_optical_flow'),
          'control': ('mode_supervisor', 'force_controller', 'mavlink_bridge')}

NODE_CLASSES = {
    ('ibvs_perception', 'window_detector'):
        'ibvs_perception.window_detector_node:WindowDetectorNode',
    ('ibvs_perception', 'pad_detector'): 'ibvs_perception.pad_detector_node:PadDetectorNode',
    ('ibvs_perception', 'optical_flow'): 'ibvs_perception.optical_flow_node:OpticalFlowNode',
    ('ibvs_control', 'mode_supervisor'):
        'ibvs_control.mode_supervisor_node:ModeSupervisorNode',
    ('ibvs_control', 'force_controller'):
        'ibvs_control.force_controller_node:ForceControllerNode',
    ('ibvs_control', 'mavlink_bridge'): 'ibvs_control.mavlink_bridge_node:MavlinkBridgeNode',
}


def node_class(package: str, executable: str) -> type[Node]:
    """Import the node class of ``package``/``executable``."""
    module, name = NODE_CLASSES[(package, executable)].split(':')
    return getattr(__import__(module, fromlist=[name]), name)


def build_nodes(specs: list, context: Context, intra_process: bool = True,
                user_ros_args: tuple = ()) -> list:
    """Instantiate every spec's node class with its name and per-run overrides.

    ``user_ros_args`` (``--ros-args ...`` of the command line) follow each node's own tail, so
    that a user's ``-p name:=value`` wins over the parameter file as it does for a node's own
    process (rcl gives a node's own arguments precedence over the global ones: as global
    arguments only, the file's value would silently win). rcl reads the parameter file of the
    tail as for a process: the node's section and the ``/**`` block (params.yaml keeps it
    last: rcl files a ``-p`` under ``/**``, so the tail's and the user's ``-p`` win over the
    sections).

    When the MAVLink bridge is among them, its imu/data goes to the others in process
    (``ibvs_common.intra_process``: every node class with an ``imu_local`` argument takes it
    from there instead of through DDS, as rclcpp's intra-process communication would). Every
    node class with a ``camera_inputs`` argument shares one subscription per camera with the
    others (``SharedCameraInputs``). ``intra_process=False`` gives each node its own.
    """
    from ibvs_common.intra_process import IntraProcessTopic
    from ibvs_perception.camera_input import SharedCameraInputs
    classes = [node_class(spec.package, spec.executable) for spec in specs]
    with_bridge = any(spec.executable == 'mavlink_bridge' for spec in specs)
    imu_local = IntraProcessTopic('imu/data') if with_bridge and intra_process else None
    shared = {'imu_local': imu_local,
              'camera_inputs': SharedCameraInputs() if intra_process else None}
    nodes = []
    for spec, cls in zip(specs, classes):
        accepted = inspect.signature(cls).parameters
        extra = {k: v for k, v in shared.items() if v is not None and k in accepted}
        # the node's own command-line tail, as its process would get it: parameter files,
        # overrides and remappings apply to this node only
        nodes.append(cls(node_name=spec.name, context=context,
                         cli_args=list(spec.ros_args()) + list(user_ros_args), **extra))
    return nodes


def executor_groups(nodes: list, control_thread: bool) -> list:
    """Return the nodes by executor: all on one, or the control nodes on a second one."""
    if not control_thread:
        return [nodes]
    control = [n for n in nodes if n.get_name() in GROUPS['control']]
    return [[n for n in nodes if n not in control], control]


def write_specs(specs: list, path: str) -> None:
    """Write node specs as JSON for ``composed --specs`` (the runner's composed layout)."""
    with open(path, 'w') as f:
        json.dump([dataclasses.asdict(s) for s in specs], f, indent=1)


def read_specs(path: str) -> list:
    """Read the node specs written by :func:`write_specs`; ValueError if malformed."""
    try:
        with open(path) as f:
            raw = json.load(f)
        return [graph.NodeSpec(**{**d, 'parameters': tuple(d['parameters']),
                                  'remappings': tuple(tuple(r) for r in d['remappings'])})
                for d in raw]
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise ValueError(f'bad node spec file {path}: {exc}') from exc


def main(argv: list | None = None) -> int:
    """Run the onboard graph in this process until Ctrl-C or SIGTERM."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import remove_ros_args
    from ibvs_common.spin import spin_guarded_groups
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--mavlink-url', default=None, help="the autopilot's MAVLink URL")
    p.add_argument('--params-file', default=None, help='default: installed params.yaml')
    p.add_argument('--use-sim-time', action='store_true')
    p.add_argument('--nodes', default='', help='comma-separated onboard node names (default: '
                   'all of them)')
    p.add_argument('--no-intra-process', action='store_true',
                   help='imu/data and the images through DDS to every node, as between '
                   'processes')
    p.add_argument('--single-executor', action='store_true',
                   help='every node on one executor in one thread (by default the control '
                   'nodes, GROUPS["control"], have an executor of their own in a second '
                   'thread: their callbacks do not queue behind image processing)')
    p.add_argument('--specs', default=None, help='JSON node specs (write_specs) instead of the '
                   'onboard graph of the options above: how the runner composes a run')
    a = p.parse_args(remove_ros_args(['composed'] + argv)[1:])
    graph.ensure_ament_prefix_path()
    if a.specs:
        try:
            specs = read_specs(a.specs)
        except ValueError as exc:
            print(f'composed: {exc}', file=sys.stderr)
            return 2
    else:
        specs = graph.onboard_graph(graph.GraphOptions(
            params_file=a.params_file, use_sim_time=a.use_sim_time, mavlink_url=a.mavlink_url))
    if a.nodes:
        wanted = [n for n in a.nodes.split(',') if n]
        unknown = sorted(set(wanted) - {s.name for s in specs})
        if unknown:
            print(f'composed: unknown node name(s) {unknown}; onboard nodes: '
                  f'{[s.name for s in specs]}', file=sys.stderr)
            return 2
        specs = [s for s in specs if s.name in wanted]
    user_ros_args = argv[argv.index('--ros-args'):] if '--ros-args' in argv else []
    rclpy.init(args=['composed'] + user_ros_args)
    nodes = []
    try:
        nodes = build_nodes(specs, rclpy.get_default_context(),
                            intra_process=not a.no_intra_process,
                            user_ros_args=tuple(user_ros_args))
        spin_guarded_groups(executor_groups(nodes, control_thread=not a.single_executor))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:          # a bad parameter of one node: never fly with it
        rclpy.logging.get_logger('composed').fatal(f'refusing to start: {exc}')
        return 1
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
