#!/usr/bin/env python3
"""Thread CPU of every rclpy callback of one process, by node, topic and time: a launcher.

Usage: ``python benchmarks/callback_cpu.py OUT.json -m MODULE [ARGS ...]`` runs ``MODULE``
(e.g. ``ibvs_bringup.composed``) as ``python -m`` would, after wrapping the callbacks that its
nodes give ``Node.create_subscription`` and ``Node.create_timer``. Each call adds its thread CPU
(``time.thread_time_ns``: the CPU this thread used, not the time it waited for the GIL or for
a core) to its node and topic, in bins of ``BIN_S`` of the system clock, so that a benchmark
can split the figures by the modes it saw. ``OUT.json`` is rewritten every ``DUMP_S`` and at
exit, with the process CPU and the callbacks' thread names.

What is not in a callback: the executor's own work (taking and converting messages, the
dispatch), the MAVLink reader thread, Fast DDS's threads and the garbage collector when it
runs between callbacks. The process CPU minus the callbacks' sum is that rest.

Measurement only: nothing of the flight path imports this module (bench_onboard.py
``--callback-cpu`` uses it). The wrapper keeps the callback's signature (``functools.wraps``),
which rclpy reads to decide whether to pass a MessageInfo.
"""
from __future__ import annotations

import atexit
import functools
import json
import os
import runpy
import sys
import threading
import time
from typing import Callable

BIN_S = 0.1          # s of the system clock per bin
DUMP_S = 0.5         # s between two writes of the output


class CallbackCpu:
    """Thread CPU and calls of wrapped callbacks, per (node, what) and time bin."""

    def __init__(self) -> None:
        # 'node what' -> {bin index: [calls, thread CPU ns]}; bin = system ns // BIN_NS
        self.bins: dict = {}
        self.threads: dict = {}     # 'node what' -> thread name of its last call
        self._bin_ns = int(BIN_S * 1e9)

    def wrap(self, key: str, callback: Callable) -> Callable:
        """Return ``callback`` wrapped to count its calls and thread CPU under ``key``."""
        bins = self.bins.setdefault(key, {})

        @functools.wraps(callback)
        def counted(*args):
            wall, t0 = time.time_ns(), time.thread_time_ns()
            try:
                return callback(*args)
            finally:
                cell = bins.setdefault(wall // self._bin_ns, [0, 0])
                cell[0] += 1
                cell[1] += time.thread_time_ns() - t0
                self.threads[key] = threading.current_thread().name
        return counted

    def snapshot(self) -> dict:
        """Return the figures so far (JSON-able): bins, bin width, threads and process CPU."""
        return {'bin_ns': self._bin_ns, 'process_cpu_s': time.process_time(),
                'threads': dict(self.threads),
                'bins': {k: {str(b): list(v) for b, v in list(cells.items())}
                         for k, cells in list(self.bins.items())}}


def install(counter: CallbackCpu) -> None:
    """Wrap the callbacks of every subscription and timer created from now on."""
    from rclpy.node import Node
    create_subscription, create_timer = Node.create_subscription, Node.create_timer

    def subscription(node, msg_type, topic, callback, *args, **kwargs):
        return create_subscription(node, msg_type, topic,
                                   counter.wrap(f'{node.get_name()} sub {topic}', callback),
                                   *args, **kwargs)

    def timer(node, period, callback, *args, **kwargs):
        return create_timer(node, period,
                            counter.wrap(f'{node.get_name()} timer {period:g} s', callback),
                            *args, **kwargs)
    Node.create_subscription, Node.create_timer = subscription, timer


def per_mode(snapshot: dict, modes: list, end_ns: int) -> dict:
    """Split the callbacks' thread CPU by mode: {mode: {key: (calls, CPU ns)}}.

    ``modes``: (system ns at which it began, name), in time order; the last ends at
    ``end_ns``. A bin counts for the mode in force at its middle; bins before the first mode
    and after ``end_ns`` count for none.
    """
    starts = [ns for ns, _ in modes] + [end_ns]
    out: dict = {name: {} for _, name in modes}
    half = snapshot['bin_ns'] // 2
    for key, cells in snapshot['bins'].items():
        for b, (calls, cpu_ns) in cells.items():
            t = int(b) * snapshot['bin_ns'] + half
            for i, (_, name) in enumerate(modes):
                if starts[i] <= t < starts[i + 1]:
                    calls0, cpu0 = out[name].get(key, (0, 0))
                    out[name][key] = (calls0 + calls, cpu0 + cpu_ns)
                    break
    return out


def main(argv: list) -> None:
    """Run ``-m MODULE ARGS`` with the callbacks counted into ``argv[0]``."""
    if len(argv) < 3 or argv[1] != '-m':
        sys.exit(__doc__.split('\n\n')[1])
    out_path, module, rest = argv[0], argv[2], argv[3:]
    counter = CallbackCpu()
    install(counter)

    def dump() -> None:
        tmp = out_path + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(counter.snapshot(), f)
        os.replace(tmp, out_path)

    def dump_every() -> None:
        while True:
            time.sleep(DUMP_S)
            dump()
    threading.Thread(target=dump_every, name='callback_cpu', daemon=True).start()
    atexit.register(dump)
    sys.argv = [module] + rest
    runpy.run_module(module, run_name='__main__', alter_sys=True)


if __name__ == '__main__':
    main(sys.argv[1:])
