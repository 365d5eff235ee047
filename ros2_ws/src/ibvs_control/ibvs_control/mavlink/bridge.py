"""The MAVLink bridge without ROS: one part per concern, composed (docs/mavlink.md).

- :mod:`~ibvs_control.mavlink.link`: connection, signing, heartbeats, link supervision;
- :mod:`~ibvs_control.mavlink.time_sync`: the clock offset by TIMESYNC, the ROS time given;
- :mod:`~ibvs_control.mavlink.imu_intake`: telemetry in, imu/data samples, specific force;
- :mod:`~ibvs_control.mavlink.setpoint_stream`: forces and headings -> SET_ATTITUDE_TARGET;
- :mod:`~ibvs_control.mavlink.engagement`: supervisor mode, arm requests, the sequencer, safety;
- :mod:`~ibvs_control.mavlink.rates`: the telemetry streams asked of the autopilot;
- :mod:`~ibvs_control.mavlink.pilot_switch`: the pilot's mission switch (RC_CHANNELS);
- :mod:`~ibvs_control.mavlink.params`: the autopilot parameters read and what they imply;
- :mod:`~ibvs_control.mavlink.status`: log events and the /diagnostics snapshot.

The node calls the ``on_*`` inputs, :meth:`MavlinkBridge.poll` (receive: from its reader
thread, and at the stream rate), :meth:`MavlinkBridge.stream` and :meth:`MavlinkBridge.heartbeat`
with the ROS time (system time on a vehicle, sim time in the sim).
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

from ibvs_common.core.modes import FLYING_MODES, Mode
from ibvs_control.core.pilot_input import PilotInput
from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.engagement import Engagement
from ibvs_control.mavlink.hover import HoverThrust
from ibvs_control.mavlink.imu_intake import ImuIntake
from ibvs_control.mavlink.link import MavlinkLink
from ibvs_control.mavlink.params import AutopilotParams, Changed, param_value
from ibvs_control.mavlink.pilot_switch import PilotSwitch
from ibvs_control.mavlink.rates import TelemetryRates
from ibvs_control.mavlink.sequencer import Autopilot, EngageState, FLIGHT_STATES
from ibvs_control.mavlink.setpoint_stream import SetpointStream
from ibvs_control.mavlink.setpoints import SetpointSource
from ibvs_control.mavlink.status import bridge_status, BridgeStatus, EventLog
from ibvs_control.mavlink.telemetry import ImuSample, Telemetry
from ibvs_control.mavlink.time_sync import RosTime, TimeSync, TimesyncExchange

__all__ = ['BridgeConfig', 'BridgeStatus', 'ImuSample', 'MavlinkBridge', 'SetpointSource']

MAV_CMD_SET_MESSAGE_INTERVAL = 511
# the streams that arrive at 50-100 Hz and need no supervision step of their own (poll)
HIGH_RATE_TYPES = frozenset(('ATTITUDE_QUATERNION', 'HIGHRES_IMU', 'SCALED_IMU',
                             'ATTITUDE_TARGET'))
# leaving a flight state for one of these: the vehicle left the bridge's hands (pilot / GCS
# mode switch, link lost, a command failed): the mission is over (core/pilot_input.py)
RELEASED_STATES = (EngageState.HELD, EngageState.NO_LINK, EngageState.FAILED)


class MavlinkBridge:
    """ROS-free bridge: call on_* for inputs, poll/stream/heartbeat from timers."""

    def __init__(self, config: BridgeConfig,
                 clock: Callable[[], float] = time.monotonic,
                 heartbeat_clock: Callable[[], float] | None = None) -> None:
        self.config = config
        self.clock = clock
        self.events = EventLog()
        self.ros = RosTime()
        self.link = MavlinkLink(config.link, clock, heartbeat_clock)
        self.time_sync = TimeSync(config.time_sync)
        self.timesync = TimesyncExchange(self.time_sync, self.link.send_timesync)
        self.telemetry = Telemetry(self.time_sync, clock, config.px4_events)
        self.hover = HoverThrust(config.configured_hover_thrust,
                                 config.hover_thrust_source == 'autopilot', config.estimator)
        self.params = AutopilotParams(self.hover.seed, config.link.source_system,
                                      config.param_retry_s, config.param_timeout_s)
        self.engagement = Engagement(config, self.link, self.params, self.telemetry, self.ros,
                                     self.events)
        self.setpoints = SetpointStream(config, self.link, self.time_sync, self.ros,
                                        self.telemetry, self.hover, self.engagement,
                                        self.events, clock)
        self.imu = ImuIntake(config, self.link, self.telemetry, self.hover, self.setpoints,
                             self.engagement)
        self.rates = TelemetryRates(config, self.link, self.engagement, self.events, clock)
        self.pilot = PilotSwitch(config.pilot_switch)
        self._last_tick_t: float | None = None
        self._was_up = False
        self._sync_reboots = 0
        self._identify()

    # --- inputs from ROS ---------------------------------------------------------------
    def on_supervisor_mode(self, mode: int) -> None:
        """ibvs/mode: full telemetry rates, then the engagement commands, leave at once."""
        if self.engagement.on_supervisor_mode(mode):
            now = self.clock()
            self.rates.request(now)
            self._run_sequencer(now)

    def on_supervisor_status(self, stamp_ns: int, mode: int | None) -> str:
        """ibvs/supervisor_status: the mode of the frame of ``stamp_ns``; '' or why refused."""
        reason = self.setpoints.on_supervisor_status(stamp_ns, mode)
        if not reason:
            self.rates.on_frame()
        return reason

    def on_heading(self, stamp_ns: int, q_wxyz_enu_flu: np.ndarray,
                   ros_ns: int | None = None) -> str:
        """ibvs/heading_setpoint of stamp_ns (base_link in map); '' or the refusal reason."""
        self.ros.set(ros_ns)
        return self.setpoints.on_heading(stamp_ns, q_wxyz_enu_flu)

    def on_force(self, stamp_ns: int, F_I: np.ndarray, ros_ns: int | None = None) -> str:
        """ibvs/force_setpoint (in {I}): sent at once; '' or why it was refused."""
        self.ros.set(ros_ns)
        return self.setpoints.on_force(stamp_ns, F_I)

    def request_arm(self) -> tuple[bool, str]:
        """ibvs/arm: allow the bridge to arm the vehicle when it engages."""
        hb = self.link.heartbeat
        to_sequencer = self.engagement.sequencer is not None and not (hb and hb.armed)
        answer = self.engagement.request_arm()
        if to_sequencer:
            self.rates.request(self.clock())       # full telemetry rates before arming
        return answer

    # --- timers ------------------------------------------------------------------------
    def heartbeat(self) -> None:
        """1 Hz: our HEARTBEAT."""
        self.link.send_heartbeat()

    @property
    def quiet(self) -> bool:
        """Whether nothing is to be engaged or flown: the periodic step may slow down.

        Standby (PX4: the keepalive stream of the level hover), the supervisor IDLE, the
        clocks synced and the stream released. Anything that engages (a supervisor mode, an
        arm request) acts at once, not at the next step.
        """
        seq = self.engagement.sequencer
        return (seq is not None and seq.state == EngageState.STANDBY
                and self.engagement.supervisor_mode == Mode.IDLE and self.setpoints.enabled
                and self.time_sync.synced)

    def tick_due(self) -> bool:
        """Whether the node's periodic step (poll, supervision, repeat) runs now.

        Always, except while :attr:`quiet`: then at most at ``idle_tick_rate_hz`` (steady
        clock), which is also the keepalive stream's rate then (PX4 wants > 2 Hz before
        OFFBOARD); docs/performance.md, "Idle CPU".
        """
        now = self.clock()
        c = self.config
        # half a timer period of slack: the step is called at stream_rate_hz, with jitter
        if self.quiet and self._last_tick_t is not None \
                and now - self._last_tick_t < 1.0 / c.idle_tick_rate_hz - 0.5 / c.stream_rate_hz:
            return False
        self._last_tick_t = now
        return True

    def stream(self, ros_ns: int | None = None) -> None:
        """Repeat the latest setpoint if none left for 1 / stream_rate_hz (call it often)."""
        self.ros.set(ros_ns)
        self.setpoints.repeat()

    def poll(self, ros_ns: int | None = None, supervise: bool = True,
             ros_clock: Callable[[], int | None] | None = None) -> list[ImuSample]:
        """Receive everything pending, run the sequencer, return new IMU samples.

        ``ros_ns``: ROS time now (ns; None or 0: no ``/clock`` yet, no clock sync).
        ``ros_clock`` (instead): the node's clock, read only once a message other than the
        high-rate telemetry (``HIGH_RATE_TYPES``, stamped from the autopilot's boot time) or
        the supervision needs it (a cold clock read costs ~30 us; docs/performance.md).
        ``supervise=False`` (the reader thread): the supervision (link state, sequencer,
        clock sync, parameter and stream requests) runs only after other messages.
        """
        now = self.clock()
        clock_read = ros_clock is None
        if clock_read:
            self.ros.set(ros_ns, force=True)
        samples = []
        messages = self.link.poll()
        for msg in messages:
            if not clock_read and msg.get_type() not in HIGH_RATE_TYPES:
                self.ros.set(ros_clock(), force=True)
                clock_read = True
            sample = self._handle(msg)
            if sample is not None:
                samples.append(sample)
        if not supervise and all(m.get_type() in HIGH_RATE_TYPES for m in messages):
            return samples
        if not clock_read:
            self.ros.set(ros_clock(), force=True)
        self._identify()
        self._on_link_state()
        if self.link.link_up:
            self.timesync.request(self.ros.ns, now)
            reads, changed = self.params.due(now)
            for name in reads:
                self.link.request_param(name)
            self._apply(changed)
            self.rates.request(now)
        self._run_sequencer(now)
        return samples

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) log events since the last call.

        Levels: 'info', 'warn', 'error'; 'reason-info' / 'reason-warn' / 'reason-error' are the
        autopilot's own words (STATUSTEXT, EVENT), each text once per 5 s.
        """
        return (self.events.pop() + self.link.pop_events() + self.telemetry.pop_events()
                + self.engagement.pop_events())

    def pilot_input(self) -> PilotInput:
        """Return ``ibvs/pilot_input`` now: the switch, or OFF after a release in flight."""
        return self.pilot.value(self.clock())

    def pop_heading_warning(self) -> str:
        """Text about forces flown without their heading since the last call, or ''."""
        return self.setpoints.pop_heading_warning()

    def status(self) -> BridgeStatus:
        """Diagnostics snapshot."""
        return bridge_status(self, self.clock())

    def close(self) -> None:
        """Close the link."""
        self.link.close()

    # --- internals ---------------------------------------------------------------------
    def _identify(self) -> None:
        """Once the autopilot is known: its sequencer and its telemetry streams."""
        if self.engagement.identify():
            self.rates.start(self.engagement.autopilot)

    def _handle(self, msg) -> ImuSample | None:
        """Hand one received message to the part that takes it."""
        kind = msg.get_type()
        if kind == 'TIMESYNC':
            for level, text in self.timesync.on_message(msg.tc1, msg.ts1, self.ros.ns):
                self.events.add(level, text)
        elif kind == 'PARAM_VALUE':
            value = param_value(float(msg.param_value), int(msg.param_type),
                                self.engagement.autopilot == Autopilot.PX4)
            self._apply(self.params.on_param(msg.param_id, value))
        elif kind == 'RC_CHANNELS':
            self.pilot.on_rc_channels(msg, self.clock())
        elif kind == 'COMMAND_ACK':
            if int(msg.command) == MAV_CMD_SET_MESSAGE_INTERVAL:
                self.rates.on_ack(msg.result)
            else:
                self.engagement.on_command_ack(msg.command, msg.result)
        else:
            return self.imu.on_message(msg, self.ros.ns)
        return None

    def _apply(self, changed: Changed) -> None:
        """Apply what the autopilot's parameters changed; pass their events on."""
        for level, text in self.params.pop_events():
            self.events.add(level, text)
        if Changed.SEED in changed:
            self.imu.start_estimator()
        if Changed.TILT_BOOST in changed:
            self.setpoints.shaper.tilt_boost_by_autopilot = self.params.tilt_boosted_by_autopilot

    def _on_link_state(self) -> None:
        """Link back / autopilot reboot: ask for the streams again, forget per-boot state."""
        up = self.link.link_up
        rebooted = self.time_sync.reboots != self._sync_reboots
        self._sync_reboots = self.time_sync.reboots
        if (up and not self._was_up) or rebooted:
            self.rates.restart()
            if self._was_up or rebooted:
                self.telemetry.reset()
                self.engagement.safety.reset_contact()
        if not up and self._was_up:
            self.engagement.safety.reset_contact()
        self._was_up = up

    def _run_sequencer(self, now: float) -> None:
        sp = self.setpoints
        seq = self.engagement.sequencer
        was = seq.state if seq is not None else None
        if self.engagement.run(now, sp.streaming_s(now), sp.shaper.ramp_done(now),
                               self.hover.seed.value is not None):
            sp.stopped()
        if seq is not None and seq.state != was:
            self._note_release(was, seq.state)

    def _note_release(self, was: EngageState, state: EngageState) -> None:
        """Latch the pilot input OFF on a release in flight; end the latch at standby."""
        if was in FLIGHT_STATES and state in RELEASED_STATES \
                and self.engagement.supervisor_mode in FLYING_MODES:
            self.pilot.release()        # (a supervisor that stopped flying ended it itself)
            self.events.add('warn', f'the vehicle left the bridge in {was.name} '
                                    f'({state.name}): ibvs/pilot_input OFF, the mission ends')
        elif state == EngageState.STANDBY:
            self.pilot.rearm()
