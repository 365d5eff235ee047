"""Start the graph of ``graph.py`` as separate processes, where launch_ros is not available.

Each node runs as ``<resolved executable> --ros-args -r __node:=<name> --params-file ... -p ...
-r from:=to`` (``NodeSpec.ros_args``), in its own process group, with the caller's environment
(ROS_DOMAIN_ID, discovery range, AMENT_PREFIX_PATH pass through). ``ProcessRunner`` stops every
process it started on exit, Ctrl-C or SIGTERM (SIGINT, then SIGTERM, then SIGKILL, each with a
timeout) and reports a process that died: name, exit code and its last stderr lines. If the
runner itself is killed, every process it started is sent SIGTERM by the kernel
(``parent_death``): the graph never runs on without its runner.

As on a vehicle, the graph keeps running when a node dies: ``ProcessRunner.supervise`` restarts
the nodes marked ``respawn`` (the perception nodes, graph.py) after ``RESPAWN_DELAY_S``, doubled
at each restart up to ``RESPAWN_MAX_DELAY_S`` and reset once a node has run for
``RESPAWN_RESET_S``; the others stay down and the safety policy acts on their silence, exactly
as with ``ros2 launch`` (launch_ros ``respawn``).

Layouts (``LAYOUTS``): the onboard nodes as one composed process (``ibvs_bringup.composed``,
the onboard default: measured cheaper and faster on this machine, docs/performance.md) or as a
process each (the sim graph's default, and what node-kill tests need). Composed, a node cannot
die alone: the whole process is respawned with the same backoff, bridge included; the new
bridge stays in standby (it engages only on the supervisor's switch out of IDLE), while the
autopilot's own offboard-loss failsafe has taken the vehicle (docs/mavlink.md).
"""
from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass, field
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from types import FrameType
from typing import Iterable, NoReturn

from ibvs_bringup import graph, parent_death
from ibvs_bringup.ros2run import command_for
from ibvs_common.dds_profile import dds_env_overrides

STDERR_TAIL_LINES = 20
COMPOSED_NAME = 'onboard'     # process (and log) name of the composed onboard nodes
# the onboard nodes' process layouts: one composed process; a composed container per camera
# and one for control (composed.GROUPS; processes named COMPOSED_NAME_<group>); a process each
LAYOUTS = ('composed', 'grouped', 'processes')
DEFAULT_LAYOUT = {'onboard': 'composed', 'sim': 'processes'}
RESPAWN_MAX_DELAY_S = 16.0    # s, longest wait before a restart
RESPAWN_RESET_S = 30.0        # s of running that resets the backoff


def container_name(group: str) -> str:
    """Return the process (and log) name of composed.GROUPS' ``group`` in the grouped layout."""
    return f'{COMPOSED_NAME}_{group}'


def process_names(node: str) -> tuple:
    """Return the process names that may hold ``node``: its own, composed, its group's."""
    from ibvs_bringup.composed import GROUPS
    return (node, COMPOSED_NAME) + tuple(container_name(g) for g, names in GROUPS.items()
                                         if node in names)


@dataclass(frozen=True)
class DeadProcess:
    """A process that exited on its own while the graph was supposed to run."""

    name: str
    returncode: int
    stderr_tail: tuple

    def report(self) -> str:
        """Return a human-readable report of the death."""
        tail = '\n'.join('    ' + line for line in self.stderr_tail) or '    (no stderr)'
        return f'node {self.name!r} died with exit code {self.returncode}; last stderr:\n{tail}'


@dataclass
class _Respawn:
    """Restart bookkeeping of one ``respawn`` node (monotonic seconds)."""

    started: float = field(default_factory=time.monotonic)
    restarts: int = 0
    delay: float = 0.0
    due: float | None = None


class _Child:
    """One started process, its stderr tail and optional log file."""

    def __init__(self, name: str, argv: list, env: dict, log_path: str | None,
                 append: bool = False) -> None:
        self.name = name
        self.argv = argv
        self.tail: collections.deque = collections.deque(maxlen=STDERR_TAIL_LINES)
        self._log = open(log_path, 'a' if append else 'w', encoding='utf-8') \
            if log_path else None
        self.proc = subprocess.Popen(
            parent_death.wrap(argv), env=env, stdin=subprocess.DEVNULL,
            stdout=self._log if self._log else subprocess.DEVNULL,
            stderr=subprocess.PIPE, process_group=0)
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()

    def _read_stderr(self) -> None:
        for raw in iter(self.proc.stderr.readline, b''):
            line = raw.decode('utf-8', 'replace').rstrip('\n')
            self.tail.append(line)
            if self._log:
                try:
                    self._log.write(line + '\n')
                    self._log.flush()
                except ValueError:   # closed at stop
                    return

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        self._reader.join(timeout=1.0)
        if self.proc.stderr:
            self.proc.stderr.close()
        if self._log:
            self._log.close()


