"""PX4's part of the engage sequences: OFFBOARD, AUTO.LAND and the setpoint stream before them.

PX4 refuses OFFBOARD without a setpoint stream (``prestream_s``, > 1 s), so setpoints stream
from the link's start (a keepalive of the level hover while in standby). The switch is
``MAV_CMD_DO_SET_MODE`` param1 = 1 (custom mode), param2 = 6 (the main mode; not the packed
``6 << 16``, which PX4 acknowledges and ignores); the land mode is AUTO.LAND (main 4, sub 6).
The switch does not wait for the pre-arm bit: PX4's is ``canArm`` of the *current* mode, so an
indoor vehicle left in Position mode without a position estimate would never be armable there,
though it is in OFFBOARD. Forces lost: stop streaming (PX4's offboard-loss failsafe acts).
"""
from __future__ import annotations

from ibvs_control.mavlink.sequencer.common import (
    Autopilot, AutopilotStrategy, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, SequencerConfig,
    SequencerInputs, SwitchWait)

PX4_MAIN_MODE_OFFBOARD = 6             # PX4 custom main mode (custom_mode bits 16-23)
PX4_MAIN_MODE_AUTO = 4
PX4_AUTO_SUB_MODE_LAND = 6             # custom_mode bits 24-31
PX4_MAIN_MODE_SHIFT = 16
PX4_SUB_MODE_SHIFT = 24


def px4_main_mode(custom_mode: int) -> int:
    """PX4 main mode of a HEARTBEAT custom_mode (bits 16-23; sub mode is bits 24-31)."""
    return (int(custom_mode) >> PX4_MAIN_MODE_SHIFT) & 0xFF


def px4_sub_mode(custom_mode: int) -> int:
    """PX4 sub mode of a HEARTBEAT custom_mode (bits 24-31)."""
    return (int(custom_mode) >> PX4_SUB_MODE_SHIFT) & 0xFF


class Px4Strategy(AutopilotStrategy):
    """PX4: OFFBOARD after a setpoint stream, AUTO.LAND, stop streaming on input loss."""

    autopilot = Autopilot.PX4
    default_loss_action = 'stop'
    streams_while_idle = True
    streams_before_switch = True

    def in_offboard(self, custom_mode: int) -> bool:
        """Whether the main mode is OFFBOARD."""
        return px4_main_mode(custom_mode) == PX4_MAIN_MODE_OFFBOARD

    def in_land_mode(self, custom_mode: int) -> bool:
        """Whether the mode is AUTO.LAND."""
        return (px4_main_mode(custom_mode) == PX4_MAIN_MODE_AUTO
                and px4_sub_mode(custom_mode) == PX4_AUTO_SUB_MODE_LAND)

    def offboard_params(self) -> tuple[float, ...]:
        """DO_SET_MODE (1, 6): OFFBOARD."""
        return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(PX4_MAIN_MODE_OFFBOARD))

    def land_params(self) -> tuple[float, ...]:
        """DO_SET_MODE (1, 4, 6): AUTO.LAND."""
        return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(PX4_MAIN_MODE_AUTO),
                float(PX4_AUTO_SUB_MODE_LAND))

    def switch_wait(self, inp: SequencerInputs, engaging_s: float,
                    config: SequencerConfig) -> SwitchWait:
        """Wait for the stream first: more than ``prestream_s`` of it."""
        return SwitchWait.STREAM if inp.streaming_s <= config.prestream_s else SwitchWait.NONE
