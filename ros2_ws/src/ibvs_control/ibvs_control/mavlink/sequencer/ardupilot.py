"""ArduCopter's part of the engage sequences: GUID_OPTIONS, GUIDED_NOGPS, LAND, the pre-arm bit.

ArduCopter reads SET_ATTITUDE_TARGET's thrust as thrust only with ``GUID_OPTIONS`` bit 3 set
(otherwise as a climb rate): without it, or unread, the bridge refuses to fly. The offboard
mode is GUIDED_NOGPS (custom_mode 20), the land mode LAND (9); a GUIDED mode obeys setpoints at
once, so they stream from the switch on only. The switch waits, as the arming does, for the
pre-arm bit (SYS_STATUS): a not-yet-ready ArduCopter still sets modes of its own (it applies its
RC mode switch when its RC input first turns valid, ~1.5 s after boot, which would replace a
GUIDED_NOGPS set just before, and the bridge would rightly take that for a pilot's takeover).
No pre-arm report yet: it waits up to ``armable_unknown_wait_s``, then tries. Forces lost: LAND.
"""
from __future__ import annotations

from ibvs_control.mavlink.sequencer.common import (
    Autopilot, AutopilotStrategy, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, SequencerConfig,
    SequencerInputs, SwitchWait)

ARDUCOPTER_MODE_GUIDED_NOGPS = 20      # ArduCopter custom_mode
ARDUCOPTER_MODE_LAND = 9
GUID_OPTIONS_THRUST_BIT = 1 << 3       # GUID_OPTIONS bit 3: "SetAttitudeTarget interprets
#                                        thrust as thrust" (not climb rate)


class ArduPilotStrategy(AutopilotStrategy):
    """ArduCopter: GUID_OPTIONS checked, GUIDED_NOGPS once armable, LAND on input loss."""

    autopilot = Autopilot.ARDUPILOT
    default_loss_action = 'land'
    streams_while_idle = False
    streams_before_switch = False

    def in_offboard(self, custom_mode: int) -> bool:
        """Whether the mode is GUIDED_NOGPS."""
        return int(custom_mode) == ARDUCOPTER_MODE_GUIDED_NOGPS

    def in_land_mode(self, custom_mode: int) -> bool:
        """Whether the mode is LAND."""
        return int(custom_mode) == ARDUCOPTER_MODE_LAND

    def offboard_params(self) -> tuple[float, ...]:
        """DO_SET_MODE (1, 20): GUIDED_NOGPS."""
        return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ARDUCOPTER_MODE_GUIDED_NOGPS))

    def land_params(self) -> tuple[float, ...]:
        """DO_SET_MODE (1, 9): LAND."""
        return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ARDUCOPTER_MODE_LAND))

    def refusal(self, inp: SequencerInputs) -> str:
        """GUID_OPTIONS unread after the parameter timeout, or without bit 3."""
        if inp.guid_options is None:
            if inp.params_timed_out:
                return ('GUID_OPTIONS could not be read: refusing to fly (thrust might be read '
                        'as a climb rate)')
            return ''
        if not int(inp.guid_options) & GUID_OPTIONS_THRUST_BIT:
            return (f'GUID_OPTIONS = {int(inp.guid_options)} lacks bit 3 (SET_ATTITUDE_TARGET '
                    'thrust as thrust): refusing to fly; set GUID_OPTIONS |= 8 on the autopilot')
        return ''

    def parameters_ready(self, inp: SequencerInputs) -> bool:
        """GUID_OPTIONS has been read."""
        return inp.guid_options is not None

    def switch_wait(self, inp: SequencerInputs, engaging_s: float,
                    config: SequencerConfig) -> SwitchWait:
        """Wait, disarmed, for the pre-arm bit (unreported: ``armable_unknown_wait_s``)."""
        if not inp.armed and (inp.armable is False or (
                inp.armable is None and engaging_s < config.armable_unknown_wait_s)):
            return SwitchWait.ARMABLE
        return SwitchWait.NONE