class ProcessRunner:
    """Start named processes, watch them, and stop them all (also as a context manager)."""

    def __init__(self, env: dict | None = None, log_dir: str | None = None,
                 stop_timeouts: tuple = (5.0, 3.0, 2.0)) -> None:
        # default: the caller's environment plus the project's DDS profile (graph.py)
        self.env = {**os.environ, **dds_env_overrides()} if env is None else dict(env)
        self.log_dir = log_dir
        self.stop_timeouts = stop_timeouts     # after SIGINT, after SIGTERM, after SIGKILL
        self.children: list[_Child] = []
        self._reported: set = set()
        self._respawn: dict[str, _Respawn] = {}
        if log_dir:
            os.makedirs(log_dir, exist_ok=True)

    def start(self, name: str, argv: list, respawn: bool = False) -> None:
        """Start ``argv`` as process ``name`` in a new process group."""
        log = os.path.join(self.log_dir, f'{name}.log') if self.log_dir else None
        self.children.append(_Child(name, list(argv), self.env, log))
        if respawn:
            self._respawn[name] = _Respawn()

    def start_node(self, spec: graph.NodeSpec) -> None:
        """Start one node of the graph the way ``ros2 run`` would."""
        self.start(spec.name, command_for(spec.package, spec.executable, spec.ros_args()),
                   respawn=spec.respawn)

    def start_composed(self, specs: list, name: str = COMPOSED_NAME,
                       respawn: bool = False) -> None:
        """Start ``specs`` as one process (ibvs_bringup.composed, one executor).

        The specs go through a JSON file next to the logs (or a temporary one). ``respawn``:
        restart the whole process with the perception nodes' backoff when it dies.
        """
        from ibvs_bringup.composed import write_specs
        if self.log_dir:
            path = os.path.join(self.log_dir, f'{name}.specs.json')
        else:
            fd, path = tempfile.mkstemp(prefix='composed-', suffix='.json')
            os.close(fd)
        write_specs(list(specs), path)
        self.start(name, [sys.executable, '-m', 'ibvs_bringup.composed', '--specs', path],
                   respawn=respawn)

    def start_layout(self, specs: list, layout: str, respawn_composed: bool = False) -> None:
        """Start ``specs``: a process each, or the onboard ones in one or a few containers.

        ``grouped``: a container per group of composed.GROUPS that has nodes in ``specs``
        (named by :func:`container_name`); an onboard node of no group gets its own process.
        """
        if layout not in LAYOUTS:
            raise ValueError(f'layout must be one of {LAYOUTS}, got {layout!r}')
        onboard = [s for s in specs if s.role == 'onboard']
        if layout == 'composed':
            self.start_graph([s for s in specs if s.role != 'onboard'])
            self.start_composed(onboard, respawn=respawn_composed)
        elif layout == 'grouped':
            from ibvs_bringup.composed import GROUPS
            grouped = {name for names in GROUPS.values() for name in names}
            self.start_graph([s for s in specs if s.role != 'onboard' or s.name not in grouped])
            for group, names in GROUPS.items():
                members = [s for s in onboard if s.name in names]
                if members:
                    self.start_composed(members, name=container_name(group),
                                        respawn=respawn_composed)
        else:
            self.start_graph(specs)

    def kill(self, name: str) -> str:
        """SIGKILL the process ``name`` (fault injection); return its name."""
        child = next(c for c in self.children if c.name == name)
        child.signal(signal.SIGKILL)
        child.proc.wait(timeout=5.0)
        return name

    def supervise(self, now: float | None = None) -> list[str]:
        """Restart the dead ``respawn`` nodes whose backoff has passed; return what happened.

        Deaths are reported once each (as by :meth:`dead`); call it periodically.
        """
        now = time.monotonic() if now is None else now
        events = [d.report() + ('' if d.name in self._respawn else ' (not restarted)')
                  for d in self.dead()]
        for i, c in enumerate(self.children):
            state = self._respawn.get(c.name)
            if state is None or c.proc.poll() is None:
                continue
            if state.due is None:                     # it just died: schedule the restart
                if state.restarts == 0 or now - state.started >= RESPAWN_RESET_S:
                    state.delay = graph.RESPAWN_DELAY_S
                else:
                    state.delay = min(2.0 * state.delay, RESPAWN_MAX_DELAY_S)
                state.due = now + state.delay
                events.append(f'node {c.name!r} restarts in {state.delay:.1f} s')
            elif now >= state.due:
                c.close()
                log = os.path.join(self.log_dir, f'{c.name}.log') if self.log_dir else None
                self.children[i] = _Child(c.name, c.argv, self.env, log, append=True)
                self._reported.discard(c.name)
                state.restarts += 1
                state.started, state.due = now, None
                events.append(f'node {c.name!r} restarted ({state.restarts} so far)')
        return events

    def start_graph(self, specs: Iterable[graph.NodeSpec]) -> None:
        """Start every node of ``specs``."""
        for spec in specs:
            self.start_node(spec)

    def dead(self) -> list[DeadProcess]:
        """Return processes that exited since the last call (each reported once)."""
        out = []
        for c in self.children:
            rc = c.proc.poll()
            if rc is not None and c.name not in self._reported:
                self._reported.add(c.name)
                c._reader.join(timeout=0.5)
                out.append(DeadProcess(c.name, rc, tuple(c.tail)))
        return out

    def running(self) -> list[str]:
        """Return the names of the processes still running."""
        return [c.name for c in self.children if c.proc.poll() is None]

    def stop(self) -> dict:
        """Stop every process (SIGINT, SIGTERM, SIGKILL with timeouts); return exit codes."""
        for sig, timeout in zip((signal.SIGINT, signal.SIGTERM, signal.SIGKILL),
                                self.stop_timeouts):
            alive = [c for c in self.children if c.proc.poll() is None]
            if not alive:
                break
            for c in alive:
                c.signal(sig)
            deadline = time.monotonic() + timeout
            for c in alive:
                try:
                    c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for c in self.children:
            c.close()
        return {c.name: c.proc.poll() for c in self.children}

    def __enter__(self) -> 'ProcessRunner':
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class Terminated(Exception):
    """SIGTERM received (raised in the main thread so that finally blocks run)."""


