"""Plots and ground-truth features from a synthetic trajectory (no ROS)."""
from ibvs_harness import plots, report
from ibvs_common.core.config import load_pad_layout
from ibvs_sim.core.world import load_world
import numpy as np
import pytest


@pytest.fixture(scope='module')
def world():
    return load_world()


def _synthetic_log(world) -> report.RunLog:
    """Straight to the window centre, through it, then down onto the pad."""
    log = report.RunLog()
    start = np.array([-2.0, 0.1, -1.82])
    through = np.array([0.3, 0.0, -1.6])
    pad = np.array([0.0, 0.0, -0.1])
    ts = np.linspace(0.0, 20.0, 401)
    for t in ts:
        if t < 10.0:
            p = start + (through - start) * t / 10.0
            v = (through - start) / 10.0
        else:
            p = through + (pad - through) * (t - 10.0) / 10.0
            v = (pad - through) / 10.0
        log.add_truth(t, p, v, [0.0, 0.02, 0.0], [0.0, 0.0, 0.01])
        log.add_vector('force', t, [0.0, 0.0, -16.44])
        log.add_vector('flow_down', t, v / max(0.05, -p[2]))
    for t, m in ((0.0, 0), (1.0, 1), (8.0, 2), (11.0, 3), (19.5, 4)):
        log.add_mode(t, m)
    assert not log.add_mode(20.0, 4)          # unchanged mode is not a transition
    return log


def test_flow_truth_is_velocity_over_plane_distance(world):
    front, down = report.flow_truth(np.array([[-2.0, 0.0, -1.5], [1.0, 0.0, -0.02]]),
                                    np.array([[1.0, 0.0, 0.0], [0.0, 0.5, 0.0]]), world)
    np.testing.assert_allclose(front[0], [1.0 / 1.5, 0, 0])      # wall at x = -0.5
    np.testing.assert_allclose(down[0], [1.0 / 1.5, 0, 0])       # floor at z = 0
    np.testing.assert_allclose(front[1], [0, 0.5 / 2.0, 0])      # back wall at x = 3
    assert np.all(np.isnan(down[1]))                             # 2 cm: undefined


def test_window_and_pad_feature_truth(world):
    xi = np.array([[-2.0, 0.1, -1.82], [0.5, 0.0, -1.0]])
    q = report.q_w_bar_truth(xi, world)
    # far from the window alpha_w = 1: q_w_bar = (xi - window centre) / distance to the wall
    np.testing.assert_allclose(q[0], np.array([-1.5, 0.1, -0.22]) / 1.5, atol=1e-9)
    assert np.all(np.isnan(q[1]))
    qt = report.q_t_truth(np.array([[0.0, 0.0, -1.0], [-2.0, 0.0, -1.0]]), load_pad_layout(),
                          world)
    assert abs(qt[0, 0]) < 1e-12 and abs(qt[0, 1]) < 1e-12 and qt[0, 2] < -0.9
    assert np.all(np.isnan(qt[1]))                               # before the crossing


def test_named_vector_accepts_the_usual_namings():
    names = ['alpha_w', 'q_t_x', 'q_t_y', 'q_t_z', 'phi_t.x', 'phi_t.y', 'phi_t.z']
    values = [0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    np.testing.assert_allclose(report.named_vector(names, values, 'q_t'), [1, 2, 3])
    np.testing.assert_allclose(report.named_vector(names, values, 'phi_t'), [4, 5, 6])
    assert report.named_vector(names, values, 'q_w_bar') is None


def test_every_figure_is_written_from_a_synthetic_run(world, tmp_path):
    pad = load_pad_layout()
    data = report.run_data(_synthetic_log(world), world, pad)
    assert data.modes[0] == (0.0, 0) and data.modes[-1] == (19.5, 4)
    # the scene to scale: the wall's face in its plane, the band around the window, the pad
    assert np.all(data.wall_corners_I[:, 0] == world.wall_x)
    assert np.ptp(data.wall_corners_I[:, 1]) == pytest.approx(np.ptp(world.wall_y_range))
    assert np.ptp(data.window_outer_corners_I[:, 1]) == pytest.approx(
        world.window.width + 2 * world.window.frame_band)
    biggest = max(pad.groups, key=lambda g: g.c)
    assert data.pad_half_side == pytest.approx(
        biggest.c + biggest.side / 2 + pad.quiet_zone * biggest.side)
    paths = plots.plot_run(data, str(tmp_path))
    names = {p.split('/')[-1] for p in paths}
    assert names == {'position_mode.png', 'velocity.png', 'force.png', 'angular_velocity.png',
                     'euler.png', 'flow_front.png', 'flow_down.png', 'q_w_bar.png', 'q_t.png',
                     'trajectory_3d.png'}
    for p in paths:
        head = open(p, 'rb').read(8)
        assert head == b'\x89PNG\r\n\x1a\n' and len(open(p, 'rb').read()) > 5000


def test_missing_series_skip_their_figures(tmp_path):
    data = plots.RunData(series={'velocity': plots.TimeSeries.of([0, 1], [[0, 0, 0], [1, 0, 0]]),
                                 'force': plots.TimeSeries.of([], [])})
    paths = plots.plot_run(data, str(tmp_path))
    assert [p.split('/')[-1] for p in paths] == ['velocity.png']


def test_summary_json_is_written_without_nan(tmp_path):
    path = tmp_path / 'r' / 'summary.json'
    report.write_json(str(path), {'a': float('nan'), 'b': [np.float64(1.5)], 'c': {'d': 2}})
    assert path.read_text().split() == ['{', '"a":', 'null,', '"b":', '[', '1.5', '],',
                                        '"c":', '{', '"d":', '2', '}', '}']
