"""What a run reports, ROS-free: run log, ground-truth features and flows, plots, summary.

summary.json is computed by ``ibvs_sim.core.evaluation`` (docs/spec.md section 5).

Everything here is in the paper frame {I} (x along the window normal, z down); the monitor in
``run_scenario`` converts the ROS messages (map ENU, base_link FLU) with ``frames`` before
appending. Ground truth of the features comes from geometry (world.yaml, pad_layout.yaml) and
the ground-truth pose, never from the images.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from typing import Any

from ibvs_harness.plots import RunData, TimeSeries
from ibvs_common.core import features
from ibvs_common.core.config import PadLayout
from ibvs_sim.core.world import WorldConfig
import numpy as np

FEATURE_VECTORS = ('q_w_bar', 'q_t', 'q_w', 'phi_w', 'phi_t')


@dataclass
class RunLog:
    """Samples of one run, appended by the monitor ({I}, SI, sim time in s)."""

    t: list = field(default_factory=list)              # ground truth
    xi: list = field(default_factory=list)
    v: list = field(default_factory=list)
    euler: list = field(default_factory=list)          # roll, pitch, yaw of R_IB
    omega: list = field(default_factory=list)          # body FRD rates
    modes: list = field(default_factory=list)          # [(mode, t_start)]
    events: list = field(default_factory=list)         # sim/events dicts
    vectors: dict = field(default_factory=dict)        # name -> ([t], [v])

    def add_truth(self, t: float, xi: np.ndarray, v: np.ndarray, euler: np.ndarray,
                  omega: np.ndarray) -> None:
        """Append one ground-truth sample."""
        self.t.append(float(t))
        self.xi.append(np.asarray(xi, dtype=float))
        self.v.append(np.asarray(v, dtype=float))
        self.euler.append(np.asarray(euler, dtype=float))
        self.omega.append(np.asarray(omega, dtype=float))

    def add_mode(self, t: float, mode: int) -> bool:
        """Record a mode if it changed; return True if it did."""
        if self.modes and self.modes[-1][0] == int(mode):
            return False
        self.modes.append((int(mode), float(t)))
        return True

    def add_vector(self, name: str, t: float, value: np.ndarray) -> None:
        """Append one sample of a named vector series (force, flow_down, q_t, ...)."""
        ts, vs = self.vectors.setdefault(name, ([], []))
        ts.append(float(t))
        vs.append(np.asarray(value, dtype=float).reshape(-1))

    @property
    def mode(self) -> int | None:
        """Return the latest mode number, None before the first one."""
        return self.modes[-1][0] if self.modes else None

    def truth_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (t, xi (N, 3), v (N, 3))."""
        return (np.asarray(self.t), np.asarray(self.xi).reshape(-1, 3),
                np.asarray(self.v).reshape(-1, 3))


def named_vector(names: list, values: list, prefix: str) -> np.ndarray | None:
    """Extract the 3-vector ``prefix`` from a named vector (JointState names/positions).

    Accepts ``prefix_x/_y/_z``, ``prefix.x/.y/.z`` and ``prefix[0..2]`` naming; None if absent.
    """
    index = {n: i for i, n in enumerate(names)}
    for keys in ([f'{prefix}_{a}' for a in 'xyz'], [f'{prefix}.{a}' for a in 'xyz'],
                 [f'{prefix}[{i}]' for i in range(3)], [f'{prefix}/{a}' for a in 'xyz']):
        if all(k in index for k in keys):
            return np.array([values[index[k]] for k in keys], dtype=float)
    return None


# --- ground truth from geometry ----------------------------------------------------------

