"""Engage / arm / hand-back sequencing: the common state machine and one strategy per autopilot.

:func:`engage_sequencer` builds the sequencer of an autopilot (``common``: states, inputs,
commands, the machine; ``px4`` and ``ardupilot``: their modes, commands and checks).
"""
from __future__ import annotations

from ibvs_control.mavlink.sequencer.ardupilot import ArduPilotStrategy
from ibvs_control.mavlink.sequencer.common import (
    Autopilot, AutopilotStrategy, CommandRequest, EngageSequencer, EngageState, FLIGHT_STATES,
    MavCmd, MavResult, SequencerConfig, SequencerInputs)
from ibvs_control.mavlink.sequencer.px4 import px4_main_mode, px4_sub_mode, Px4Strategy

__all__ = ['ArduPilotStrategy', 'Autopilot', 'AutopilotStrategy', 'CommandRequest',
           'engage_sequencer', 'EngageSequencer', 'EngageState', 'FLIGHT_STATES', 'MavCmd',
           'MavResult', 'px4_main_mode', 'px4_sub_mode', 'Px4Strategy', 'SequencerConfig',
           'SequencerInputs', 'strategy_for']


def strategy_for(autopilot: Autopilot) -> AutopilotStrategy:
    """Return the strategy of ``autopilot``."""
    return Px4Strategy() if autopilot == Autopilot.PX4 else ArduPilotStrategy()


def engage_sequencer(autopilot: Autopilot,
                     config: SequencerConfig | None = None) -> EngageSequencer:
    """Return a sequencer for ``autopilot`` with ``config`` (default: the defaults)."""
    return EngageSequencer(strategy_for(autopilot), config or SequencerConfig())
