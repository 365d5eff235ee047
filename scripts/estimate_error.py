#!/usr/bin/env python3
"""Attitude-estimate error and lateral drift in WINDOW mode of recorded runs, from their bags.

For each run directory of ``run_scenario`` (summary.json and bag/, sim or PX4 SIH): over the
WINDOW mode (its start and end from summary.json ``run.transitions``), imu/data, which
carries the autopilot's attitude estimate ``R_est = R_IB R_err`` through the bridge, against
sim/ground_truth/odom (the truth R_IB). The error ``R_err = R_IB^T R_est`` is a body
rotation vector (roll, pitch, yaw; FRD axes), median over the WINDOW samples that have an
imu/data sample within 6 ms. Also the truth's lateral position y_I at the start and end of
WINDOW. An autopilot holds its estimate, so an estimate rolled +d flies the truth rolled -d,
which pushes the vehicle towards -y_I (docs/design.md "Attitude-estimate error"): this
prints what a run's autopilot did, to compare with that.

``--increments``: instead, how fast the error moves over the whole bag, the structure function
std(err(t + lag) - err(t)) per axis at ``INCREMENT_LAGS_S``: the truth interpolated on SO(3)
to each imu/data stamp (from the two truth samples around it, at most ``MAX_TRUTH_GAP_S``
apart), lags matched within ``LAG_TOLERANCE_S``. Its value at one camera frame is the attitude
jitter that a derotated optical flow reads as rotation of the scene (docs/sim_autopilot.md).

Usage: ``AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python scripts/estimate_error.py
[--increments] RUN_DIR [RUN_DIR ...]``. Figures: docs/px4_sih.md, docs/sim_autopilot.md.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import re
import sys

import numpy as np

IMU_TOPIC, TRUTH_TOPIC = '/imu/data', '/sim/ground_truth/odom'
MAX_PAIR_S = 0.006                  # s, largest stamp difference of a (truth, imu) pair
INCREMENT_LAGS_S = (0.01, 0.02, 0.04, 0.1, 0.2, 0.5, 1.0)
MAX_TRUTH_GAP_S = 0.025             # s, truth samples farther apart are not interpolated
LAG_TOLERANCE_S = 0.003             # s, a pair of samples is at a lag within this
_T_RE = re.compile(r't = ([0-9.]+) s')


def window_interval(transitions: list[str]) -> tuple[float, float] | None:
    """Return (start, end) ROS time (s) of the first WINDOW mode, or None."""
    start = end = None
    for text in transitions:
        m = _T_RE.search(text)
        if m is None:
            continue
        if start is None and re.search(r'-> WINDOW\b', text):
            start = float(m.group(1))
        elif start is not None and re.search(r'WINDOW ->', text):
            end = float(m.group(1))
            break
    return None if start is None or end is None else (start, end)


def _stamp_s(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def window_estimate_error(run_dir: str | Path) -> dict | None:
    """Return the WINDOW figures of one run (see the module doc), or None without them.

    Keys: ``window_s`` (start, end), ``error_deg`` (median roll, pitch, yaw error), ``pairs``
    (samples compared), ``y_I_m`` (truth y at the start and end of WINDOW), ``success``.
    """
    from ibvs_harness.bag import deserialize, read_messages
    from ibvs_common.core.frames import log_so3, R_IB_from_quat_map_base, vec_map_to_I
    run = Path(run_dir)
    try:
        summary = json.loads((run / 'summary.json').read_text())
    except (OSError, ValueError):
        return None
    interval = window_interval(summary.get('run', {}).get('transitions') or [])
    if interval is None or not (run / 'bag').is_dir():
        return None
    t0, t1 = interval
    imu_t, imu_R, truth = [], [], []
    for topic, msgtype, _, data in read_messages(run / 'bag', [IMU_TOPIC, TRUTH_TOPIC]):
        msg = deserialize(data, msgtype)
        if topic == IMU_TOPIC:
            q = msg.orientation
            imu_t.append(_stamp_s(msg.header))
            imu_R.append(R_IB_from_quat_map_base((q.w, q.x, q.y, q.z)))
        else:
            q, p = msg.pose.pose.orientation, msg.pose.pose.position
            truth.append((_stamp_s(msg.header), R_IB_from_quat_map_base((q.w, q.x, q.y, q.z)),
                          vec_map_to_I(np.array([p.x, p.y, p.z]))))
    if not imu_t or not truth:
        return None
    order = np.argsort(imu_t)
    imu_t = np.asarray(imu_t)[order]
    imu_R = [imu_R[k] for k in order]
    errors = []
    for t, R_IB, _ in truth:
        if not t0 <= t <= t1:
            continue
        j = int(np.clip(np.searchsorted(imu_t, t), 0, len(imu_t) - 1))
        j = min((j, max(j - 1, 0)), key=lambda k: abs(imu_t[k] - t))
        if abs(imu_t[j] - t) <= MAX_PAIR_S:
            errors.append(log_so3(R_IB.T @ imu_R[j]))
    in_window = [xi for t, _, xi in truth if t0 <= t <= t1]
    if not errors or not in_window:
        return None
    return {'window_s': (t0, t1), 'pairs': len(errors),
            'error_deg': tuple(math.degrees(e) for e in np.median(np.array(errors), axis=0)),
            'y_I_m': (float(in_window[0][1]), float(in_window[-1][1])),
            'success': summary.get('success')}


def error_series(bag_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,) s, errors (N, 3) rad): R_err = R_IB^T R_est at every imu/data stamp.

    The truth R_IB at an imu/data stamp is interpolated on SO(3) between the truth samples
    around it (at most MAX_TRUTH_GAP_S apart); stamps outside the truth are left out.
    """
    from ibvs_harness.bag import deserialize, read_messages
    from ibvs_common.core.frames import exp_so3, log_so3, R_IB_from_quat_map_base
    est, truth = [], []
    for topic, msgtype, _, data in read_messages(bag_dir, [IMU_TOPIC, TRUTH_TOPIC]):
        msg = deserialize(data, msgtype)
        q = msg.orientation if topic == IMU_TOPIC else msg.pose.pose.orientation
        (est if topic == IMU_TOPIC else truth).append(
            (_stamp_s(msg.header), R_IB_from_quat_map_base((q.w, q.x, q.y, q.z))))
    est.sort(key=lambda x: x[0])
    truth.sort(key=lambda x: x[0])
    t_truth = np.array([t for t, _ in truth])
    stamps, errors = [], []
    for t, R_est in est:
        i = int(np.searchsorted(t_truth, t, side='right'))
        if i == 0 or i >= len(truth):
            continue
        (ta, Ra), (tb, Rb) = truth[i - 1], truth[i]
        if tb - ta > MAX_TRUTH_GAP_S:
            continue
        R_true = Ra @ exp_so3((t - ta) / (tb - ta) * log_so3(Ra.T @ Rb))
        stamps.append(t)
        errors.append(log_so3(R_true.T @ R_est))
    return np.array(stamps), np.array(errors).reshape(-1, 3)


