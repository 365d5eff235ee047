"""The project's Fast DDS profile (ibvs_bringup/config/fastdds.xml) for the graph's processes.

config/fastdds.xml enlarges the shared-memory segment so that camera images are not lost: two
361 kB images in flight overflow Fast DDS's 0.5 MB default, and the segment that matters is
the image *publisher's* own (docs/bringup.md). The runner and the launch files add the profile
to their processes' environment (:func:`dds_env_overrides`); an image publisher started alone
(``ros2 run`` of the sim or the bag player) applies it to itself before ``rclpy.init``
(:func:`use_dds_profile_here`). A profile the user set, or another RMW, is left alone.
"""
from __future__ import annotations

import os
from typing import Mapping

from ibvs_common.core.config import CONFIG_PACKAGE

DDS_PROFILE_FILE_NAME = 'fastdds.xml'
FASTDDS_PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'    # read by Fast DDS 2.x (Jazzy)
RMW_ENV, FASTDDS_RMW = 'RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp'


def dds_env_overrides(environ: Mapping[str, str] | None = None) -> dict:
    """Return the environment to add for the graph's processes: the project's Fast DDS profile.

    Nothing is added when a profile is already set or another RMW is chosen (``environ``:
    default ``os.environ``).
    """
    env = os.environ if environ is None else environ
    if env.get(FASTDDS_PROFILE_ENV) or env.get(RMW_ENV, FASTDDS_RMW) != FASTDDS_RMW:
        return {}
    from ament_index_python.packages import get_package_share_directory
    return {FASTDDS_PROFILE_ENV: os.path.join(get_package_share_directory(CONFIG_PACKAGE),
                                              'config', DDS_PROFILE_FILE_NAME)}


def use_dds_profile_here() -> dict:
    """Give this process the project's Fast DDS profile unless one is set; return what was set.

    Fast DDS reads the profile when the process's first participant is created: call this
    before ``rclpy.init``.
    """
    env = dds_env_overrides()
    os.environ.update(env)
    return env