def flow_truth(xi: np.ndarray, v: np.ndarray, world: WorldConfig
               ) -> tuple[np.ndarray, np.ndarray]:
    """Return the true translational flows v/d (N, 3) of the front and down cameras, {I}.

    Front: the plane ahead along x (the wall before the crossing, the back wall after it).
    Down: the floor. NaN where the distance is below 5 cm.
    """
    xi = np.asarray(xi, dtype=float).reshape(-1, 3)
    v = np.asarray(v, dtype=float).reshape(-1, 3)
    d_front = np.where(xi[:, 0] < world.wall_x, world.wall_x - xi[:, 0],
                       world.back_wall_x - xi[:, 0])
    d_down = world.floor_z - xi[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        front = np.where((d_front > 0.05)[:, None], v / d_front[:, None], np.nan)
        down = np.where((d_down > 0.05)[:, None], v / d_down[:, None], np.nan)
    return front, down


def q_w_bar_truth(xi: np.ndarray, world: WorldConfig, eps: float = 0.2,
                  delta: float = 0.05) -> np.ndarray:
    """Return q_w_bar (N, 3) from the true bearings to the window corners (NaN once past)."""
    out = np.full((len(xi), 3), np.nan)
    corners = world.window.corners_I()
    eta = np.array([1.0, 0.0, 0.0])
    for i, p in enumerate(np.asarray(xi, dtype=float).reshape(-1, 3)):
        if p[0] >= world.wall_x - 0.02:
            continue
        b = corners - p
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        try:
            out[i] = features.compute_window_features(b, eps, delta, eta).q_w_bar
        except ValueError:
            pass
    return out


def q_t_truth(xi: np.ndarray, pad: PadLayout, world: WorldConfig) -> np.ndarray:
    """Return q_t (N, 3) from the true bearings to every marker centre (NaN before crossing).

    The measured q_t uses the landmarks of the complete groups in view; for marker sets centred
    on the pad centre both point the same way, so this is the reference of the figure.
    """
    centres = np.vstack([g.marker_centres_I() for g in pad.groups])
    out = np.full((len(xi), 3), np.nan)
    for i, p in enumerate(np.asarray(xi, dtype=float).reshape(-1, 3)):
        if p[0] <= world.wall_x or world.floor_z - p[2] < 0.05:
            continue
        b = centres - p
        out[i] = features.centroid_feature(b / np.linalg.norm(b, axis=1, keepdims=True))
    return out


def run_data(log: RunLog, world: WorldConfig, pad: PadLayout) -> RunData:
    """Return the plots' data of a run: measured series and their ground truth."""
    t, xi, v = log.truth_arrays()
    series = {'position': TimeSeries.of(t, xi), 'velocity': TimeSeries.of(t, v),
              'euler': TimeSeries.of(t, np.asarray(log.euler).reshape(-1, 3)),
              'omega': TimeSeries.of(t, np.asarray(log.omega).reshape(-1, 3))}
    for name, (ts, vs) in log.vectors.items():
        series[name] = TimeSeries.of(ts, np.asarray(vs))
    if len(t):
        front, down = flow_truth(xi, v, world)
        series['flow_front_truth'] = TimeSeries.of(t, front)
        series['flow_down_truth'] = TimeSeries.of(t, down)
        series['q_w_bar_truth'] = TimeSeries.of(t, q_w_bar_truth(xi, world))
        series['q_t_truth'] = TimeSeries.of(t, q_t_truth(xi, pad, world))
    y0, y1 = world.wall_y_range
    z0, z1 = world.wall_z_range
    x = world.wall_x
    wall = np.array([[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]], dtype=float)
    # the outermost marker's outer edge plus its quiet zone (a fraction of its side)
    outer = max(g.c + g.side * (0.5 + pad.quiet_zone) for g in pad.groups)
    return RunData(series=series, modes=[(ts, m) for m, ts in log.modes],
                   window_corners_I=world.window.corners_I(), pad_center_I=np.zeros(3),
                   window_outer_corners_I=world.window.outer_corners_I(),
                   wall_corners_I=wall, pad_half_side=float(outer))


def summarize(log: RunLog, world: WorldConfig, envelope_radius: float,
              envelope_height: float) -> dict:
    """Return docs/spec.md section 5's summary from the ground truth (ibvs_sim's evaluation)."""
    from ibvs_sim.core.evaluation import evaluate_run
    t, xi, v = log.truth_arrays()
    if len(t) == 0:
        return {'success': False, 'error': 'no ground truth received',
                'window': {'crossed': False, 'min_clearance_m': None,
                           'crossing_offset_m': None, 'crossing_speed_mps': None},
                'landing': {'landed': False, 'error_m': None, 'touchdown_speed_mps': None},
                'modes': [{'mode': m, 't_start_s': ts} for m, ts in log.modes],
                'duration_s': 0.0}
    touchdown = next((e for e in log.events if e.get('type') == 'touchdown'), None)
    speed = None if touchdown is None else touchdown.get('speed_mps')
    return evaluate_run(t, xi, v, world, envelope_radius, envelope_height, log.modes,
                        None if speed is None else float(speed))


def write_json(path: str, data: dict) -> None:
    """Write ``data`` as indented JSON (NaN-free: NaN becomes null)."""
    def clean(x: Any) -> Any:
        if isinstance(x, float) and not np.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.generic):
            return clean(x.item())
        return x
    os.makedirs(os.path.dirname(path) or '.', exist_ok=True)
    with open(path, 'w', encoding='utf-8') as f:
        json.dump(clean(data), f, indent=2)
        f.write('\n')
