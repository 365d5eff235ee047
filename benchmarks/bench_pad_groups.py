"""Pad groups: q_t at a change of the set of complete groups, and completeness per altitude.

Frames: the sim's renderer (``ibvs_sim.core.render.SceneRenderer``, down camera) plus the
sim's read noise (Gaussian, sigma 1.5 grey levels), at seeded random descent poses; the pad
detector of ``ibvs_perception.core.pad`` with its default configuration (params.yaml).

``switch`` (issue 15 item 5): at each pose with >= 2 complete groups S, every switch that
one group g can cause (S vs S - {g}, same frame, same detection) moves the feature by
``angle`` (deg) and ``|dq|``. Features: ``centroid`` = centroid_feature of the marker
centres of the groups (q_t before), ``pad`` = features.pad_feature (the pad centre seen
through every complete group; q_t after). ``geometry`` rows use the exact bearings of the
marker centres (no image): what the set change does by itself. ``accuracy``: the angle of the
feature of one detected group to the same feature from exact bearings, and the relative error
of the group's height estimate (features.pad_height_estimate, the supervisor's cue). Then
smooth descents (one tracked detector per descent, 150 frames): the set changes and
|q_t(k) - q_t(k-1)| at the changes against the other frames (which include the motion).

``complete``: for each altitude, random lateral offsets and tilts; per group, the share of
frames in which the group is complete among those in which its 4 markers lie wholly inside
the image (>= 2 px from the border), with the median side of its smallest marker (px);
then the same by smallest-marker size. Conditions: ``sim`` (read noise 1.5), ``noise 8``,
``blur 4`` (linear motion blur, random direction), ``noise 5 + blur 3``; the degradations of
benchmarks/bench_window_robustness.py. Each frame is searched twice by the same detector
(whole image, then the tracked region), as in a descent; the second result counts.
``--no-small-pass`` turns the detector's small-marker pass off (the detector before it).

Run: AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python benchmarks/bench_pad_groups.py
(``--part switch|complete``, ``--poses N``.)
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from ibvs_common.core import features as ft
from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_perception.core.pad import PadDetector, PadDetectorConfig
from ibvs_sim.core.render import SceneRenderer
from ibvs_sim.core.world import load_world

from bench_window_robustness import degrade as window_degrade   # same directory

READ_NOISE = 1.5                 # grey levels, the sim's camera_read_noise_std
ALTITUDES_M = (0.3, 0.4, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
SIZE_BINS_PX = (0.0, 8.0, 10.0, 12.0, 15.0, 20.0, 30.0, np.inf)
CONDITIONS = (('sim', 0.0, 0.0), ('noise 8', 8.0, 0.0), ('blur 4', 0.0, 4.0),
              ('noise 5 + blur 3', 5.0, 3.0))
BORDER_PX = 2.0
WALL_SIDE_X = -0.3               # m: the wall (x = -0.5) hides the pad from beyond it


def degrade(img: np.ndarray, noise: float, blur: float, rng: np.random.Generator) -> np.ndarray:
    """Motion blur (px), then Gaussian noise (sigma, grey levels) on top of the read noise."""
    if blur > 0.0:
        img = window_degrade(img, 'blur', blur, rng)
    return window_degrade(img, 'noise', float(np.hypot(noise, READ_NOISE)), rng)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def truth_bearings_I(group, xi: np.ndarray) -> np.ndarray:
    P = group.marker_centres_I() - xi
    return P / np.linalg.norm(P, axis=1, keepdims=True)


def marker_corners_px(group, cam, R_IB: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Distorted pixels (4 markers, 4 corners, 2) of a group's markers (NaN behind the lens)."""
    h = 0.5 * group.side
    sq = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    P = np.concatenate([c + sq for c in group.marker_centres_I()]) - xi
    uv, _ = cam.model.bearings_to_pixels(frames.bearings_I_to_C(P, R_IB, cam.R_BC))
    return uv.reshape(4, 4, 2)


def in_view(uv: np.ndarray, cam) -> bool:
    return bool(np.all(np.isfinite(uv)) and np.all(uv >= BORDER_PX - 0.5)
                and np.all(uv[..., 0] <= cam.model.width - 0.5 - BORDER_PX)
                and np.all(uv[..., 1] <= cam.model.height - 0.5 - BORDER_PX))


def smallest_side_px(uv: np.ndarray) -> float:
    return float(np.linalg.norm(uv - np.roll(uv, 1, axis=1), axis=2).mean(axis=1).min())


def split_groups(det, R_IB: np.ndarray, R_BC: np.ndarray) -> dict:
    p = frames.bearings_C_to_I(det.bearings_C, R_IB, R_BC)
    return {g: p[4 * k:4 * k + 4] for k, g in enumerate(det.group_names)}


def features_of(groups: dict, names) -> tuple[np.ndarray, np.ndarray]:
    p = np.concatenate([groups[n] for n in names])
    return ft.centroid_feature(p), ft.pad_feature(p)


