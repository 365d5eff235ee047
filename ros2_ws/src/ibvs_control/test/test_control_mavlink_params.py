"""AutopilotParams: which autopilot parameters the bridge reads, when, and what they imply."""
import pytest

from ibvs_control.mavlink.hover import HoverThrustSeed
from ibvs_control.mavlink.params import (ADVISORY_PARAM_READS, AutopilotParams, Changed)
from ibvs_control.mavlink.sequencer import Autopilot

OURS = 245          # the bridge's MAVLink system id


def params(autopilot, use_autopilot=True, configured=0.5):
    p = AutopilotParams(HoverThrustSeed(configured, use_autopilot), OURS, retry_s=0.5,
                        timeout_s=3.0)
    p.autopilot = autopilot
    return p


def test_px4_reads_its_hover_thrust_with_retries_and_the_advisory_failsafe_pair():
    p = params(Autopilot.PX4)
    assert p.missing() == ['MPC_THR_HOVER']
    reads, changed = p.due(0.0)
    assert reads == ['MPC_THR_HOVER', 'COM_OF_LOSS_T', 'COM_OBL_RC_ACT'] and not changed
    assert p.due(0.3) == ([], Changed.NOTHING)            # retried only every 0.5 s
    assert p.due(0.5)[0] == reads
    # the name comes NUL-padded as bytes, as pymavlink gives it
    assert p.on_param(b'MPC_THR_HOVER\x00\x00\x00', 0.42) == Changed.SEED
    assert p.seed.value == 0.42 and p.missing() == []
    assert p.pop_events() == [('info', 'hover thrust seed 0.420 from MPC_THR_HOVER')]
    assert p.due(1.0)[0] == ['COM_OF_LOSS_T', 'COM_OBL_RC_ACT']


def test_an_unanswered_hover_parameter_falls_back_to_the_configured_value_at_the_time_out():
    p = params(Autopilot.PX4, configured=0.47)
    p.due(0.0)
    assert p.due(2.9)[1] == Changed.NOTHING and p.seed.value is None and not p.timed_out(2.9)
    reads, changed = p.due(3.0)
    assert changed == Changed.SEED and p.timed_out(3.0)
    assert p.seed.value == 0.47 and 'did not answer' in p.seed.source
    assert p.due(3.5) == (['COM_OF_LOSS_T', 'COM_OBL_RC_ACT'], Changed.NOTHING)


def test_nothing_is_read_before_the_autopilot_is_known():
    p = params(None)
    assert p.missing() == [] and p.due(0.0) == ([], Changed.NOTHING)


@pytest.mark.parametrize('boost, boosted', [(1, True), (0, False), (2, True)])
def test_ardupilot_angle_boost_says_who_compensates_the_tilt(boost, boosted):
    p = params(Autopilot.ARDUPILOT, use_autopilot=False)
    assert p.missing() == ['GUID_OPTIONS', 'ATC_ANGLE_BOOST']
    assert p.on_param('ATC_ANGLE_BOOST', float(boost)) == Changed.TILT_BOOST
    assert p.tilt_boosted_by_autopilot is boosted
    text = p.pop_events()[0][1]
    assert ('vertical component' in text) is boosted and ('|F|' in text) is not boosted
    assert p.on_param('ATC_ANGLE_BOOST', 0.0 if boost else 1.0) == Changed.NOTHING   # once
    assert p.on_param('GUID_OPTIONS', 8.0) == Changed.NOTHING and p.guid_options == 8
    assert p.missing() == []


def test_ardupilot_angle_boost_unread_assumes_the_default_one():
    p = params(Autopilot.ARDUPILOT, use_autopilot=False)
    p.on_param('GUID_OPTIONS', 8.0)
    p.due(0.0)
    _, changed = p.due(3.0)
    assert changed == Changed.TILT_BOOST and p.angle_boost == 1 and p.tilt_boosted_by_autopilot
    assert "assuming ArduPilot's default 1" in p.pop_events()[0][1]


@pytest.mark.parametrize('action, timeout, failsafe, levels', [
    (4, 1.0, True, ['info']),                 # Land mode: what a vehicle without GPS needs
    (0, 1.0, False, ['warn']),                # Position mode: needs a position estimate
    (4, 3.0, True, ['info', 'warn']),         # a long time-out is warned about too
])
def test_px4_offboard_loss_is_assessed_once_both_are_read(action, timeout, failsafe, levels):
    p = params(Autopilot.PX4, use_autopilot=False)
    p.on_param('COM_OBL_RC_ACT', float(action))
    assert p.dead_bridge_failsafe is None                 # one of the pair: not yet
    p.on_param('COM_OF_LOSS_T', timeout)
    assert p.dead_bridge_failsafe is failsafe
    events = p.pop_events()
    assert [level for level, _ in events] == levels
    if not failsafe:
        assert 'needs a position estimate' in events[0][1]


@pytest.mark.parametrize('enabled, gcs, failsafe', [(5, OURS, True), (0, OURS, False),
                                                    (5, 255, False)])
def test_ardupilot_gcs_failsafe_lands_only_for_this_bridge(enabled, gcs, failsafe):
    p = params(Autopilot.ARDUPILOT, use_autopilot=False)
    p.on_param('FS_GCS_ENABLE', float(enabled))
    p.on_param('SYSID_MYGCS', float(gcs))
    assert p.dead_bridge_failsafe is failsafe
    level, text = p.pop_events()[0]
    assert level == ('info' if failsafe else 'warn')
    if gcs != OURS:
        assert f'SYSID_MYGCS = {gcs} is not this bridge' in text


@pytest.mark.parametrize('name, value, warned', [
    ('GUID_TIMEOUT', 3.0, True), ('GUID_TIMEOUT', 0.5, False), ('GUID_TIMEOUT', 1.0, False),
    ('FS_GCS_TIMEOUT', 5.0, True), ('FS_GCS_TIMEOUT', 2.0, False)])
def test_ardupilot_dead_bridge_timeouts_are_read_and_long_ones_warned(name, value, warned):
    """GUID_TIMEOUT (the last target flown) and FS_GCS_TIMEOUT (then coasting, before
    LAND) are read with the pair, and a value over the advised limit is warned about."""
    p = params(Autopilot.ARDUPILOT, use_autopilot=False)
    assert name in p.due(0.0)[0]                             # asked for, advisory
    p.on_param(name, value)
    assert p.dead_bridge_params[name] == value and p.dead_bridge_failsafe is None
    events = p.pop_events()
    assert [lv for lv, _ in events] == (['warn'] if warned else [])
    if warned:
        assert f'ArduPilot {name} = {value:g} s' in events[0][1]


def test_advisory_reads_stop_after_their_budget():
    p = params(Autopilot.PX4, use_autopilot=False)
    reads = [p.due(0.5 * k)[0] for k in range(ADVISORY_PARAM_READS + 3)]
    assert sum(bool(r) for r in reads) == ADVISORY_PARAM_READS
    assert reads[-1] == []
