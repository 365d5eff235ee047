"""A campaign's statistics: success intervals, failure causes, the per-level table.

From the runs' summary.json dicts alone (docs/spec.md section 5), so a finished campaign can
be tabulated again without flying.
"""
from __future__ import annotations

import math
from typing import Callable, Iterable

from ibvs_common.core.modes import Mode
from ibvs_sim.core.evaluation import (
    MAX_DURATION_S, MAX_LANDING_ERROR_M, MAX_TOUCHDOWN_SPEED_MPS)
import numpy as np

Z_95 = 1.959963984540054          # standard normal quantile of 0.975


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (default 95 %); (0, 1) when n = 0.

    ``(p + z^2/2n -+ z sqrt(p (1 - p) / n + z^2 / 4n^2)) / (1 + z^2 / n)``, p = successes / n.
    """
    if n <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= n:
        raise ValueError(f'successes {successes} not in [0, {n}]')
    p = successes / n
    denom = 1.0 + z * z / n
    centre = p + z * z / (2 * n)
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4.0 * n * n))
    return max(0.0, (centre - half) / denom), min(1.0, (centre + half) / denom)


def failure_cause(summary: dict) -> str | None:
    """Why a run failed docs/spec.md section 5 (None: success), from its summary alone.

    In this order: 'collision before crossing' / 'collision after crossing' (envelope touched
    wall, frame or back wall), 'failsafe in <mode>' (the supervisor's, with the mode it left:
    'window' approach, 'crossing' (e.g. its timeout: no pad seen), 'landing'), 'floor before
    window' /
    'stalled before window' (never crossed; landed or not), 'no touchdown' (crossed, still
    flying at 60 s), 'landing error' (> 0.10 m), 'touchdown speed' (> 0.5 m/s),
    'duration' (> 60 s).
    """
    if summary.get('success'):
        return None
    w, ld = summary.get('window', {}), summary.get('landing', {})
    modes = [m.get('mode') for m in summary.get('modes', [])]
    clearance = w.get('min_clearance_m')
    if clearance is not None and clearance <= 0.0:
        return 'collision after crossing' if w.get('crossed') else 'collision before crossing'
    if modes and modes[-1] == int(Mode.FAILSAFE):
        before = Mode(modes[-2]).name.lower() if len(modes) > 1 else 'idle'
        return f'failsafe in {before}'
    if not w.get('crossed'):
        return 'floor before window' if ld.get('landed') else 'stalled before window'
    if not ld.get('landed'):
        return 'no touchdown'
    if ld.get('error_m') is None or ld['error_m'] > MAX_LANDING_ERROR_M:
        return 'landing error'
    if ld.get('touchdown_speed_mps') is None or \
            ld['touchdown_speed_mps'] > MAX_TOUCHDOWN_SPEED_MPS:
        return 'touchdown speed'
    if summary.get('duration_s', 0.0) > MAX_DURATION_S:
        return 'duration'
    return 'other'


def finite_stat(values: list, fn: Callable) -> float | None:
    """``fn`` of the finite values among ``values`` (None and NaN left out); None if none."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(fn(np.asarray(v))) if v else None


def aggregate(summaries: Iterable[dict]) -> list[dict]:
    """Per (law, level) rows of the campaign table from the runs' summary.json dicts.

    Success rate and its 95 % Wilson interval over all runs; clearance (m) min and median over
    the successes (the target is about every success); crossing speed (m/s) median and min
    over the runs that crossed; landing error (m) median and p95, touchdown speed (m/s) p95
    over the runs that crossed and touched down (failures included); failure causes counted.
    ``success_not_shutdown``: the successes whose last mode is not SHUTDOWN (docs/spec.md section
    5's numbers met, but the supervisor did not end the flight: e.g. a touchdown in LANDING
    that then failed safe; CI's whole-graph tests require the last modes 2, 3, 4).
    Percentiles: numpy's linear interpolation.
    """
    groups: dict = {}
    for s in summaries:
        r = s['run']
        groups.setdefault((r['law'], float(r['wind_level_mps2'])), []).append(s)
    rows = []
    for (law, level), runs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        n = len(runs)
        ok = [s for s in runs if s.get('success')]
        crossed = [s for s in runs if s['window'].get('crossed')]
        landed = [s for s in runs          # touchdowns on the far side, not blown-back ones
                  if s['landing'].get('landed') and s['window'].get('crossed')]
        lo, hi = wilson_interval(len(ok), n)
        causes: dict = {}
        for s in runs:
            c = failure_cause(s)
            if c is not None:
                causes[c] = causes.get(c, 0) + 1
        rows.append({
            'law': law, 'wind_level_mps2': level, 'runs': n, 'successes': len(ok),
            'success_rate': len(ok) / n if n else None, 'success_ci95': [lo, hi],
            'clearance_min_m': finite_stat([s['window']['min_clearance_m'] for s in ok], np.min),
            'clearance_median_m': finite_stat(
                [s['window']['min_clearance_m'] for s in ok], np.median),
            'crossing_speed_median_mps': finite_stat(
                [s['window']['crossing_speed_mps'] for s in crossed], np.median),
            'crossing_speed_min_mps': finite_stat(
                [s['window']['crossing_speed_mps'] for s in crossed], np.min),
            'landing_error_median_m': finite_stat(
                [s['landing']['error_m'] for s in landed], np.median),
            'landing_error_p95_m': finite_stat(
                [s['landing']['error_m'] for s in landed], lambda a: np.percentile(a, 95)),
            'touchdown_speed_p95_mps': finite_stat(
                [s['landing']['touchdown_speed_mps'] for s in landed],
                lambda a: np.percentile(a, 95)),
            'failure_causes': dict(sorted(causes.items(), key=lambda kv: -kv[1])),
            'success_not_shutdown': sum(1 for s in ok if not s.get('modes') or
                                        s['modes'][-1].get('mode') != int(Mode.SHUTDOWN)),
            'wall_time_mean_s': finite_stat([s['run'].get('wall_time_s') for s in runs], np.mean),
        })
    return rows


def format_table(rows: list[dict]) -> str:
    """Format the aggregate rows as a Markdown table (lengths in cm, speeds in m/s)."""
    def f(x: float | None, scale: float = 1.0, digits: int = 2) -> str:
        return '-' if x is None else f'{x * scale:.{digits}f}'
    lines = ['| law | wind (m/s²) | success | rate [95 % CI] | clearance min / median (cm) '
             '| crossing speed median [min] (m/s) | landing error median / p95 (cm) '
             '| touchdown p95 (m/s) | failures | successes not ending in SHUTDOWN |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lo, hi = r['success_ci95']
        causes = ', '.join(f'{k} {v}' for k, v in r['failure_causes'].items()) or '-'
        rate = '-' if r['success_rate'] is None else f"{100 * r['success_rate']:.1f} %"
        lines.append(
            f"| {r['law']} | {r['wind_level_mps2']:g} | {r['successes']} / {r['runs']} "
            f"| {rate} [{100 * lo:.1f}, {100 * hi:.1f}] "
            f"| {f(r['clearance_min_m'], 100, 1)} / {f(r['clearance_median_m'], 100, 1)} "
            f"| {f(r['crossing_speed_median_mps'])} [{f(r['crossing_speed_min_mps'])}] "
            f"| {f(r['landing_error_median_m'], 100, 1)} / "
            f"{f(r['landing_error_p95_m'], 100, 1)} "
            f"| {f(r['touchdown_speed_p95_mps'])} | {causes} "
            f"| {r.get('success_not_shutdown', '-')} |")
    return '\n'.join(lines) + '\n'
