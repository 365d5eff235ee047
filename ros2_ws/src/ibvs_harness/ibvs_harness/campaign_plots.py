"""A campaign's plots: success against wind, the starts by outcome, the landing error CDF.

PNG files beside table.md; nothing when matplotlib does not import (it is optional on a
vehicle computer).
"""
from __future__ import annotations

import math
import os

import numpy as np

from ibvs_harness.campaign_stats import failure_cause


def write_plots(rows: list[dict], summaries: list[dict], out_dir: str) -> list[str]:
    """success_vs_wind.png, initial_positions.png, landing_error_cdf.png (empty: no matplotlib).

    Initial positions in a top view of {I} (m): y east to the right, x (the window normal,
    north) up, an arrow towards where the wind blows.
    """
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    written = []
    laws = sorted({r['law'] for r in rows})
    fig, ax = plt.subplots(figsize=(6, 4))
    for law in laws:
        rr = [r for r in rows if r['law'] == law]
        x = np.array([r['wind_level_mps2'] for r in rr])
        y = np.array([r['success_rate'] for r in rr]) * 100
        lo = np.array([r['success_ci95'][0] for r in rr]) * 100
        hi = np.array([r['success_ci95'][1] for r in rr]) * 100
        err = np.clip([y - lo, hi - y], 0.0, None)     # rounding: |p - bound| ~ 1e-14
        ax.errorbar(x, y, yerr=err, marker='o', capsize=3, label=law)
    ax.set_xlabel('wind level |Δ_h|/m (m/s²)')
    ax.set_ylabel('success (%), 95 % Wilson interval')
    ax.set_ylim(-2, 102)
    ax.grid(True, alpha=0.3)
    ax.legend()
    written.append(_save(fig, out_dir, 'success_vs_wind.png'))

    keys = sorted({(s['run']['law'], s['run']['wind_level_mps2']) for s in summaries})
    causes = sorted({failure_cause(s) or 'success' for s in summaries},
                    key=lambda c: (c != 'success', c))
    colours = {c: plt.get_cmap('tab10')(i) for i, c in enumerate(causes)}
    ncol = min(4, len(keys))
    nrow = int(math.ceil(len(keys) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 3.6 * nrow), squeeze=False)
    for ax, key in zip(axes.flat, keys):
        sel = [s for s in summaries if (s['run']['law'], s['run']['wind_level_mps2']) == key]
        for c in causes:
            mine = [s for s in sel if (failure_cause(s) or 'success') == c]
            p = np.array([s['run']['initial_position_I'] for s in mine]).reshape(-1, 3)
            if not len(p):
                continue
            ax.scatter(p[:, 1], p[:, 0], s=10, color=colours[c], label=c)
            if key[1] > 0.0:        # where the wind blows towards (east right, north up)
                psi = np.array([s['run']['wind_direction_rad'] for s in mine])
                ax.quiver(p[:, 1], p[:, 0], np.sin(psi), np.cos(psi), color=colours[c],
                          angles='xy', scale_units='xy', scale=25.0, width=0.004, alpha=0.6)
        ax.set_title(f'{key[0]}, {key[1]:g} m/s²', fontsize=9)
        ax.set_xlabel('y (m, east)')
        ax.set_ylabel('x (m, window normal)')
    for ax in list(axes.flat)[len(keys):]:
        ax.axis('off')
    handles = [plt.Line2D([], [], marker='o', ls='', color=colours[c]) for c in causes]
    fig.legend(handles, causes, loc='lower center', ncol=min(4, len(causes)), fontsize=8)
    fig.suptitle('initial positions (top view) by outcome, arrows: wind direction')
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    written.append(_save(fig, out_dir, 'initial_positions.png'))

    fig, ax = plt.subplots(figsize=(6, 4))
    for key in keys:
        e = np.sort([s['landing']['error_m'] for s in summaries
                     if (s['run']['law'], s['run']['wind_level_mps2']) == key
                     and s['landing'].get('landed') and s['landing'].get('error_m') is not None])
        n = sum(1 for s in summaries if (s['run']['law'], s['run']['wind_level_mps2']) == key)
        if len(e):
            ax.step(e * 100, np.arange(1, len(e) + 1) / n, where='post',
                    label=f'{key[0]}, {key[1]:g} m/s²')
    ax.axvline(10.0, color='k', ls='--', lw=0.8)
    ax.set_xlabel('landing error (cm)')
    ax.set_ylabel('fraction of all runs')
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    written.append(_save(fig, out_dir, 'landing_error_cdf.png'))
    return written


def _save(fig, out_dir: str, name: str) -> str:
    import matplotlib.pyplot as plt    # only once write_plots imported it
    path = os.path.join(out_dir, name)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