def raise_on_sigterm() -> None:
    """Turn SIGTERM into a ``Terminated`` exception in the main thread."""
    def handler(signum: int, frame: FrameType | None) -> NoReturn:
        raise Terminated()
    signal.signal(signal.SIGTERM, handler)


def options_from_args(args: argparse.Namespace) -> graph.GraphOptions:
    """Build GraphOptions from the common command-line options."""
    return graph.GraphOptions(
        params_file=args.params_file, use_sim_time=args.graph == 'sim',
        mavlink_port=args.mavlink_port, mavlink_url=args.mavlink_url,
        initial_position=tuple(args.initial_position) if args.initial_position else None,
        wind=tuple(args.wind) if args.wind else None, crossing_law=args.crossing_law)


def add_graph_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``GraphOptions`` to ``parser``."""
    parser.add_argument('--params-file', default=None, help='default: installed params.yaml')
    parser.add_argument('--mavlink-port', type=int, default=graph.DEFAULT_MAVLINK_PORT)
    parser.add_argument('--mavlink-url', default=None, help='onboard graph: vehicle URL')
    parser.add_argument('--initial-position', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                        help='paper frame {I}, m')
    parser.add_argument('--wind', type=float, nargs=3, metavar=('FX', 'FY', 'FZ'),
                        help='{I}, N')
    parser.add_argument('--crossing-law', choices=graph.CROSSING_LAWS)


def main(argv: list | None = None) -> int:
    """Run the sim or onboard graph until Ctrl-C or SIGTERM; restart perception nodes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('graph', nargs='?', choices=('sim', 'onboard'), default='sim')
    parser.add_argument('--layout', choices=LAYOUTS, default=None,
                        help='the onboard nodes in one composed process, in a container per '
                             'camera and one for control (grouped: for two or more cores), or '
                             'a process each (default: composed for onboard, processes for '
                             'sim)')
    add_graph_arguments(parser)
    parser.add_argument('--log-dir', default=None, help='write <node>.log files here')
    args = parser.parse_args(argv)
    graph.ensure_ament_prefix_path()
    try:
        opts = options_from_args(args)
        specs = graph.sim_graph(opts) if args.graph == 'sim' else graph.onboard_graph(opts)
    except ValueError as exc:          # a bad parameter file or option: nothing is started
        print(f'runner: {exc}', file=sys.stderr, flush=True)
        return 2
    raise_on_sigterm()
    runner = ProcessRunner(log_dir=args.log_dir)
    rc = 0
    layout = args.layout or DEFAULT_LAYOUT[args.graph]
    try:
        runner.start_layout(specs, layout, respawn_composed=True)
        print(f'runner: started {", ".join(s.name for s in specs)} ({layout})', flush=True)
        while True:
            for event in runner.supervise():
                print(f'runner: {event}', file=sys.stderr, flush=True)
                rc = 1
            time.sleep(0.2)
    except (KeyboardInterrupt, Terminated):
        pass
    finally:
        codes = runner.stop()
        print(f'runner: stopped ({codes})', flush=True)
    return rc


if __name__ == '__main__':
    sys.exit(main())
