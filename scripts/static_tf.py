#!/usr/bin/env python3
"""Print the tf2_ros commands that publish the cameras' mounts (base_link -> optical frames).

The mode supervisor publishes these transforms on /tf_static itself (parameter
`publish_camera_tf`, when tf2_msgs is installed); for a graph without it (the venv's PyPI
wheels lack tf2_msgs, or `publish_camera_tf: false`), run the printed `ros2 run tf2_ros
static_transform_publisher` commands. From vehicle.yaml (default: the installed one): each
camera's mount R_BC (optical -> body FRD) and lever arm t_BC (m, body FRD), turned into
base_link's FLU (REP-103) by ``ibvs_common.core.camera_tf``, as the supervisor does.

Run: ``.venv/bin/python scripts/static_tf.py [--vehicle FILE]``.
"""
from __future__ import annotations

import argparse
import sys

from ibvs_common.core.camera_tf import camera_transforms
from ibvs_common.core.config import load_vehicle


def static_tf_commands(vehicle_file: str | None = None) -> list[str]:
    """Return one static_transform_publisher command per camera of the vehicle file."""
    out = []
    for tf in camera_transforms(load_vehicle(vehicle_file).cameras.values()):
        t, (x, y, z, w) = tf.translation, tf.q_xyzw
        out.append('ros2 run tf2_ros static_transform_publisher '
                   f'--x {t[0]:.4f} --y {t[1]:.4f} --z {t[2]:.4f} '
                   f'--qx {x:.6f} --qy {y:.6f} --qz {z:.6f} --qw {w:.6f} '
                   f'--frame-id {tf.parent} --child-frame-id {tf.child}')
    return out


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--vehicle', default=None, help='vehicle YAML (default: the installed one)')
    print('\n'.join(static_tf_commands(p.parse_args(argv).vehicle)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
