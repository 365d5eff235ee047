"""The cameras' mounts as static transforms ``base_link`` -> optical frame (ROS-free).

What ``/tf_static`` carries so that RViz and Foxglove place the cameras on the vehicle
(docs/interfaces.md "Frames"). One transform per camera of vehicle.yaml: parent
``base_link`` (the ROS body frame, FLU), child the camera's ``frame_id`` (its optical frame:
z along the optical axis, x right, y down in the image), from the camera's ``R_BC`` (optical
-> body FRD) and ``t_BC`` (optical centre in body FRD, m). The conversion FRD -> FLU is
frames.py's (:func:`~ibvs_common.core.frames.camera_mount_in_base_link`).

Convention (tf2, REP-103): the transform parent -> child holds the child frame's pose in the
parent: its ``translation`` is the child's origin expressed in the parent (m) and its
rotation maps child-frame coordinates into the parent frame,
``x_base_link = R(q) x_optical + translation``. Quaternions in ROS message order
(x, y, z, w), unit, w >= 0.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ibvs_common.core.config import CameraConfig
from ibvs_common.core.frames import BASE_FRAME, camera_mount_in_base_link


@dataclass(frozen=True)
class StaticTransform:
    """One static transform parent -> child (the module doc's convention)."""

    parent: str                 # frame_id of the parent frame
    child: str                  # frame_id of the child frame
    translation: np.ndarray     # (3,) m, the child's origin in the parent frame
    q_xyzw: np.ndarray          # (4,) unit quaternion (x, y, z, w): child -> parent coordinates


def camera_transforms(cameras: Iterable[CameraConfig]) -> list[StaticTransform]:
    """Return ``base_link`` -> ``<frame_id>`` for each camera, in the order given.

    ``cameras``: e.g. ``load_vehicle().cameras.values()``. Raises ValueError when two
    cameras share a ``frame_id`` (tf2 would keep only one of them).
    """
    out: list[StaticTransform] = []
    for cam in cameras:
        if any(t.child == cam.frame_id for t in out):
            raise ValueError(f'two cameras have the frame_id {cam.frame_id!r}')
        translation, q_xyzw = camera_mount_in_base_link(cam.R_BC, cam.t_BC)
        out.append(StaticTransform(BASE_FRAME, cam.frame_id, translation, q_xyzw))
    return out
