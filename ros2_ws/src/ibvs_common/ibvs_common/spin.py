"""spin_guarded: spin one node on the fastest executor, surviving a sample rclpy cannot convert.

Executor: rclpy's C++ ``EventsExecutor`` (``rclpy.experimental``, in Jazzy's rclpy 7.1) when
it is there, else the ``SingleThreadedExecutor``. The events executor dispatches each message
from C++ instead of rebuilding a Python wait set at every wake-up: measured with
benchmarks/bench_latency.py (docs/performance.md), it is most of the graph's idle CPU, which a
100 Hz IMU to five subscribers otherwise costs. ``IBVS_EXECUTOR=single`` forces the plain one.
It is driven by ``spin_once`` with a timeout: with the rclpy 7.1.6 wheels its ``spin()``
dispatched no timer at all (measured: 0 callbacks of a 100 Hz timer in 1 s, and it ignored
``shutdown``), while ``spin_once`` ran every one.

Under load, a best-effort sample can reach rclpy in a state its Python message class refuses
(e.g. a string field that is not valid UTF-8, or a NaN where the class asserts): rclpy's
``take_message`` then raises ``RuntimeError: Unable to convert call argument '0' to Python
object`` from inside ``spin`` (ros2/rclpy#848), which would end the node. For flight software
one bad sample must cost one sample, not the node: the error is logged (throttled) and spinning
resumes. KeyboardInterrupt and ExternalShutdownException still end the spin as usual.

Stopping: SIGINT and SIGTERM (Ctrl-C, launch, the runner, systemd) end the spin between two
callbacks, with the context still valid, so the caller destroys the nodes and shuts rclpy down
in order. rclpy's own handlers, which :func:`spin_guarded_nodes` replaces while it spins (in
the main thread), shut the context down at once, under a callback that may be publishing:
"Exception in 'subscriptions' callback" (FATAL, from the events executor) and "publisher's
context is invalid" in the log of a stopped run. A stop takes up to
``SPIN_ONCE_TIMEOUT_S`` when no work arrives.

Garbage collector: before spinning, ``gc.freeze()`` moves every object built at start-up
(modules, parameters, buffers: some 45,000 in the supervisor, controller, window detector
and flow nodes) out of the collector's reach. A full collection, which Python runs now and
then in the middle of a callback, then scans only what the nodes allocated since:
``benchmarks/bench_gc_pause.py`` measured 5.0 ms median, 14.5 ms max before, under 0.01 ms
after, against a 20 ms frame budget.
"""
from __future__ import annotations

import gc
import os
import signal
import threading
from typing import Callable, TYPE_CHECKING

import rclpy
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

if TYPE_CHECKING:
    from rclpy.context import Context

LOG_THROTTLE_S = 2.0
SPIN_ONCE_TIMEOUT_S = 0.5               # s, longest wait for work before re-checking rclpy.ok
EXECUTOR_ENV = 'IBVS_EXECUTOR'          # 'events' (default when available) | 'single'
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def make_executor(context: Context | None = None) -> Executor:
    """Return the events executor when available (and not disabled), else a single-threaded one."""
    if os.environ.get(EXECUTOR_ENV, 'events') != 'single':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(context=context)
        except ImportError:
            pass
    return SingleThreadedExecutor(context=context)


def run_node(make_node: Callable[[], Node], name: str, args: list[str] | None = None,
             refuse: tuple[type[BaseException], ...] = (ValueError,)) -> None:
    """Run one node until Ctrl-C or SIGTERM: every console script's ``main()``.

    The Jazzy demo_nodes_py pattern (init, build, spin, destroy, shut down) on
    :func:`spin_guarded`. An exception of a type in ``refuse`` while building the node (a bad
    parameter or configuration file, a port in use) is logged as fatal under ``name`` and the
    process exits with status 1: a node never runs on a configuration it refused.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = make_node()
        spin_guarded(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except refuse as exc:
        rclpy.logging.get_logger(name).fatal(f'cannot start: {exc}')
        raise SystemExit(1) from exc
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def spin_guarded(node: Node) -> int:
    """Spin ``node`` until shutdown; return the number of RuntimeErrors survived."""
    return spin_guarded_nodes([node])


def spin_guarded_nodes(nodes: list) -> int:
    """Spin ``nodes`` on one executor until shutdown; return the RuntimeErrors survived."""
    return spin_guarded_groups([nodes])


def spin_guarded_groups(groups: list) -> int:
    """Spin each group of nodes on an executor of its own, each in its own thread.

    The first group spins in the calling thread (the main thread: it takes SIGINT/SIGTERM),
    the others in threads of their own; all stop together. A group's callbacks never wait
    behind another group's: the composed container's control nodes do not queue behind the
    images (``ibvs_bringup.composed``). Python runs one thread at a time, but
    hands over at least every 5 ms (``sys.getswitchinterval``) and whenever OpenCV or the
    middleware releases the interpreter. Return the RuntimeErrors survived, all groups.
    """
    groups = [list(g) for g in groups if g]
    context = groups[0][0].context
    executors = [make_executor(context) for _ in groups]
    for executor, nodes in zip(executors, groups):
        for node in nodes:
            executor.add_node(node)
    gc.freeze()                 # start-up objects: never scanned again by a full collection
    stop: list = []
    errors = [0] * len(groups)
    previous = _catch_stop_signals(stop)
    failed: list = []           # an exception that ended a side thread: ends them all

    def side(i: int) -> None:
        try:
            _spin_until_stop(executors[i], groups[i], stop, errors, i)
        except BaseException as exc:       # re-raised in the main thread
            failed.append(exc)
            stop.append('failed')

    threads = [threading.Thread(target=side, args=(i,), name=f'executor-{i}', daemon=True)
               for i in range(1, len(groups))]
    try:
        for thread in threads:
            thread.start()
        _spin_until_stop(executors[0], groups[0], stop, errors, 0)
    finally:
        stop.append('done')
        for thread in threads:
            thread.join(timeout=2.0 * SPIN_ONCE_TIMEOUT_S + 1.0)
        for executor in executors:
            executor.shutdown()
        _restore_signals(previous)
    if failed:                  # as if it had been raised here: the process ends on it
        raise failed[0]
    return sum(errors)


def _spin_until_stop(executor: Executor, nodes: list, stop: list, errors: list,
                     index: int) -> None:
    """Spin ``executor`` until rclpy shuts down or ``stop`` fills; count survived errors."""
    context = nodes[0].context
    while rclpy.ok(context=context) and not stop:
        try:
            executor.spin_once(timeout_sec=SPIN_ONCE_TIMEOUT_S)
        except RuntimeError as exc:
            if not rclpy.ok(context=context):
                return
            errors[index] += 1
            nodes[0].get_logger().error(
                f'dropped a message rclpy could not take ({exc}); {errors[index]} so far',
                throttle_duration_sec=LOG_THROTTLE_S)


def _catch_stop_signals(stop: list) -> dict:
    """Make SIGINT/SIGTERM append to ``stop``; return the handlers replaced (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda signum, _frame: stop.append(signum))
    return previous


def _restore_signals(previous: dict) -> None:
    """Put back Python's handlers; Python's defaults where the replaced one was not Python's."""
    for sig, handler in previous.items():
        if handler is None:      # installed outside Python (rclpy's): not restorable
            handler = signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
        signal.signal(sig, handler)
