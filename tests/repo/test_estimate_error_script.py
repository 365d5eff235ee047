"""scripts/estimate_error.py: the estimate's error against the truth in WINDOW, from a bag."""
import json
from pathlib import Path
import sys

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu

from ibvs_harness import bag
from ibvs_common.core.frames import (quat_from_rot, rot_map_base_from_R_IB, rot_x, rot_y, rot_z,
                                     vec_I_to_map)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / 'scripts'))
import estimate_error  # noqa: E402


def _set_q(q_msg, R_IB):
    q_msg.w, q_msg.x, q_msg.y, q_msg.z = (float(v) for v in quat_from_rot(
        rot_map_base_from_R_IB(R_IB)))


def _stamp(header, t):
    header.stamp.sec, header.stamp.nanosec = int(t), int(round((t - int(t)) * 1e9))


def write_run(run: Path, R_err: np.ndarray, t0: float = 100.0) -> None:
    """Truth yawed 0.3 rad, pitched 2 deg, y_I 0.1 -> -0.2 m over WINDOW [t0 + 1, t0 + 3]."""
    run.mkdir()
    (run / 'summary.json').write_text(json.dumps({'success': True, 'run': {'transitions': [
        f'mode IDLE -> WINDOW at t = {t0 + 1.0:.3f} s: start requested',
        f'mode WINDOW -> CROSSING at t = {t0 + 3.0:.3f} s: lost the window']}}))
    R_IB = rot_z(0.3) @ rot_y(np.radians(2.0))
    with bag.BagWriter(run / 'bag') as w:
        w.add_topic('imu/data', 'sensor_msgs/msg/Imu')
        w.add_topic('sim/ground_truth/odom', 'nav_msgs/msg/Odometry')
        for k in range(400):                              # 100 Hz for 4 s
            t = t0 + 0.01 * k
            y = 0.1 - 0.15 * min(max(t - t0 - 1.0, 0.0), 2.0)
            odom = Odometry()
            _stamp(odom.header, t)
            _set_q(odom.pose.pose.orientation, R_IB)
            p = vec_I_to_map(np.array([-1.0, y, -1.5]))
            odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z = (
                float(v) for v in p)
            imu = Imu()
            _stamp(imu.header, t + 0.002)                 # the IMU 2 ms later: still paired
            _set_q(imu.orientation, R_IB @ R_err)
            w.write('sim/ground_truth/odom', int(t * 1e9), serialize_message(odom))
            w.write('imu/data', int(t * 1e9), serialize_message(imu))


def test_the_estimate_error_is_read_as_a_body_rotation_over_window(tmp_path, capsys):
    write_run(tmp_path / 'run', rot_x(np.radians(1.7)))
    r = estimate_error.window_estimate_error(tmp_path / 'run')
    assert r['window_s'] == pytest.approx((101.0, 103.0))
    assert r['error_deg'] == pytest.approx((1.7, 0.0, 0.0), abs=1e-6)
    assert r['pairs'] == 201                              # 101.00 ... 103.00 s
    assert r['y_I_m'] == pytest.approx((0.1, -0.2), abs=1e-9)
    assert estimate_error.main([str(tmp_path / 'run'), str(tmp_path / 'none')]) == 0
    out = capsys.readouterr().out
    assert 'roll +1.70,' in out and '+0.100 -> -0.200 m' in out
    assert 'none: no WINDOW interval' in out


def test_only_the_first_window_interval_counts_and_a_run_without_one_gives_none():
    assert estimate_error.window_interval([
        'mode IDLE -> WINDOW at t = 1.000 s: start', 'mode WINDOW -> FAILSAFE at t = 2.5 s: x',
        'mode IDLE -> WINDOW at t = 9.000 s: again', 'mode WINDOW -> CROSSING at t = 9.5 s: y',
    ]) == (1.0, 2.5)
    assert estimate_error.window_interval(['mode IDLE -> WINDOW at t = 1.0 s: start']) is None


def test_the_increments_of_a_random_walk_error_grow_as_its_lag_s_square_root(tmp_path, capsys):
    """A synthetic error that steps by N(0, 0.05 deg) per 10 ms imu/data sample in roll only,
    the truth (50 Hz, rotating at 0.5 rad/s in yaw) interpolated to the IMU stamps: the
    structure function is 0.05 deg sqrt(lag / 10 ms) in roll (the random walk's closed form)
    and 0 in pitch and yaw (the interpolation of the truth adds nothing)."""
    from ibvs_common.core.frames import exp_so3
    run = tmp_path / 'walk'
    run.mkdir()
    rng = np.random.default_rng(4)
    step = np.radians(0.05)
    roll = np.cumsum(rng.normal(0.0, step, 2000))
    with bag.BagWriter(run / 'bag') as w:
        w.add_topic('imu/data', 'sensor_msgs/msg/Imu')
        w.add_topic('sim/ground_truth/odom', 'nav_msgs/msg/Odometry')
        for k in range(2000):                             # 20 s, imu 100 Hz, truth 50 Hz
            t = 100.0 + 0.01 * k
            R_IB = rot_z(0.5 * (t - 100.0)) @ rot_y(0.1)
            if k % 2 == 0:
                odom = Odometry()
                _stamp(odom.header, t)
                _set_q(odom.pose.pose.orientation, R_IB)
                w.write('sim/ground_truth/odom', int(t * 1e9), serialize_message(odom))
            imu = Imu()
            _stamp(imu.header, t)
            _set_q(imu.orientation, R_IB @ exp_so3(np.array([roll[k], 0.0, 0.0])))
            w.write('imu/data', int(t * 1e9), serialize_message(imu))
    stamps, errors = estimate_error.error_series(run / 'bag')
    assert len(stamps) >= 1990
    np.testing.assert_allclose(errors[:, 0], roll[:len(stamps)], atol=1e-6)
    assert np.max(np.abs(errors[:, 1:])) < 1e-3 * step
    inc = estimate_error.increment_std(stamps, errors, (0.01, 0.04, 0.16))
    for lag, (d, n) in inc.items():
        assert n > 1000
        assert d[0] == pytest.approx(step * np.sqrt(lag / 0.01), rel=0.1), lag
        assert d[1] < 1e-3 * step and d[2] < 1e-3 * step
    assert estimate_error.main(['--increments', str(run)]) == 0
    assert 'lag  0.02 s' in capsys.readouterr().out
