"""The image publishers (sim, PX4 sim, bag player) take the project's DDS profile by themselves."""
import importlib
import os

import pytest

from ibvs_common import spin
from ibvs_common.dds_profile import FASTDDS_PROFILE_ENV, RMW_ENV


class _InitReached(Exception):
    pass


@pytest.mark.parametrize('module', ['ibvs_sim.sim_node', 'ibvs_sim.px4_sim_node',
                                    'ibvs_harness.bag_player_node'])
def test_an_image_publisher_started_alone_takes_the_profile_before_rclpy_init(module,
                                                                              monkeypatch):
    """`ros2 run` of the sim or the bag player: the profile is set before the participant."""
    mod = importlib.import_module(module)
    monkeypatch.delenv(FASTDDS_PROFILE_ENV, raising=False)
    monkeypatch.delenv(RMW_ENV, raising=False)
    seen = {}

    def init(*args, **kwargs):
        seen['profile'] = os.environ.get(FASTDDS_PROFILE_ENV)
        raise _InitReached

    monkeypatch.setattr(spin.rclpy, 'init', init)
    with pytest.raises(_InitReached):
        mod.main([])
    assert seen['profile'] and seen['profile'].endswith('fastdds.xml')