def summary(values, unit: str = '') -> str:
    v = np.asarray(values, dtype=float)
    if len(v) == 0:
        return 'n 0'
    return (f'median {np.median(v):.4f}{unit}  p95 {np.percentile(v, 95):.4f}{unit}  '
            f'max {v.max():.4f}{unit}  (n {len(v)})')


def random_descent_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    h = rng.uniform(0.15, 2.0)
    r = min(0.5, 0.6 * h) * np.sqrt(rng.uniform())
    a = rng.uniform(-np.pi, np.pi)
    x = r * np.cos(a)
    x = -x if x < WALL_SIDE_X else x       # the camera stays on the pad's side of the wall
    xi = np.array([x, r * np.sin(a), -h])
    return frames.rot_from_euler_zyx(*rng.uniform(-0.25, 0.25, 2), rng.uniform(-0.3, 0.3)), xi


def part_switch(n_poses: int, config: PadDetectorConfig) -> None:
    layout, cam = load_pad_layout(), load_vehicle().cameras['down']
    renderer = SceneRenderer(load_world(), layout, cam)
    by_name = {g.name: g for g in layout.groups}
    rng = np.random.default_rng(15)
    rows = {k: [] for k in ('centroid', 'pad', 'geometry centroid', 'geometry pad')}
    norms = {k: [] for k in rows}
    accuracy = {'centroid': [], 'pad': []}
    pad_acc_by_group = {g.name: [] for g in layout.groups}
    height_by_group = {g.name: [] for g in layout.groups}
    for _ in range(n_poses):
        R_IB, xi = random_descent_pose(rng)
        img = degrade(renderer.render(R_IB, xi), 0.0, 0.0, rng)
        det = PadDetector(layout, config).process(img, cam.model)
        groups = split_groups(det, R_IB, cam.R_BC)
        truth = {n: truth_bearings_I(by_name[n], xi) for n in groups}
        for n in groups:
            c_meas, p_meas = features_of(groups, [n])
            c_true, p_true = features_of(truth, [n])
            accuracy['centroid'].append(angle_deg(c_meas, c_true))
            accuracy['pad'].append(angle_deg(p_meas, p_true))
            pad_acc_by_group[n].append(angle_deg(p_meas, p_true))
            height_by_group[n].append(abs(ft.pad_height_estimate(groups[n], by_name[n].c)
                                          / -xi[2] - 1.0))
        names = list(groups)
        if len(names) < 2:
            continue
        for g in names:
            rest = [n for n in names if n != g]
            for src, tag in ((groups, ''), (truth, 'geometry ')):
                c_all, p_all = features_of(src, names)
                c_rest, p_rest = features_of(src, rest)
                rows[tag + 'centroid'].append(angle_deg(c_all, c_rest))
                rows[tag + 'pad'].append(angle_deg(p_all, p_rest))
                norms[tag + 'centroid'].append(float(np.linalg.norm(c_all - c_rest)))
                norms[tag + 'pad'].append(float(np.linalg.norm(p_all - p_rest)))
    print(f'switch: {n_poses} poses (0.15-2 m, lateral <= min(0.5, 0.6 h) m, x >= -0.3 m, '
          'roll/pitch '
          '+-0.25 rad, yaw +-0.3 rad), every one-group switch of each pose')
    for k in rows:
        print(f'  {k:18s} angle {summary(rows[k], " deg")}')
        print(f'  {"":18s} |dq|  {summary(norms[k])}')
    for k, v in accuracy.items():
        print(f'  accuracy {k:9s} one group vs exact: {summary(v, " deg")}')
    for k, v in pad_acc_by_group.items():
        print(f'  accuracy pad, group {k}: {summary(v, " deg")}; height |rel. error| '
              f'{summary(height_by_group[k])}')
    for seed in range(3):
        descent(renderer, layout, cam, config, seed)


def descent(renderer, layout, cam, config, seed: int, n: int = 150) -> None:
    """Fly a smooth descent 2 -> 0.15 m from a lateral offset with tilt: q_t frame to frame."""
    rng = np.random.default_rng(100 + seed)
    start = np.array([rng.uniform(-0.3, 0.4), rng.uniform(-0.4, 0.4), -2.0])
    end = np.array([*rng.uniform(-0.03, 0.03, 2), -0.15])
    ph = rng.uniform(0, 2 * np.pi, 3)
    detector = PadDetector(layout, config)
    prev, changes, steady = None, {'centroid': [], 'pad': []}, {'centroid': [], 'pad': []}
    n_changes = 0
    for k in range(n):
        s = k / (n - 1)
        xi = start + (end - start) * (1 - (1 - s) ** 1.5)
        R_IB = frames.rot_from_euler_zyx(0.15 * np.sin(6 * s + ph[0]),
                                         0.15 * np.sin(5 * s + ph[1]),
                                         0.2 * np.sin(3 * s + ph[2]))
        img = degrade(renderer.render(R_IB, xi), 0.0, 0.0, rng)
        det = detector.process(img, cam.model, stamp_s=0.02 * k)
        if not det.group_names:
            prev = None
            continue
        groups = split_groups(det, R_IB, cam.R_BC)
        q = dict(zip(('centroid', 'pad'), features_of(groups, list(groups))))
        if prev is not None:
            target = changes if prev[0] != det.group_names else steady
            n_changes += prev[0] != det.group_names
            for key in q:
                target[key].append(float(np.linalg.norm(q[key] - prev[1][key])))
        prev = (det.group_names, q)
    print(f'descent seed {seed}: {n} frames 2 -> 0.15 m from ({start[0]:+.2f}, {start[1]:+.2f}),'
          f' {n_changes} set changes')
    for key in ('centroid', 'pad'):
        print(f'  {key:8s} |dq| at a change: {summary(changes[key])}')
        print(f'  {"":8s} |dq| otherwise:   {summary(steady[key])}')


