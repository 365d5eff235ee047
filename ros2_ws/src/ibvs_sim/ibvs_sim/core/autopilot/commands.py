"""COMMAND_LONG of the sim autopilot, answered with COMMAND_ACK as PX4's commander answers.

- COMPONENT_ARM_DISARM: param1 1 arm, 0 disarm (param2 = 21196 forces it in the air);
- DO_SET_MODE: param1 must have CUSTOM_MODE_ENABLED, param2 / param3 the PX4 main / sub mode
  (cast to uint8_t as PX4 does); POSCTL, OFFBOARD, AUTO_LOITER, AUTO_LAND are flown;
- SET_MESSAGE_INTERVAL (param1 message id, param2 µs) and REQUEST_MESSAGE (param1 id).

A refused mode switch or arming change answers TEMPORARILY_REJECTED (with a STATUSTEXT), NaN or
infinite params DENIED, other commands UNSUPPORTED. Commands for another system or component
are counted and not answered.
"""
from __future__ import annotations

from typing import Any

from ibvs_sim.core.autopilot.config import (AutopilotCounters, finite, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_sim.core.autopilot.modes import FlightModeMachine
from ibvs_sim.core.autopilot.protocol import (
    ARM_ACTION_ARM, ARM_ACTION_DISARM, FlightMode, MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE, MAV_CMD_REQUEST_MESSAGE, MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_RESULT_ACCEPTED, MAV_RESULT_DENIED,
    MAV_RESULT_TEMPORARILY_REJECTED, MAV_RESULT_UNSUPPORTED, MAV_SEVERITY_CRITICAL,
    MAV_SEVERITY_WARNING, Px4AutoSubMode, Px4MainMode, PX4_FORCE_DISARM_MAGIC, UINT8_MASK)
from ibvs_sim.core.autopilot.telemetry import Telemetry


class CommandHandler:
    """Decode COMMAND_LONG, act on the mode machine or the telemetry, send the COMMAND_ACK."""

    def __init__(self, counters: AutopilotCounters, warn: RateLimitedLog, link: AutopilotLink,
                 modes: FlightModeMachine, telemetry: Telemetry) -> None:
        """Act on ``modes`` (arming, mode) and ``telemetry`` (intervals, requests)."""
        self.counters = counters
        self._warn = warn
        self._link = link
        self._modes = modes
        self._telemetry = telemetry

    def on_command_long(self, msg: Any, state: VehicleStateView) -> None:
        """Handle a COMMAND_LONG read at sim time ``state.t`` and acknowledge it to its sender."""
        if not self._link.for_us(msg.target_system, msg.target_component):
            return
        self.counters.commands += 1
        handlers = {MAV_CMD_COMPONENT_ARM_DISARM: self._arm_disarm,
                    MAV_CMD_DO_SET_MODE: self._set_mode,
                    MAV_CMD_SET_MESSAGE_INTERVAL: self._set_message_interval,
                    MAV_CMD_REQUEST_MESSAGE: self._request_message}
        handler = handlers.get(msg.command)
        if handler is None:
            self.counters.commands_unsupported += 1
            result = MAV_RESULT_UNSUPPORTED
        else:
            result = handler(msg, state)
        if result != MAV_RESULT_ACCEPTED:
            self.counters.commands_rejected += 1
        self._link.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(),
                                        msg.get_srcComponent())

    def _arm_disarm(self, msg: Any, state: VehicleStateView) -> int:
        if not finite(msg.param1, msg.param2):
            return MAV_RESULT_DENIED
        action = int(round(msg.param1))
        if action == ARM_ACTION_ARM:
            if self._modes.arm(state):
                return MAV_RESULT_ACCEPTED
            self._link.statustext(MAV_SEVERITY_CRITICAL, 'Arming denied: no offboard signal')
            return MAV_RESULT_TEMPORARILY_REJECTED
        if action == ARM_ACTION_DISARM:
            forced = int(round(msg.param2)) == PX4_FORCE_DISARM_MAGIC
            if self._modes.disarm(state, forced):
                return MAV_RESULT_ACCEPTED
            self._link.statustext(MAV_SEVERITY_CRITICAL, 'Disarming denied: not landed')
            return MAV_RESULT_TEMPORARILY_REJECTED
        return MAV_RESULT_DENIED

    def _set_mode(self, msg: Any, state: VehicleStateView) -> int:
        if not finite(msg.param1, msg.param2, msg.param3):
            return MAV_RESULT_DENIED
        base_mode = int(msg.param1) & UINT8_MASK
        if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MAV_RESULT_UNSUPPORTED  # base-mode-only switches are not modelled
        # PX4 casts the float params to uint8_t: on x86 SITL a packed 6 << 16 reads as 0.
        main = int(msg.param2) & UINT8_MASK
        sub = int(msg.param3) & UINT8_MASK
        if main == Px4MainMode.OFFBOARD:
            if self._modes.request_offboard(state):
                return MAV_RESULT_ACCEPTED
            self._link.statustext(MAV_SEVERITY_CRITICAL,
                                  'Switching to Offboard is currently not available')
            return MAV_RESULT_TEMPORARILY_REJECTED
        if main == Px4MainMode.POSCTL:
            self._modes.set_mode(FlightMode.POSCTL, state)
            return MAV_RESULT_ACCEPTED
        if main == Px4MainMode.AUTO and sub == Px4AutoSubMode.LOITER:
            self._modes.set_mode(FlightMode.AUTO_LOITER, state)
            return MAV_RESULT_ACCEPTED
        if main == Px4MainMode.AUTO and sub == Px4AutoSubMode.LAND:
            self._modes.set_mode(FlightMode.AUTO_LAND, state)
            return MAV_RESULT_ACCEPTED
        if any(main == known for known in Px4MainMode):
            self._link.statustext(MAV_SEVERITY_WARNING,
                                  f'Mode {main}/{sub} not available in the sim')
            return MAV_RESULT_TEMPORARILY_REJECTED
        # Unknown main mode: PX4's commander leaves the mode unchanged and still accepts.
        self._warn.warning('mode', 'DO_SET_MODE with unknown main mode %d (param2=%r): ignored',
                           main, msg.param2)
        return MAV_RESULT_ACCEPTED

    def _set_message_interval(self, msg: Any, state: VehicleStateView) -> int:
        if not finite(msg.param1, msg.param2):
            return MAV_RESULT_DENIED
        return self._telemetry.set_interval(int(msg.param1), int(msg.param2))

    def _request_message(self, msg: Any, state: VehicleStateView) -> int:
        if not finite(msg.param1):
            return MAV_RESULT_DENIED
        if self._telemetry.send_once(int(msg.param1), state):
            return MAV_RESULT_ACCEPTED
        return MAV_RESULT_UNSUPPORTED
