"""The pilot's radio in a firmware run: a mission switch on an RC channel, by sim time.

A real PX4 in lockstep takes its RC input from the simulator (simulator_mavlink takes an
RC_CHANNELS message from it into ``input_rc``, as from jMAVSim and Gazebo), and reports it in
RC_CHANNELS to the companion link, where the bridge reads the pilot's mission switch
(docs/onboard.md "Start and abort from the radio"). :class:`PilotSwitchRadio` is that radio:
8 channels, the sticks centred (the
throttle too: PX4's altitude hold at mid-stick), the switch channel OFF (1100 us) from boot
and ON (1900 us) from ``on_at_s`` of the mission's sim time (0 when the pre-roll ended, the
sim's first frame) to ``off_at_s`` (None: for good), or as the pilot flips it. ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

RC_CHANNELS = 8                 # channels the radio has (RC_CHANNELS carries 18: the rest unused)
RC_MAX_CHANNELS = 18
RC_UNUSED = 0xFFFF
CENTRE_US, OFF_US, ON_US = 1500, 1100, 1900
RSSI = 100                      # what PX4 reports for an RC_CHANNELS_OVERRIDE input


@dataclass
class PilotSwitchRadio:
    """The switch ``channel`` (1-8): OFF, ON from ``on_at_s`` until ``off_at_s`` (mission s).

    ``on_at_s`` None: no schedule, only the pilot's :meth:`flip` moves it (the sim node's
    ``sim/pilot_switch``: a harness flips it once the preflight says go, as a pilot would).
    Whatever happened last by a mission time holds: a schedule time or a flip.
    """

    channel: int
    on_at_s: float | None = None
    off_at_s: float | None = None
    flips: list = field(default_factory=list)     # (mission s, ON) of each flip, in order

    def __post_init__(self) -> None:
        if not 1 <= int(self.channel) <= RC_CHANNELS:
            raise ValueError(f'the simulated radio has channels 1-{RC_CHANNELS}, not '
                             f'{self.channel}')

    def flip(self, on: bool, mission_t: float) -> None:
        """Put the switch ON (True) or OFF at mission time ``mission_t``, as the pilot."""
        self.flips.append((float(mission_t), bool(on)))

    def switch_us(self, mission_t: float | None) -> int:
        """Return the switch channel (us) at mission time ``mission_t`` (None: the pre-roll)."""
        if mission_t is None:
            return OFF_US
        events = [(t, state) for t, state in ((self.on_at_s, True), (self.off_at_s, False))
                  if t is not None] + list(self.flips)
        on = False
        for t, state in sorted(events, key=lambda e: e[0]):     # stable: the schedule first
            if t <= mission_t:
                on = state
        return ON_US if on else OFF_US

    def message(self, mav: Any, t_us: int, mission_t: float | None) -> Any:
        """Return the RC_CHANNELS of firmware time ``t_us`` (us)."""
        channels = [CENTRE_US] * RC_CHANNELS + [RC_UNUSED] * (RC_MAX_CHANNELS - RC_CHANNELS)
        channels[int(self.channel) - 1] = self.switch_us(mission_t)
        return mav.rc_channels_encode(int(t_us) // 1000, RC_CHANNELS, *channels, RSSI)