def part_complete(n_poses: int, config: PadDetectorConfig) -> None:
    layout, cam = load_pad_layout(), load_vehicle().cameras['down']
    renderer = SceneRenderer(load_world(), layout, cam)
    rng = np.random.default_rng(16)
    poses = {h: [] for h in ALTITUDES_M}
    for h in ALTITUDES_M:
        for _ in range(n_poses):
            r = 0.3 * h * np.sqrt(rng.uniform())
            a = rng.uniform(-np.pi, np.pi)
            R_IB = frames.rot_from_euler_zyx(*rng.uniform(-0.15, 0.15, 2), rng.uniform(-0.3, 0.3))
            x = r * np.cos(a)
            x = -x if x < WALL_SIDE_X else x       # the camera stays on the pad's side of the wall
            poses[h].append((R_IB, np.array([x, r * np.sin(a), -h])))
    images = {h: [renderer.render(R, xi) for R, xi in poses[h]] for h in ALTITUDES_M}
    names = [g.name for g in layout.groups]
    print(f'complete: {n_poses} poses per altitude (lateral <= 0.3 h, x >= -0.3 m, '
          'roll/pitch +-0.15 rad, '
          'yaw +-0.3 rad); % complete of frames with the group wholly in view '
          '(median smallest marker px)')
    for cond, noise, blur in CONDITIONS:
        crng = np.random.default_rng(17)
        by_size = {b: [0, 0] for b in range(len(SIZE_BINS_PX) - 1)}
        times = []
        print(f'  {cond}')
        print('  h (m) | ' + ' | '.join(f'{n:>14s}' for n in names))
        for h in ALTITUDES_M:
            stats = {n: [0, 0, []] for n in names}
            for (R_IB, xi), img0 in zip(poses[h], images[h]):
                img = degrade(img0, noise, blur, crng)
                detector = PadDetector(layout, config)
                detector.process(img, cam.model)
                t0 = time.perf_counter()
                det = detector.process(img, cam.model)
                times.append(time.perf_counter() - t0)
                for g in layout.groups:
                    uv = marker_corners_px(g, cam, R_IB, xi)
                    if not in_view(uv, cam):
                        continue
                    side = smallest_side_px(uv)
                    ok = g.name in det.group_names
                    stats[g.name][0] += 1
                    stats[g.name][1] += ok
                    stats[g.name][2].append(side)
                    b = int(np.searchsorted(SIZE_BINS_PX, side, side='right')) - 1
                    by_size[b][0] += 1
                    by_size[b][1] += ok
            cells = []
            for n in names:
                seen, ok, sides = stats[n]
                cells.append(f'{100 * ok / seen:5.1f} ({np.median(sides):5.1f})' if seen
                             else f'{"-":>14s}')
            print(f'  {h:5.2f} | ' + ' | '.join(f'{c:>14s}' for c in cells))
        bins = []
        for b, (seen, ok) in by_size.items():
            lo, hi = SIZE_BINS_PX[b], SIZE_BINS_PX[b + 1]
            if seen:
                bins.append(f'{lo:.0f}-{hi:.0f} px: {100 * ok / seen:.0f} % of {seen}')
        print('  by smallest marker: ' + '; '.join(bins))
        ms = 1e3 * np.asarray(times)
        print(f'  tracked-frame time median {np.median(ms):.2f} ms, p99 '
              f'{np.percentile(ms, 99):.2f} ms')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--part', choices=('switch', 'complete', 'all'), default='all')
    parser.add_argument('--poses', type=int, default=0,
                        help='poses (switch: total, default 150; complete: per altitude, '
                             'default 40)')
    parser.add_argument('--no-small-pass', action='store_true',
                        help="the detector without its small-marker pass")
    for name in ('small_marker_px', 'small_marker_min_px', 'small_marker_target_px'):
        parser.add_argument('--' + name.replace('_', '-'), type=float, default=None,
                            help=f'PadDetectorConfig.{name} (default: the config default)')
    args = parser.parse_args()
    config = PadDetectorConfig()
    for name in ('small_marker_px', 'small_marker_min_px', 'small_marker_target_px'):
        if getattr(args, name) is not None:
            config = dataclasses.replace(config, **{name: getattr(args, name)})
    if args.no_small_pass:
        config = dataclasses.replace(config, small_marker_px=0.0)
    if args.part in ('switch', 'all'):
        part_switch(args.poses or 150, config)
    if args.part in ('complete', 'all'):
        part_complete(args.poses or 40, config)


if __name__ == '__main__':
    main()
