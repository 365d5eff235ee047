"""Ground-truth evaluation of one run: docs/spec.md section 5's summary.json.

Evaluation only (like the paper's VICON): nothing here is ever fed to the controller. Input is
the ground-truth trajectory in {I} (NED-type: x along the window normal, z down).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ibvs_sim.core.world import WorldConfig
from ibvs_sim.core.contacts import floor_clearance, obstacle_clearance

MAX_DURATION_S = 60.0
MAX_LANDING_ERROR_M = 0.10
MAX_TOUCHDOWN_SPEED_MPS = 0.5


@dataclass
class GroundTruthLog:
    """Ground-truth samples of one run (append as the run goes)."""

    t: list = field(default_factory=list)        # s
    xi_I: list = field(default_factory=list)     # m, (3,)
    v_I: list = field(default_factory=list)      # m/s, (3,)

    def append(self, t: float, xi_I: np.ndarray, v_I: np.ndarray) -> None:
        """Add one sample."""
        self.t.append(float(t))
        self.xi_I.append(np.asarray(xi_I, dtype=float).copy())
        self.v_I.append(np.asarray(v_I, dtype=float).copy())

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (t (N,), xi_I (N, 3), v_I (N, 3))."""
        return (np.asarray(self.t), np.asarray(self.xi_I).reshape(-1, 3),
                np.asarray(self.v_I).reshape(-1, 3))


def evaluate_run(t: np.ndarray, xi_I: np.ndarray, v_I: np.ndarray, world: WorldConfig,
                 envelope_radius: float, envelope_height: float,
                 modes: list[tuple[int, float]],
                 touchdown_speed_mps: float | None = None, t_start_s: float | None = 0.0
                 ) -> dict:
    """Return the summary dict of docs/spec.md section 5 from a ground-truth trajectory.

    - touchdown: the first sample whose envelope bottom reaches the floor; its speed is the
      vertical speed there, its error the horizontal distance of the body to the pad centre;
    - min_clearance_m: the smallest clearance to wall, window frame and back wall before
      touchdown (the floor is the goal, not an obstacle);
    - crossing: where the body origin passes the wall plane (linear interpolation), the offset
      to the window centre (y, z) and the speed along the window normal e1;
    - success: all of docs/spec.md section 5's conditions.

    ``touchdown_speed_mps``: the impact speed measured by the sim at its physics rate (its
    touchdown event); sampled ground truth can miss it (a floor contact stops the body within
    one step), so when given it is used, and otherwise the larger vertical speed of the
    contact sample and the one before it.

    ``t_start_s``: the sim time the run started at, the origin of ``duration_s`` (the sim
    clock starts at 0; a recorder that heard its first sample later must not shorten the
    run); None: the first sample.
    """
    t = np.asarray(t, dtype=float)
    xi = np.asarray(xi_I, dtype=float).reshape(-1, 3)
    v = np.asarray(v_I, dtype=float).reshape(-1, 3)
    if len(t) == 0:
        raise ValueError('empty trajectory')
    td = next((i for i in range(len(t))
               if floor_clearance(xi[i], world, envelope_height) <= 0.0), None)
    end = len(t) if td is None else td + 1
    clear = min(obstacle_clearance(xi[i], world, envelope_radius, envelope_height)[0]
                for i in range(end))

    crossed, offset, speed = False, None, None     # null in JSON when never crossed
    s = xi[:end, 0] - world.wall_x
    idx = np.nonzero((s[:-1] < 0.0) & (s[1:] >= 0.0))[0]
    if len(idx):
        i = int(idx[0])
        a = -s[i] / (s[i + 1] - s[i])
        p = xi[i] + a * (xi[i + 1] - xi[i])
        vel = v[i] + a * (v[i + 1] - v[i])
        offset = [float(p[1] - world.window.center_I[1]), float(p[2] - world.window.center_I[2])]
        speed = float(vel[0])
        crossed = speed > 0.0

    landed = td is not None
    error = float(np.hypot(*xi[td, :2])) if landed else None
    td_speed = None
    if landed:
        td_speed = float(max(v[td, 2], v[td - 1, 2] if td > 0 else v[td, 2]))
        if touchdown_speed_mps is not None:
            td_speed = float(touchdown_speed_mps)
    duration = float(t[td] if landed else t[-1]) - float(t[0] if t_start_s is None
                                                         else t_start_s)
    success = bool(crossed and clear > 0.0 and landed and error <= MAX_LANDING_ERROR_M
                   and td_speed <= MAX_TOUCHDOWN_SPEED_MPS and duration <= MAX_DURATION_S)
    return {
        'success': success,
        'window': {'crossed': crossed, 'min_clearance_m': float(clear),
                   'crossing_offset_m': offset, 'crossing_speed_mps': speed},
        'landing': {'landed': landed, 'error_m': error, 'touchdown_speed_mps': td_speed},
        'modes': [{'mode': int(m), 't_start_s': float(ts)} for m, ts in modes],
        'duration_s': duration,
    }
