"""Who flies the vehicle: the supervisor's mode and arm requests into the engage sequencer.

The autopilot's flavour (configured, or from its HEARTBEAT), the sequencer built for it, the
safety monitor's detectors as the sequencer's inputs, and the commands it asks for sent on the
link (ROS-free).
"""
from __future__ import annotations

from dataclasses import replace

from ibvs_common.core.modes import Mode
from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.link import MavAutopilot, MavlinkLink
from ibvs_control.mavlink.params import AutopilotParams
from ibvs_control.mavlink.safety import SafetyMonitor
from ibvs_control.mavlink.sequencer import (
    Autopilot, engage_sequencer, EngageSequencer, EngageState, SequencerInputs)
from ibvs_control.mavlink.status import EventLog
from ibvs_control.mavlink.telemetry import Telemetry
from ibvs_control.mavlink.time_sync import RosTime

AUTOPILOT_OF_HEARTBEAT = {MavAutopilot.PX4: Autopilot.PX4,
                          MavAutopilot.ARDUPILOTMEGA: Autopilot.ARDUPILOT}


class Engagement:
    """The supervisor's mode, arm requests, the engage sequencer and the safety monitor."""

    def __init__(self, config: BridgeConfig, link: MavlinkLink, params: AutopilotParams,
                 telemetry: Telemetry, ros: RosTime, events: EventLog) -> None:
        self.config = config
        self.link = link
        self.params = params
        self.telemetry = telemetry
        self.ros = ros
        self.events = events
        self.safety = SafetyMonitor(replace(
            config.safety, hold_last_s=config.hold_last_s,
            disarm_force_after_s=config.sequencer.disarm_force_after_s))
        self.autopilot: Autopilot | None = (None if config.autopilot == 'auto'
                                            else Autopilot(config.autopilot))
        self.params.autopilot = self.autopilot
        self.sequencer: EngageSequencer | None = None
        self.supervisor_mode = Mode.IDLE
        self.idle_reports = 0
        self.arm_pending = bool(config.arm_on_start)    # asked before the sequencer exists

    def on_supervisor_mode(self, mode: int) -> bool:
        """ibvs/mode; whether the mode changed (unknown values are refused, logged)."""
        try:
            new = Mode(int(mode))
        except ValueError:
            self.events.add('error', f'unknown supervisor mode {mode}: kept '
                                     f'{self.supervisor_mode}')
            return False
        if new == Mode.IDLE:
            self.idle_reports += 1
        if new == self.supervisor_mode:
            return False
        self.events.add('info', f'supervisor mode {self.supervisor_mode.name} -> {new.name}')
        self.supervisor_mode = new
        return True

    def request_arm(self) -> tuple[bool, str]:
        """ibvs/arm: allow the bridge to arm the vehicle when it engages."""
        hb = self.link.heartbeat
        if hb is not None and hb.armed:
            return True, 'the vehicle is already armed'
        if self.sequencer is None:
            self.arm_pending = True
            return True, ('arm request noted: no autopilot yet; the bridge arms the vehicle once '
                          'it is in the offboard mode and armable')
        return self.sequencer.request_arm()

    def identify(self) -> bool:
        """Build the sequencer once the autopilot is known; whether it was built now."""
        if self.sequencer is not None:
            return False
        hb = self.link.heartbeat
        if self.autopilot is None and hb is not None:
            self.autopilot = AUTOPILOT_OF_HEARTBEAT.get(hb.autopilot)
            if self.autopilot is None:
                self.events.add('error', f'autopilot type {hb.autopilot} unsupported: set the '
                                         "'autopilot' parameter to px4 or ardupilot")
                return False
        if self.autopilot is None:
            return False
        self.params.autopilot = self.autopilot
        self.sequencer = engage_sequencer(self.autopilot, self.config.sequencer)
        self.sequencer.arm_requested = self.arm_pending
        return True

    @property
    def streaming(self) -> bool:
        """Whether the sequencer wants setpoints streamed (the link aside)."""
        return self.sequencer is not None and self.sequencer.streaming

    @property
    def resting(self) -> bool:
        """Standby, supervisor IDLE, disarmed and no arm request: nothing to engage."""
        hb = self.link.heartbeat
        seq = self.sequencer
        return (seq is not None and seq.state == EngageState.STANDBY
                and self.supervisor_mode == Mode.IDLE and hb is not None and not hb.armed
                and not seq.arm_requested)

    def run(self, now: float, streaming_s: float, ramp_done: bool,
            hover_thrust_ready: bool) -> bool:
        """Step the sequencer and send its commands; whether setpoints stopped streaming now."""
        if self.sequencer is None:
            return False
        hb = self.link.heartbeat
        vehicle = self.ros.vehicle_s
        safety = self.safety
        was = self.sequencer.state
        inp = SequencerInputs(
            t=now, link_up=self.link.link_up, supervisor_mode=self.supervisor_mode,
            idle_reports=self.idle_reports, armed=bool(hb and hb.armed),
            custom_mode=hb.custom_mode if hb else 0, streaming_s=streaming_s,
            hover_thrust_ready=hover_thrust_ready, guid_options=self.params.guid_options,
            params_timed_out=self.params.timed_out(now), ramp_done=ramp_done,
            armable=self.telemetry.armable, landed=self.telemetry.landed,
            inputs_lost=safety.inputs_lost(vehicle), touchdown=safety.touchdown,
            airborne_at_low_thrust=safety.airborne_at_low_thrust,
            heartbeat_t=self.link.heartbeat_at)
        for req in self.sequencer.step(inp):
            self.events.add('info', f'command {req.command.name} {req.params}: {req.reason}')
            self.link.send_command_long(req.command, req.params)
        if self.sequencer.state == was:
            return False
        if self.sequencer.state == EngageState.SET_MODE:
            safety.start_count(vehicle)     # engaging without any force: counts
        return not self.sequencer.streaming

    def on_command_ack(self, command: int, result: int) -> None:
        """Take the COMMAND_ACK of a sequencer command."""
        if self.sequencer is not None:
            self.sequencer.on_command_ack(command, result)
        if result != 0:
            self.events.add('warn', f'command {command} answered with result {result}')

    def pop_events(self) -> list[tuple[str, str]]:
        """Return the sequencer's transitions since the last call, as log events."""
        if self.sequencer is None:
            return []
        return [('info', f'engage: {e}') for e in self.sequencer.pop_events()]
