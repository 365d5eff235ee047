"""Timing figures of a sim node (``sim/stats``): the graph's answer latency, the wall budget.

ROS-free; the ``sim`` and ``px4_sim`` nodes publish them.
"""
from __future__ import annotations

import numpy as np

NS_PER_MS = 1_000_000


class AnswerLatency:
    """Image -> setpoint latency of the graph, as the simulated vehicle sees it (wall clock).

    :meth:`published` notes when each frame's images left; :meth:`answered` takes each new
    setpoint's time_boot_ms and the wall time it was read: the published frame nearest it,
    within ``tolerance_ms``, is answered, its latency the read minus the publication.
    ``stamp_errors_ms`` keeps time_boot_ms minus the frame's time (docs/sim.md "Timing").
    Frames off the graph's frame grid when published (a stride above 1: the graph computes
    every n-th frame by design) are owed no answer: ``answered_grid_fraction`` counts the
    others only.
    """

    def __init__(self, keep: int = 200, tolerance_ms: int = 9) -> None:
        self._published: dict[int, tuple[float, bool]] = {}   # frame ms -> (wall s, on grid)
        self._keep = int(keep)
        self.tolerance_ms = int(tolerance_ms)
        self.latencies_s: list[float] = []
        self.stamp_errors_ms: list[int] = []
        self.frames = 0
        self.grid_frames = 0            # published on the graph's frame grid
        self.grid_answered = 0
        self._last_ms: int | None = None

    def published(self, t_ns: int, wall: float, on_grid: bool = True) -> None:
        """Note that the frame at sim time ``t_ns`` was published at ``wall``.

        ``on_grid``: whether it was on the graph's frame grid then (the graph computes it).
        """
        self.frames += 1
        self.grid_frames += int(bool(on_grid))
        self._published[t_ns // NS_PER_MS] = (wall, bool(on_grid))
        while len(self._published) > self._keep:
            del self._published[min(self._published)]

    def answered(self, time_boot_ms: int | None, wall: float) -> None:
        """Note the newest setpoint's time_boot_ms as read at ``wall``."""
        if time_boot_ms is None or time_boot_ms == self._last_ms:
            return
        self._last_ms = time_boot_ms
        ms = int(time_boot_ms)
        near = [k for k in self._published if abs(k - ms) <= self.tolerance_ms]
        if near:
            frame_ms = min(near, key=lambda k: abs(k - ms))
            published, on_grid = self._published.pop(frame_ms)
            self.latencies_s.append(wall - published)
            self.grid_answered += int(on_grid)
            self.stamp_errors_ms.append(ms - frame_ms)

    def stats(self) -> dict:
        """Median, p95, p99, max (ms); the fraction of published (and of grid) frames answered."""
        lat = np.asarray(self.latencies_s, dtype=float) * 1e3
        out = {'frames_published': self.frames, 'frames_answered': int(lat.size),
               'answered_fraction': float(lat.size / self.frames) if self.frames else 0.0,
               'frames_on_grid': self.grid_frames,
               'answered_grid_fraction': (float(self.grid_answered / self.grid_frames)
                                          if self.grid_frames else 0.0)}
        if lat.size:
            out.update({f'latency_{k}_ms': float(v) for k, v in (
                ('median', np.median(lat)), ('p95', np.percentile(lat, 95)),
                ('p99', np.percentile(lat, 99)), ('max', lat.max()))})
            errors = np.abs(self.stamp_errors_ms)
            out.update({'answer_stamp_error_max_ms': int(errors.max()),
                        'answer_stamp_exact_fraction': float(np.mean(errors == 0))})
        return out


def wall_budget(wall_s: float, frames: int, parts: dict) -> dict:
    """Where a run's wall clock went, per frame published (ms): the ``sim/stats`` figures.

    ``wall_s``: wall clock (s) since frame 0 was published; ``parts``: name -> wall s spent in
    it (the sim node: physics substeps, render with read noise, publish, imu_hold: a rendered
    frame waiting for imu/data in lockstep). ``graph_wait`` is the rest: the sim waiting for
    the graph's answer and products (lockstep) or for the wall clock (realtime), and its own
    ticks. Returns ``sim_wall_s`` and ``wall_<part>_ms_per_frame``; empty before any frame.
    """
    if frames <= 0 or wall_s <= 0.0:
        return {}
    parts = dict(parts)
    parts['graph_wait'] = max(0.0, wall_s - sum(parts.values()))
    return {'sim_wall_s': round(wall_s, 3),
            **{f'wall_{k}_ms_per_frame': round(v * 1e3 / frames, 3) for k, v in parts.items()}}
