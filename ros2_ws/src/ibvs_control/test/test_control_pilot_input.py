"""The pilot's mission switch: the bridge's reading of RC_CHANNELS, the supervisor's edges."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from ibvs_control.core.pilot_input import PilotAction, PilotInput, PilotInputWatch
from ibvs_control.mavlink.pilot_switch import PilotSwitch, PilotSwitchConfig

OFF, ON, UNKNOWN = PilotInput.OFF, PilotInput.ON, PilotInput.UNKNOWN


def rc(us_of: dict, chancount: int = 8):
    """An RC_CHANNELS-like message: channels of ``us_of`` (1-based), others 1500 or unused."""
    fields = {f'chan{i}_raw': (1500 if i <= chancount else 0xFFFF) for i in range(1, 19)}
    fields.update({f'chan{i}_raw': us for i, us in us_of.items()})
    return SimpleNamespace(chancount=chancount, rssi=255, **fields)


# --- the bridge: RC_CHANNELS -> switch position -------------------------------------------------

def test_hysteresis_on_at_and_above_on_us_off_at_and_below_off_us():
    sw = PilotSwitch(PilotSwitchConfig(channel=7, on_us=1700, off_us=1300))
    seen = []
    for t, us in enumerate((1500, 1300, 1500, 1699, 1700, 1500, 1301, 1300, 2000)):
        sw.on_rc_channels(rc({7: us}), float(t) * 0.1)
        seen.append(sw.value(float(t) * 0.1))
    # the band before any reading is no reading; then each side holds until the other
    assert seen == [UNKNOWN, OFF, OFF, OFF, ON, ON, ON, OFF, ON]


@pytest.mark.parametrize('msg', [rc({7: 0xFFFF}), rc({7: 0}), rc({7: 1900}, chancount=6)],
                         ids=['UINT16_MAX', 'zero', 'beyond chancount'])
def test_an_unused_channel_is_no_reading(msg):
    sw = PilotSwitch(PilotSwitchConfig(channel=7))
    sw.on_rc_channels(msg, 0.0)
    assert sw.value(0.0) == UNKNOWN and sw.invalid_readings == 1


def test_no_valid_reading_for_the_timeout_is_unknown_and_the_band_after_it_too():
    sw = PilotSwitch(PilotSwitchConfig(channel=3, timeout_s=1.0))
    sw.on_rc_channels(rc({3: 1900}), 0.0)
    assert sw.value(1.0) == ON and sw.value(1.01) == UNKNOWN
    sw.on_rc_channels(rc({3: 1500}), 2.0)            # back in the band: still unknown
    assert sw.value(2.0) == UNKNOWN


def test_a_release_is_off_until_the_switch_is_seen_off_rearm_does_not_end_it():
    sw = PilotSwitch(PilotSwitchConfig(channel=7))
    sw.on_rc_channels(rc({7: 1900}), 0.0)
    sw.release()
    sw.rearm()                                       # a switch is configured: only OFF ends it
    sw.on_rc_channels(rc({7: 1900}), 0.1)
    assert sw.value(0.1) == OFF
    sw.on_rc_channels(rc({7: 1100}), 0.2)
    sw.on_rc_channels(rc({7: 1900}), 0.3)
    assert sw.value(0.3) == ON


def test_without_a_switch_rc_is_ignored_and_a_release_lasts_until_rearm():
    sw = PilotSwitch(PilotSwitchConfig(channel=0))
    sw.on_rc_channels(rc({1: 1900}), 0.0)
    assert sw.value(0.0) == UNKNOWN and sw.invalid_readings == 0
    sw.release()
    assert sw.value(100.0) == OFF
    sw.rearm()
    assert sw.value(100.0) == UNKNOWN


@pytest.mark.parametrize('kw', [{'channel': 19}, {'channel': -1}, {'on_us': 1300, 'off_us': 1300},
                                {'timeout_s': 0.0}, {'rate_hz': float('nan')}])
def test_a_bad_switch_configuration_is_refused(kw):
    with pytest.raises(ValueError):
        PilotSwitchConfig(**kw)


# --- the supervisor: changes of ibvs/pilot_input -> start / abort -------------------------------

def actions(values):
    watch = PilotInputWatch()
    return [watch.on_input(v).name for v in values], watch


def test_off_then_on_starts_on_then_off_aborts():
    got, _ = actions([UNKNOWN, OFF, ON, ON, OFF, OFF])
    assert got == ['NONE', 'ABORT', 'START', 'NONE', 'ABORT', 'NONE']


def test_on_at_boot_starts_nothing_until_cycled():
    got, watch = actions([UNKNOWN, ON])
    assert got == ['NONE', 'NONE'] and watch.on_without_off
    assert watch.on_input(OFF) == PilotAction.ABORT and not watch.on_without_off
    assert watch.on_input(ON) == PilotAction.START


def test_an_rc_loss_between_keeps_the_last_known_position():
    # OFF, lost, back ON: the pilot moved it meanwhile -> start; ON, lost, back ON: nothing
    assert actions([OFF, UNKNOWN, ON])[0] == ['ABORT', 'NONE', 'START']
    assert actions([OFF, ON, UNKNOWN, ON])[0] == ['ABORT', 'START', 'NONE', 'NONE']


def test_a_value_outside_the_enum_is_refused():
    with pytest.raises(ValueError):
        PilotInputWatch().on_input(7)
