"""scripts/static_tf.py: the cameras' mounts as tf2_ros commands, in base_link's FLU."""
from pathlib import Path
import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / 'scripts'))
from static_tf import static_tf_commands  # noqa: E402


def value(cmd: str, name: str) -> float:
    parts = cmd.split()
    return float(parts[parts.index(name) + 1])


def test_the_down_cameras_optical_axis_points_down_in_base_link():
    cmd = next(c for c in static_tf_commands() if 'down_camera_optical_frame' in c)
    q = np.array([value(cmd, f'--q{a}') for a in 'wxyz'])
    w, x, y, z = q
    # rotation matrix of (w, x, y, z); its third column is the optical z axis in base_link
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    assert np.allclose(R[:, 2], [0.0, 0.0, -1.0])        # FLU: down is -z
    assert '--frame-id base_link' in cmd and np.isclose(np.linalg.norm(q), 1.0, atol=1e-5)
