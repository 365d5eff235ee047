"""Throughput of the whole graph in the lockstep simulator: sim time over wall time.

Flies the reference scenario (``python -m ibvs_harness.run_scenario``, lockstep, the graph as
``make run`` starts it, no plots) ``--runs`` times, one after the other, and reads each run's
summary.json ``timing``: ``sim_over_wall`` (sim time / wall time from the sim's first frame to
the end of the flight: process start-up and discovery are not counted; target >= 0.5 on this
2-core machine, issue 14 item 5) and the sim node's wall budget per frame (physics, render,
publish, imu_hold, graph_wait: the graph's own time and the waits for it). Also prints the
image -> setpoint latency and whether every run gave the same flight (window, landing and mode
figures bit for bit, as lockstep runs should). ``--bag`` records the bag as ``make run``
does; ``--layout composed`` flies the onboard nodes in one process.

Run: ``AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python benchmarks/bench_lockstep.py [--runs N]
[--bag] [--smoke]`` on a quiet machine (the load average is printed): the figures move by
+-5 % between runs of the same code on a machine shared with other work. ``--smoke`` (CI)
flies one run stopped 1.5 s of sim time after the start.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time

import numpy as np

BUDGET = ('physics', 'render', 'publish', 'imu_hold', 'graph_wait')
SAME_KEYS = ('window', 'landing', 'modes')


def load_average() -> str:
    """Return the 1-minute load average as text ('?' where unknown)."""
    try:
        return f'{os.getloadavg()[0]:.2f}'
    except OSError:
        return '?'


def fly(results: str, name: str, args) -> dict:
    """Fly one run; return its summary.json (raise on a run that could not be flown)."""
    cmd = [sys.executable, '-m', 'ibvs_harness.run_scenario', '--run-name', name,
           '--results-root', results, '--no-plots', '--layout', args.layout]
    if not args.bag:
        cmd.append('--no-bag')
    if args.smoke:
        cmd += ['--max-sim-time', '1.5']
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    path = Path(results) / name / 'summary.json'
    if proc.returncode not in (0, 1) or not path.exists():
        raise RuntimeError(f'{name}: run_scenario exited {proc.returncode}:\n'
                           f'{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}')
    summary = json.loads(path.read_text())
    summary['_process_wall_s'] = time.monotonic() - t0
    return summary


def row(name: str, s: dict, load_before: str) -> str:
    """One run's line."""
    t = s.get('timing', {})
    budget = ' '.join(f'{k} {t.get(f"wall_{k}_ms_per_frame", float("nan")):.2f}'
                      for k in BUDGET)
    return (f'{name}: sim/wall {t.get("sim_over_wall", float("nan")):.3f} '
            f'({t.get("flight_sim_s", float("nan")):.2f} s of sim time in '
            f'{t.get("wall_s", float("nan")):.2f} s; the whole process '
            f'{s["_process_wall_s"]:.1f} s), success {s.get("success")}, latency median '
            f'{t.get("latency_median_ms", float("nan")):.1f} ms; ms per frame: {budget} '
            f'(load {load_before} -> {load_average()})')


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--runs', type=int, default=3, help='reference flights, one at a time')
    p.add_argument('--bag', action='store_true', help='record the bag, as make run does')
    p.add_argument('--layout', choices=('processes', 'composed'), default='processes')
    p.add_argument('--timeout', type=float, default=300.0, help='wall s per run')
    p.add_argument('--results-root', default=None, help='keep the runs here (default: a '
                   'temporary directory, removed)')
    p.add_argument('--smoke', action='store_true', help='CI: one run, 1.5 s of sim time')
    args = p.parse_args(argv)
    runs = 1 if args.smoke else max(1, args.runs)
    with tempfile.TemporaryDirectory(prefix='bench_lockstep_') as tmp:
        results = args.results_root or tmp
        summaries = []
        for k in range(runs):
            load = load_average()
            s = fly(results, f'lockstep{k}', args)
            summaries.append(s)
            print(row(f'run {k}', s, load), flush=True)
    ratios = [s.get('timing', {}).get('sim_over_wall', np.nan) for s in summaries]
    print(f'sim time / wall time ({runs} run(s), {args.layout}, bag {"on" if args.bag else "off"}'
          f'): median {np.nanmedian(ratios):.3f}, min {np.nanmin(ratios):.3f}, max '
          f'{np.nanmax(ratios):.3f} (target >= 0.5)')
    for k in BUDGET:
        values = [s.get('timing', {}).get(f'wall_{k}_ms_per_frame', np.nan) for s in summaries]
        print(f'  {k}: median {np.nanmedian(values):.2f} ms per frame')
    keys = {json.dumps({k: s.get(k) for k in SAME_KEYS}, sort_keys=True) for s in summaries}
    print(f'same flight in every run: {"yes" if len(keys) == 1 else "NO"}')
    return 0 if len(keys) == 1 and np.all(np.isfinite(ratios)) else 1


if __name__ == '__main__':
    sys.exit(main())
