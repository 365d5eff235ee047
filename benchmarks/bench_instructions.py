#!/usr/bin/env python3
"""Work per frame of the perception and control cores, in instructions (callgrind).

Seconds per frame move 2-4 x with this machine's load and its host's; instructions do not.
Each perception workload processes frames of the reference flight (bench_onboard's frames:
WINDOW frames for the window detector and the wall flow, LANDING frames for the pad detector
and the floor flow), tracked as in flight, with the flight's attitude for the gyro
predictions. Each control workload (``supervisor_window``, ``controller_landing``, ...)
replays the calls that the feature-level reference run made to the supervisor's or the
controller's core, recorded outside callgrind, and counts the frames of its mode. It runs
twice under ``valgrind --tool=callgrind`` (OpenCV on one thread), with ``--warmup`` frames and
with ``--warmup + --frames`` frames; the difference per frame is the workload's cost, setup
and imports excluded. Printed beside each workload's budget: the instructions per frame a
computer must run at the camera rate (docs/onboard.md "The computer it needs"); a core over
budget says so (exit status 1 with ``--check``). The ROS side (message conversion, executor,
the nodes' own layer around the cores) is not in these figures: bench_onboard.py measures
the whole graph's CPU, and ``--callback-cpu`` each node's.

Run: ``AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python benchmarks/bench_instructions.py
[--frames N] [--workload NAME] [--check] [--smoke]`` (a few minutes: callgrind runs Python
~50 x slower).
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
# workload -> (mode whose frames it takes, budget in M instructions per frame)
WORKLOADS = {'window': ('WINDOW', 20.0), 'front_flow': ('WINDOW', 35.0),
             'pad': ('LANDING', 30.0), 'down_flow': ('LANDING', 35.0),
             'supervisor_window': ('WINDOW', 2.0), 'supervisor_landing': ('LANDING', 2.0),
             'controller_window': ('WINDOW', 3.0), 'controller_landing': ('LANDING', 3.0)}
# the control cores' workloads replay the calls that the feature-level reference run made to
# its ModeSupervisor (the supervisor node's core) and IbvsController (the force controller's)
CONTROL_CORES = {'supervisor': ('on_imu', 'on_window', 'on_pad', 'on_flow', 'start',
                                'end_frame'),
                 'controller': ('step',)}
CONTROL_CALLS = 'control_calls.pkl'
FLIGHT_S = {'WINDOW': (1.2, 3.2), 'LANDING': (7.0, 11.0)}   # replay times of those modes
COLLECTED = re.compile(r'Collected : (\d+)')
CACHE_DIR = os.path.join('results', 'bench_instructions')


def prepare(n: int, modes: set) -> None:
    """Write each mode's first ``n`` frames (both cameras, times, attitudes) for the children.

    Rendered by the sim's renderer (with its read noise) at bench_onboard's reference flight,
    outside callgrind.
    """
    sys.path.insert(0, HERE)
    import bench_onboard
    from ibvs_common.core.config import load_pad_layout, load_vehicle
    from ibvs_sim.core.render import SceneRenderer
    from ibvs_sim.core.sensor_noise import ReadNoise
    from ibvs_sim.core.world import load_world
    flight = bench_onboard.reference_flight(50.0)
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    os.makedirs(CACHE_DIR, exist_ok=True)
    for mode in modes:
        lo, hi = FLIGHT_S[mode]
        k = np.flatnonzero((flight['r'] >= lo) & (flight['r'] < hi))[:n]
        out = {}
        for cam in ('front', 'down'):
            model = vehicle.cameras[cam].model
            renderer = SceneRenderer(world, pad, vehicle.cameras[cam])
            noise = ReadNoise(2.0, (model.height, model.width), 0, cam)
            out[cam] = np.stack([noise.apply(renderer.render(flight['R'][i], flight['xi'][i]),
                                             int(i)) for i in k])
        np.savez(os.path.join(CACHE_DIR, f'{mode}.npz'), r=flight['r'][k], R=flight['R'][k],
                 **out)


def prepare_control() -> None:
    """Record the calls of the feature-level reference run to its control cores.

    Every call of CONTROL_CORES's methods, in order, with a deep copy of its arguments:
    (core, method, args, kwargs). Outside callgrind.
    """
    import copy
    import pickle
    sys.path.insert(0, HERE)
    import bench_onboard
    from ibvs_control.core.controller import IbvsController
    from ibvs_control.core.supervisor import ModeSupervisor
    from ibvs_harness import feature_sim
    calls, saved = [], []
    for core, cls in (('supervisor', ModeSupervisor), ('controller', IbvsController)):
        for name in CONTROL_CORES[core]:
            method = getattr(cls, name)
            saved.append((cls, name, method))

            def recorded(self, *args, _core=core, _name=name, _method=method, **kwargs):
                calls.append((_core, _name, copy.deepcopy(args), copy.deepcopy(kwargs)))
                return _method(self, *args, **kwargs)
            setattr(cls, name, recorded)
    try:
        feature_sim.run_feature_scenario(*bench_onboard.reference_run_args())
    finally:
        for cls, name, method in saved:
            setattr(cls, name, method)
    os.makedirs(CACHE_DIR, exist_ok=True)
    with open(os.path.join(CACHE_DIR, CONTROL_CALLS), 'wb') as f:
        pickle.dump(calls, f)


def run_control(name: str, n: int) -> None:
    """Replay the recorded calls of one control core to the first ``n`` frames of its mode.

    A frame is one controller step (the recording's order: the supervisor's calls of a frame,
    then the step). The supervisor's replay checks that it reaches each recorded step's mode.
    """
    import pickle
    sys.path.insert(0, HERE)
    import bench_onboard
    from ibvs_control.core.controller import IbvsController, with_crossing_law
    from ibvs_control.core.supervisor import ModeSupervisor
    core, mode_name = name.split('_')
    with open(os.path.join(CACHE_DIR, CONTROL_CALLS), 'rb') as f:
        calls = pickle.load(f)
    _, _, _, ctrl, sup, _ = bench_onboard.reference_run_args()
    target = ModeSupervisor(sup) if core == 'supervisor' \
        else IbvsController(with_crossing_law(ctrl, ctrl.crossing_law))
    in_mode = 0
    for who, method, args, kwargs in calls:
        if who == 'controller':             # a frame ends: count it if of the mode
            mode = args[0]
            if core == 'supervisor' and target.mode != mode:
                raise RuntimeError(f'replay: supervisor in {target.mode.name}, the run '
                                   f'stepped in {mode.name}')
            if mode.name == mode_name.upper():
                in_mode += 1
                if in_mode > n:
                    return
        if who == core:
            getattr(target, method)(*args, **kwargs)
    if in_mode < n:
        raise RuntimeError(f'the reference run has {in_mode} {mode_name} frames, not {n}')


def frames_of(mode: str, n: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Return (frames by camera, times, R_IB) of the first ``n`` prepared frames of ``mode``."""
    with np.load(os.path.join(CACHE_DIR, f'{mode}.npz')) as d:
        return ({c: d[c][:n] for c in ('front', 'down')}, d['r'][:n], d['R'][:n])