def increment_std(stamps: np.ndarray, errors: np.ndarray,
                  lags: tuple = INCREMENT_LAGS_S) -> dict:
    """{lag: (std of err(t + lag) - err(t) per axis (3,) rad, pairs)} of an error series."""
    out = {}
    for lag in lags:
        j = np.searchsorted(stamps, stamps + lag)
        i = np.nonzero(j < len(stamps))[0]
        j = j[i]
        good = np.abs(stamps[j] - stamps[i] - lag) <= LAG_TOLERANCE_S
        d = errors[j[good]] - errors[i[good]]
        out[lag] = (d.std(axis=0) if len(d) > 1 else np.full(3, np.nan), int(good.sum()))
    return out


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('runs', nargs='+', help='run_scenario result directories')
    p.add_argument('--increments', action='store_true',
                   help="the error's structure function over the whole bag (module doc)")
    a = p.parse_args(argv)
    if a.increments:
        for run in a.runs:
            stamps, errors = error_series(Path(run) / 'bag')
            if len(stamps) < 2:
                print(f'{run}: no imu/data with ground truth around it')
                continue
            std = np.degrees(errors.std(axis=0))
            print(f'{run}: {len(stamps)} samples, error std roll / pitch / yaw '
                  f'{std[0]:.3f} / {std[1]:.3f} / {std[2]:.3f} deg')
            for lag, (d, n) in increment_std(stamps, errors).items():
                d = np.degrees(d)
                print(f'  lag {lag:5.2f} s: increment std {d[0]:.4f} / {d[1]:.4f} / '
                      f'{d[2]:.4f} deg ({n} pairs)')
        return 0
    for run in a.runs:
        r = window_estimate_error(run)
        if r is None:
            print(f'{run}: no WINDOW interval, bag, imu/data or ground truth')
            continue
        roll, pitch, yaw = r['error_deg']
        y0, y1 = r['y_I_m']
        print(f'{run}: success {r["success"]}, WINDOW {r["window_s"][1] - r["window_s"][0]:.2f} '
              f's; estimate error roll {roll:+.2f}, pitch {pitch:+.2f}, yaw {yaw:+.2f} deg '
              f'(median of {r["pairs"]}); truth y_I {y0:+.3f} -> {y1:+.3f} m '
              f'({y1 - y0:+.3f})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
