"""The project's Fast DDS profile: added for the graph, taken by an image publisher alone."""
import os
import xml.etree.ElementTree as ET

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


def _duration_s(element: ET.Element, ns: dict) -> float:
    sec = element.find('p:sec', ns)
    nanosec = element.find('p:nanosec', ns)
    return (int(sec.text) if sec is not None else 0) + \
        (int(nanosec.text) * 1e-9 if nanosec is not None else 0.0)


def test_dds_profile_unmatches_a_dead_reader_within_seconds():
    """A SIGKILLed node's readers cost their publishers until the lease ends (fastdds.xml)."""
    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(dds_env_overrides({})[FASTDDS_PROFILE_ENV]).getroot()
    discovery = root.find('.//p:participant/p:rtps/p:builtin/p:discovery_config', ns)
    lease_s = _duration_s(discovery.find('p:leaseDuration', ns), ns)
    announce_s = _duration_s(discovery.find('p:leaseAnnouncement', ns), ns)
    assert 0.0 < lease_s <= 4.0             # dead readers unmatched before they cost (measured)
    assert 0.0 < announce_s <= lease_s / 3  # two late announcements do not drop a live node