def run_workload(name: str, n: int) -> None:
    """Process ``n`` frames with one core (the child, under callgrind)."""
    if name.split('_')[0] in CONTROL_CORES:
        run_control(name, n)
        return
    import cv2
    cv2.setNumThreads(1)
    from ibvs_common.core.config import load_pad_layout, load_vehicle, load_window_layout
    from ibvs_common.core.frames import e3
    from ibvs_perception.core.flow import FlowConfig, FlowEstimator, wall_normal_from_corners
    from ibvs_perception.core.pad import PadDetector, PadDetectorConfig
    from ibvs_perception.core.window import WindowDetector, WindowDetectorConfig
    mode, _ = WORKLOADS[name]
    frames, r, R = frames_of(mode, n)
    vehicle = load_vehicle()
    front, down = vehicle.cameras['front'], vehicle.cameras['down']
    if name == 'window':
        layout = load_window_layout()
        det = WindowDetector(WindowDetectorConfig(window_width_m=layout.width,
                                                  window_height_m=layout.height,
                                                  frame_band_m=layout.frame_band))
        R_prev = None
        for k in range(len(r)):
            R_IC = R[k] @ front.R_BC
            rot = None if R_prev is None else R_IC.T @ R_prev
            det.process(frames['front'][k], front.model, rot)
            R_prev = R_IC
    elif name == 'pad':
        det = PadDetector(load_pad_layout(), PadDetectorConfig())
        for k in range(len(r)):
            det.process(frames['down'][k], down.model, float(r[k]))
    else:
        cam = front if name == 'front_flow' else down
        est = FlowEstimator(FlowConfig(), cam.model, cam.R_BC)
        eta = e3
        if name == 'front_flow':
            layout = load_window_layout()
            win = WindowDetector(WindowDetectorConfig(window_width_m=layout.width,
                                                      window_height_m=layout.height,
                                                      frame_band_m=layout.frame_band))
            d = win.process(frames['front'][0], front.model, None).detection
            eta, exclude_I = wall_normal_from_corners(d.bearings_C, R[0], front.R_BC)
        else:
            exclude_I = None
        for k in range(len(r)):
            est.process(frames[cam.name][k], float(r[k]), R[k], eta, exclude_I,
                        e3 if name == 'front_flow' else None)


