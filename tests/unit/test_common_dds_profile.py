"""The project's Fast DDS profile: added for the graph, taken by an image publisher alone."""
import importlib
import os
import xml.etree.ElementTree as ET

import pytest

from ibvs_common.dds_profile import (dds_env_overrides, FASTDDS_PROFILE_ENV, FASTDDS_RMW,
                                     RMW_ENV, use_dds_profile_here)


def test_dds_profile_is_added_unless_the_user_chose_one():
    path = dds_env_overrides({})[FASTDDS_PROFILE_ENV]
    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(path).getroot()
    segment = int(root.find('.//p:transport_descriptor/p:segment_size', ns).text)
    assert segment >= 10 * 752 * 480        # room for several image pairs in flight
    assert dds_env_overrides({FASTDDS_PROFILE_ENV: '/mine.xml'}) == {}
    assert dds_env_overrides({RMW_ENV: 'rmw_cyclonedds_cpp'}) == {}
    assert dds_env_overrides({RMW_ENV: FASTDDS_RMW}) == {FASTDDS_PROFILE_ENV: path}


def test_use_dds_profile_here_sets_it_once_and_keeps_the_users(monkeypatch):
    monkeypatch.delenv(FASTDDS_PROFILE_ENV, raising=False)
    monkeypatch.delenv(RMW_ENV, raising=False)
    set_here = use_dds_profile_here()
    assert os.environ[FASTDDS_PROFILE_ENV] == set_here[FASTDDS_PROFILE_ENV]
    assert set_here[FASTDDS_PROFILE_ENV].endswith('fastdds.xml')
    monkeypatch.setenv(FASTDDS_PROFILE_ENV, '/mine.xml')     # the user's choice stays
    assert use_dds_profile_here() == {} and os.environ[FASTDDS_PROFILE_ENV] == '/mine.xml'


class _InitReached(Exception):
    pass


@pytest.mark.parametrize('module', ['ibvs_sim.sim_node', 'ibvs_sim.px4_sim_node',
                                    'ibvs_bringup.bag_player_node'])
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

    monkeypatch.setattr(mod.rclpy, 'init', init)
    with pytest.raises(_InitReached):
        mod.main([])
    assert seen['profile'] and seen['profile'].endswith('fastdds.xml')
