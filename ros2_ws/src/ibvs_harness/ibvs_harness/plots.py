"""The paper's simulation figures (section 5) from arrays, ROS-free (matplotlib Agg, PNG).

Input is a ``RunData``: named time series in the paper frame {I} (the whole-graph run and the
feature-level run both fill it). Every figure is drawn only if its series are present, so a run
without, e.g., optical flow still gets the other figures. Modes are shaded on every time plot.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use('Agg')
from matplotlib.patches import Patch  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402
import numpy as np  # noqa: E402

from ibvs_common.core.modes import Mode, mode_name  # noqa: E402

if TYPE_CHECKING:
    import numpy.typing as npt

MODE_COLOURS = {0: '#dddddd', 1: '#cfe2f3', 2: '#fce5cd', 3: '#d9ead3', 4: '#ead1dc',
                5: '#f4cccc'}
AXES = ('x', 'y', 'z')


@dataclass(frozen=True)
class TimeSeries:
    """Samples ``v`` (N, k) at times ``t`` (N,), seconds of sim time."""

    t: np.ndarray
    v: np.ndarray

    @staticmethod
    def of(t: npt.ArrayLike, v: npt.ArrayLike) -> 'TimeSeries':
        """Build from sequences; an empty sequence gives shape (0, k) or (0, 1)."""
        t = np.asarray(t, dtype=float).reshape(-1)
        v = np.asarray(v, dtype=float)
        v = v.reshape(len(t), -1) if len(t) else v.reshape(0, v.shape[-1] if v.ndim > 1 else 1)
        return TimeSeries(t, v)

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class RunData:
    """What the figures need: named series, modes and the scene.

    Series names (all {I}, SI):

    position, velocity (m, m/s), euler (roll, pitch, yaw; rad), omega (body rates, rad/s),
    force (F, N), flow_front / flow_down (measured v/d, 1/s) and *_truth, q_w_bar and q_t
    (measured image features) and *_truth.
    """

    series: dict = field(default_factory=dict)
    modes: list = field(default_factory=list)          # [(t_start_s, mode)]
    window_corners_I: np.ndarray | None = None         # (4, 3) aperture corners
    pad_center_I: np.ndarray = field(default_factory=lambda: np.zeros(3))
    window_outer_corners_I: np.ndarray | None = None   # (4, 3) outer edge of the dark band
    wall_corners_I: np.ndarray | None = None           # (4, 3) the wall's face
    pad_half_side: float | None = None                 # m, the pad's half side (outer markers)

    def get(self, name: str) -> TimeSeries | None:
        """Return a non-empty series or None."""
        s = self.series.get(name)
        return s if s is not None and len(s) else None


def _shade_modes(ax, modes: list, t_end: float) -> None:
    for i, (t0, mode) in enumerate(modes):
        t1 = modes[i + 1][0] if i + 1 < len(modes) else t_end
        ax.axvspan(t0, t1, color=MODE_COLOURS.get(int(mode), '#eeeeee'), alpha=0.5, lw=0)


def _mode_legend(fig, modes: list) -> None:
    """Name the shading: one patch per mode of the run, in the order they came."""
    seen = list(dict.fromkeys(int(m) for _, m in modes))
    if not seen:
        return
    handles = [Patch(color=MODE_COLOURS.get(m, '#eeeeee'), alpha=0.5, label=mode_name(m))
               for m in seen]
    fig.legend(handles=handles, loc='lower center', ncol=len(handles), fontsize=8,
               frameon=False, title='modes (shading)', title_fontsize=8)


def _t_end(data: RunData) -> float:
    ends = [s.t[-1] for s in data.series.values() if len(s)]
    return max(ends) if ends else 1.0


def _vector_figure(data: RunData, path: str, title: str, unit: str, names: list,
                   labels: list | None = None, components=AXES) -> str | None:
    series = [(n, data.get(n)) for n in names]
    series = [(n, s) for n, s in series if s is not None]
    if not series:
        return None
    k = max(s.v.shape[1] for _, s in series)
    fig, axes = plt.subplots(k, 1, sharex=True, figsize=(8, 2.2 * k + 0.8), squeeze=False)
    t_end = _t_end(data)
    for i, ax in enumerate(axes[:, 0]):
        _shade_modes(ax, data.modes, t_end)
        for j, (n, s) in enumerate(series):
            if i < s.v.shape[1]:
                style = '--' if n.endswith('_truth') else '-'
                label = labels[names.index(n)] if labels else n
                ax.plot(s.t, s.v[:, i], style, lw=1.2, label=label)
        ax.set_ylabel(f'{components[i] if i < len(components) else i} [{unit}]')
        ax.grid(True, alpha=0.3)
    axes[0, 0].set_title(title)
    axes[0, 0].legend(loc='best', fontsize=8)
    axes[-1, 0].set_xlabel('t [s]')
    _mode_legend(fig, data.modes)
    fig.tight_layout(rect=(0, 0.07 if data.modes else 0, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _position_figure(data: RunData, path: str) -> str | None:
    pos = data.get('position')
    if pos is None:
        return None
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8, 9))
    t_end = _t_end(data)
    for i, ax in enumerate(axes[:3]):
        _shade_modes(ax, data.modes, t_end)
        ax.plot(pos.t, pos.v[:, i], lw=1.2)
        ax.set_ylabel(f'{AXES[i]}_I [m]')
        ax.grid(True, alpha=0.3)
    if data.modes:
        ts = [m[0] for m in data.modes] + [t_end]
        ms = [m[1] for m in data.modes] + [data.modes[-1][1]]
        axes[3].step(ts, ms, where='post')
    axes[3].set_yticks([int(m) for m in Mode], [m.name for m in Mode], fontsize=7)
    axes[3].set_ylabel('mode')
    axes[3].set_xlabel('t [s]')
    axes[0].set_title('Position xi and mode')
    _mode_legend(fig, data.modes)
    fig.tight_layout(rect=(0, 0.06 if data.modes else 0, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _trajectory_figure(data: RunData, path: str) -> str | None:
    pos = data.get('position')
    if pos is None:
        return None
    fig = plt.figure(figsize=(8, 6))
    ax = fig.add_subplot(projection='3d')
    p = pos.v
    # plot with z up (-z_I) for readability
    ax.plot(p[:, 0], p[:, 1], -p[:, 2], lw=1.5, label='trajectory')
    ax.scatter([p[0, 0]], [p[0, 1]], [-p[0, 2]], marker='o', label='start')
    ax.scatter([p[-1, 0]], [p[-1, 1]], [-p[-1, 2]], marker='x', label='end')
    drawn = [p]

    def outline(corners, style, label, **kw):
        c = np.vstack([corners, corners[:1]])
        ax.plot(c[:, 0], c[:, 1], -c[:, 2], style, label=label, **kw)
        drawn.append(corners)

    if data.wall_corners_I is not None:
        w = data.wall_corners_I
        ax.add_collection3d(Poly3DCollection([list(zip(w[:, 0], w[:, 1], -w[:, 2]))],
                                             facecolor='#b0b0b0', alpha=0.15))
        outline(w, '-', 'wall', color='#808080', lw=1)
    if data.window_outer_corners_I is not None:
        outline(data.window_outer_corners_I, '-', 'dark band', color='#404040', lw=1)
    if data.window_corners_I is not None:
        outline(data.window_corners_I, 'k-', 'window', lw=2)
    pc = data.pad_center_I
    if data.pad_half_side:
        h = data.pad_half_side
        outline(pc + np.array([[h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0], [-h, h, 0.0]]), 'g-',
                'pad', lw=1.5)
    else:
        ax.scatter([pc[0]], [pc[1]], [-pc[2]], marker='s', color='g', label='pad')
    # to scale: the same metres on the three axes
    pts = np.vstack(drawn)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-3)))
    ax.set_xlabel('x_I [m]')
    ax.set_ylabel('y_I [m]')
    ax.set_zlabel('height -z_I [m]')
    ax.set_title('3-D trajectory through the window (to scale)')
    ax.legend(loc='upper left', fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_run(data: RunData, out_dir: str) -> list[str]:
    """Write the figures of ``data`` as PNG files into ``out_dir``; return their paths."""
    os.makedirs(out_dir, exist_ok=True)

    def p(name: str) -> str:
        return os.path.join(out_dir, name)

    made = [
        _position_figure(data, p('position_mode.png')),
        _vector_figure(data, p('velocity.png'), 'Velocity v', 'm/s', ['velocity']),
        _vector_figure(data, p('force.png'), 'Virtual control input F', 'N', ['force']),
        _vector_figure(data, p('angular_velocity.png'), 'Angular velocity Omega', 'rad/s',
                       ['omega']),
        _vector_figure(data, p('euler.png'), 'Euler angles', 'rad', ['euler'],
                       components=('roll', 'pitch', 'yaw')),
        _vector_figure(data, p('flow_front.png'), 'Translational optical flow, window (front)',
                       '1/s', ['flow_front', 'flow_front_truth'], ['measured', 'ground truth']),
        _vector_figure(data, p('flow_down.png'), 'Translational optical flow, landing (down)',
                       '1/s', ['flow_down', 'flow_down_truth'], ['measured', 'ground truth']),
        _vector_figure(data, p('q_w_bar.png'), 'Image feature q_w_bar', '-',
                       ['q_w_bar', 'q_w_bar_truth'], ['measured', 'ground truth']),
        _vector_figure(data, p('q_t.png'), 'Image feature q_t', '-', ['q_t', 'q_t_truth'],
                       ['measured', 'ground truth']),
        _trajectory_figure(data, p('trajectory_3d.png')),
    ]
    return [m for m in made if m]
