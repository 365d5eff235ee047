#!/usr/bin/env python3
"""Print the tf2_ros commands that publish the cameras' mounts (base_link -> optical frames).

The graph publishes no /tf_static (tf2_msgs is not among its dependencies); for RViz or
Foxglove on a Jazzy install, run the printed `ros2 run tf2_ros static_transform_publisher`
commands. From vehicle.yaml (default: the installed one): each camera's mount R_BC (optical ->
body FRD) and lever arm t_BC (m, body FRD), turned into base_link's FLU (REP-103).

Run: ``.venv/bin/python scripts/static_tf.py [--vehicle FILE]``.
"""
from __future__ import annotations

import argparse
import sys

from ibvs_common.core.config import load_vehicle
from ibvs_common.core.frames import quat_from_rot, R_FLU_FRD

BASE_FRAME = 'base_link'


def static_tf_commands(vehicle_file: str | None = None) -> list[str]:
    """Return one static_transform_publisher command per camera of the vehicle file."""
    out = []
    for cam in load_vehicle(vehicle_file).cameras.values():
        t = R_FLU_FRD @ cam.t_BC                       # the optical centre in base_link FLU
        w, x, y, z = quat_from_rot(R_FLU_FRD @ cam.R_BC)   # optical -> base_link FLU
        out.append('ros2 run tf2_ros static_transform_publisher '
                   f'--x {t[0]:.4f} --y {t[1]:.4f} --z {t[2]:.4f} '
                   f'--qx {x:.6f} --qy {y:.6f} --qz {z:.6f} --qw {w:.6f} '
                   f'--frame-id {BASE_FRAME} --child-frame-id {cam.frame_id}')
    return out


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--vehicle', default=None, help='vehicle YAML (default: the installed one)')
    print('\n'.join(static_tf_commands(p.parse_args(argv).vehicle)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
