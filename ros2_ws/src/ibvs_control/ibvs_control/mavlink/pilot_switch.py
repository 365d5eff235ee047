"""The pilot's mission switch, read from the autopilot's RC_CHANNELS (ROS-free).

The bridge asks for RC_CHANNELS at ``pilot_switch_rate_hz`` (kept at that rate while the
vehicle rests) and reads one channel, ``pilot_switch_channel`` (1-18; 0: no switch), with a
hysteresis: at or above ``pilot_switch_on_us`` it is ON, at or below ``pilot_switch_off_us``
OFF, in between unchanged. A channel the autopilot marks unused (0 or UINT16_MAX, or beyond
its ``chancount``) is no reading; none for ``pilot_switch_timeout_s`` of the steady clock is
UNKNOWN. :meth:`PilotSwitch.release` latches OFF when the vehicle left the bridge's hands in
flight, until the switch is seen OFF (without a switch: until :meth:`PilotSwitch.rearm`, the
next engagement's standby). The meaning of each value for the mission is in
:mod:`ibvs_control.core.pilot_input`.

PX4 and ArduPilot both send RC_CHANNELS (#65) with the raw PWM of the receiver's channels in
microseconds, and both feed RC_CHANNELS_OVERRIDE from a GCS into it (how the SITL tests move
the switch).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

from ibvs_common.core.params import param
from ibvs_control.core.pilot_input import PilotInput

RC_CHANNELS_MAX = 18
RC_UNUSED = (0, 0xFFFF)         # RC_CHANNELS: a channel that is not used / not valid


@dataclass(frozen=True)
class PilotSwitchConfig:
    """The RC channel of the pilot's mission switch and how it is read."""

    channel: int = param(
        0, 'RC channel (1-18) of the pilot mission switch, read from RC_CHANNELS: OFF -> ON '
        'starts the mission (preflight permitting), ON -> OFF aborts it; 0 = no switch (the '
        'ibvs/start service only)', 0, RC_CHANNELS_MAX)
    on_us: int = param(1700, 'us, the switch channel at or above this is ON', 800, 2200)
    off_us: int = param(1300, 'us, at or below this OFF (in between: unchanged)', 800, 2200)
    timeout_s: float = param(
        1.0, 's (steady clock), no valid RC_CHANNELS this long: the switch is UNKNOWN (starts '
        'and aborts nothing; the autopilot\'s RC failsafe acts)', 0.0, None)
    rate_hz: float = param(10.0, 'Hz, RC_CHANNELS stream asked of the autopilot when a switch '
                           'is configured (kept at rest)', 0.0, None)

    def __post_init__(self):
        if not 0 <= int(self.channel) <= RC_CHANNELS_MAX:
            raise ValueError(f'pilot_switch_channel must be 0-{RC_CHANNELS_MAX}, got '
                             f'{self.channel}')
        if not self.off_us < self.on_us:
            raise ValueError(f'pilot_switch_off_us ({self.off_us}) must be below '
                             f'pilot_switch_on_us ({self.on_us})')
        for name in ('timeout_s', 'rate_hz'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'pilot_switch_{name} must be finite and > 0, got {v}')

    @property
    def enabled(self) -> bool:
        """Whether a switch channel is configured."""
        return int(self.channel) > 0


class PilotSwitch:
    """The switch position from RC_CHANNELS, and the latched OFF of a release in flight."""

    def __init__(self, config: PilotSwitchConfig) -> None:
        self.config = config
        self.position = PilotInput.UNKNOWN      # from the channel alone
        self.released = False                   # latched OFF (release)
        self.invalid_readings = 0               # RC_CHANNELS without a valid switch channel
        self._valid_t: float | None = None

    def on_rc_channels(self, msg: Any, now: float) -> None:
        """Take one RC_CHANNELS message at steady time ``now``."""
        if not self.config.enabled:
            return
        ch = int(self.config.channel)
        us = getattr(msg, f'chan{ch}_raw', None)
        if us is None or int(us) in RC_UNUSED or ch > int(getattr(msg, 'chancount', 0)):
            self.invalid_readings += 1
            return
        us = int(us)
        if self._valid_t is None or now - self._valid_t > self.config.timeout_s:
            self.position = PilotInput.UNKNOWN  # in the band after a gap: still unknown
        self._valid_t = now
        if us >= self.config.on_us:
            self.position = PilotInput.ON
        elif us <= self.config.off_us:
            self.position = PilotInput.OFF
            self.released = False

    def release(self) -> None:
        """Latch OFF: the vehicle left the bridge's hands in flight (until the switch is OFF)."""
        self.released = True

    def rearm(self) -> None:
        """End the latched OFF at standby (a new engagement may follow), if no switch is set."""
        if not self.config.enabled:
            self.released = False

    def value(self, now: float) -> PilotInput:
        """Return the pilot input at steady time ``now`` (:class:`PilotInput`)."""
        if self.released:
            return PilotInput.OFF
        if self._valid_t is None or now - self._valid_t > self.config.timeout_s:
            return PilotInput.UNKNOWN
        return self.position
