"""Clearance geometry and the summary.json evaluation against hand-computed values."""
import numpy as np
import pytest

from ibvs_sim.core.world import load_world
from ibvs_sim.core.contacts import min_clearance, obstacle_clearance, cylinder_sdf
from ibvs_sim.core.evaluation import evaluate_run

W = load_world()
R, H = 0.33, 0.20


def test_cylinder_sdf_hand_values():
    xi = np.zeros(3)
    assert cylinder_sdf([1.0, 0, 0], xi, R, H) == pytest.approx(0.67)
    assert cylinder_sdf([0, 0, 0.5], xi, R, H) == pytest.approx(0.4)
    assert cylinder_sdf([0.33 + 0.3, 0, 0.1 + 0.4], xi, R, H) == pytest.approx(0.5)
    assert cylinder_sdf([0.0, 0.2, 0], xi, R, H) == pytest.approx(-0.1)


def test_clearances_in_the_reference_world():
    # facing solid wall 1 m away, far from the aperture
    c, s = min_clearance(np.array([-1.5, 2.0, -1.6]), W, R, H)
    assert s == 'wall' and c == pytest.approx(1.0 - R)
    # centred in the aperture, in the wall plane: nearest frame edges are the top and bottom
    # (0.5 m, minus half the envelope height) and the sides (0.6 m minus the radius)
    c, s = obstacle_clearance(np.array([-0.5, 0.0, -1.6]), W, R, H)
    assert s == 'window_frame' and c == pytest.approx(min(0.6 - R, 0.5 - H / 2))
    # in the plane, 0.4 m right of centre: right edge at 0.2 m, radius 0.33 -> contact; the
    # signed distance of the edge point inside the cylinder is to its nearest face, a cap
    c, _ = obstacle_clearance(np.array([-0.5, 0.4, -1.6]), W, R, H)
    assert c < 0.0 and c == pytest.approx(max(0.2 - R, -H / 2))
    # 0.2 m before the plane, 0.4 m right: distance to the edge line hypot(0.2, 0.2) - r
    c, _ = obstacle_clearance(np.array([-0.7, 0.4, -1.6]), W, R, H)
    assert c == pytest.approx(np.hypot(0.2, 0.2) - R)
    # floor
    c, s = min_clearance(np.array([0.0, 0.0, -0.15]), W, R, H)
    assert s == 'floor' and c == pytest.approx(0.05)


def straight_run(y_offset=0.0, land_at=(0.0, 0.0), touchdown_speed=0.3):
    """Fly a piecewise-straight line through the window to the pad, sampled at 100 Hz."""
    pts = [np.array([-2.0, y_offset, -1.6]), np.array([0.0 + land_at[0], land_at[1], -1.6]),
           np.array([land_at[0], land_at[1], 0.0])]
    t, xi, v = [], [], []
    tt = 0.0
    for a, b, speed in ((pts[0], pts[1], 0.25), (pts[1], pts[2], touchdown_speed)):
        n = int(np.linalg.norm(b - a) / speed / 0.01)
        for k in range(n):
            t.append(tt)
            xi.append(a + (b - a) * k / n)
            v.append((b - a) / np.linalg.norm(b - a) * speed)
            tt += 0.01
    return np.array(t), np.array(xi), np.array(v)


def test_evaluation_of_a_good_run():
    t, xi, v = straight_run()
    s = evaluate_run(t, xi, v, W, R, H, [(0, 0.0), (1, 0.5)])
    assert s['success']
    assert s['window']['crossing_offset_m'] == pytest.approx([0.0, 0.0], abs=1e-9)
    assert s['window']['crossing_speed_mps'] == pytest.approx(0.25)
    # closest approach: the descent to the pad, 0.5 m beyond the wall, minus the radius
    assert s['window']['min_clearance_m'] == pytest.approx(0.5 - R, abs=1e-3)
    assert s['landing']['touchdown_speed_mps'] == pytest.approx(0.3)
    assert s['landing']['error_m'] == pytest.approx(0.0, abs=1e-9)
    assert s['modes'][1] == {'mode': 1, 't_start_s': 0.5}
    # duration counts from sim time 0, also when the first samples were not heard
    late = evaluate_run(t[5:], xi[5:], v[5:], W, R, H, [])
    assert late['duration_s'] == pytest.approx(s['duration_s'])
    assert evaluate_run(t[5:], xi[5:], v[5:], W, R, H, [], t_start_s=None)['duration_s'] \
        == pytest.approx(s['duration_s'] - (t[5] - t[0]))


def test_evaluation_catches_frame_contact_landing_error_and_hard_touchdown():
    t, xi, v = straight_run(y_offset=0.4, land_at=(0.0, 0.4))
    s = evaluate_run(t, xi, v, W, R, H, [])
    assert not s['success'] and s['window']['min_clearance_m'] < 0.0
    assert s['landing']['error_m'] == pytest.approx(0.4)
    t, xi, v = straight_run(touchdown_speed=0.8)
    assert not evaluate_run(t, xi, v, W, R, H, [])['success']


def test_touchdown_speed_from_the_sim_event_or_the_sample_before_contact():
    t, xi, v = straight_run(touchdown_speed=0.3)
    v[-1] = 0.0                     # the plant's floor stopped the body in the contact sample
    assert evaluate_run(t, xi, v, W, R, H, [])['landing']['touchdown_speed_mps'] == \
        pytest.approx(0.3)
    s = evaluate_run(t, xi, v, W, R, H, [], touchdown_speed_mps=0.7)
    assert s['landing']['touchdown_speed_mps'] == 0.7 and not s['success']