def instructions(name: str, n: int) -> int:
    """Return the instructions callgrind counted for a child processing ``n`` frames."""
    cmd = ['valgrind', '--tool=callgrind', '--callgrind-out-file=/dev/null',
           sys.executable, os.path.abspath(__file__), '--child', name, str(n)]
    env = dict(os.environ, OMP_NUM_THREADS='1', OPENBLAS_NUM_THREADS='1',
               PYTHONDONTWRITEBYTECODE='1', PYTHONHASHSEED='0')
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
    m = COLLECTED.search(out.stderr)
    if out.returncode != 0 or m is None:
        raise RuntimeError(f'callgrind of {name} ({n} frames) failed:\n{out.stderr[-2000:]}')
    return int(m.group(1))


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--frames', type=int, default=20, help='frames counted per workload')
    p.add_argument('--warmup', type=int, default=3, help='frames before the counted ones')
    p.add_argument('--workload', action='append', choices=sorted(WORKLOADS), default=[])
    p.add_argument('--check', action='store_true', help='exit 1 if a core is over budget')
    p.add_argument('--smoke', action='store_true',
                   help='CI: every workload natively on 2 frames, then the window detector\'s '
                        'instructions on 2 frames (when valgrind is installed)')
    p.add_argument('--child', nargs=2, metavar=('WORKLOAD', 'N'), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        run_workload(a.child[0], int(a.child[1]))
        return 0
    names = ['window'] if a.smoke else (a.workload or list(WORKLOADS))
    n = 2 if a.smoke else a.frames
    if a.smoke:                      # every workload's code path, without valgrind's cost
        prepare(a.warmup + n, {mode for mode, _ in WORKLOADS.values()})
        prepare_control()
        for name in WORKLOADS:
            run_workload(name, a.warmup + n)
            print(f'{name}: {a.warmup + n} frames processed natively')
    if shutil.which('valgrind') is None:
        print('bench_instructions: valgrind is not installed (apt install valgrind): no '
              'instructions counted', file=sys.stderr)
        return 0 if a.smoke else 2
    if not a.smoke:
        image_names = [name for name in names if name.split('_')[0] not in CONTROL_CORES]
        if image_names:                                                  # outside callgrind
            prepare(a.warmup + n, {WORKLOADS[name][0] for name in image_names})
        if len(image_names) < len(names):
            prepare_control()
    over = []
    for name in names:
        t0 = time.monotonic()
        base, full = instructions(name, a.warmup), instructions(name, a.warmup + n)
        per_frame = (full - base) / n / 1e6
        budget = WORKLOADS[name][1]
        verdict = 'within budget' if per_frame <= budget else 'OVER BUDGET'
        if per_frame > budget:
            over.append(name)
        print(f'{name:18s} ({WORKLOADS[name][0]:7s} frames) {per_frame:7.1f} M instructions '
              f'per frame ({n} frames; budget {budget:.0f} M: {verdict}) '
              f'[{time.monotonic() - t0:.0f} s]', flush=True)
    return 1 if a.check and over else 0


if __name__ == '__main__':
    sys.exit(main())
