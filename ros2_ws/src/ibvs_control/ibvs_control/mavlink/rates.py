"""The telemetry streams asked of the autopilot, and their slower rates while the vehicle rests.

SET_MESSAGE_INTERVAL requests one at a time (:class:`~ibvs_control.mavlink.telemetry.
StreamRequests`), asked again when the link comes back or the autopilot reboots; the
high-rate streams slow down at rest (:class:`~ibvs_control.mavlink.telemetry.QuietTelemetry`).
ROS-free.
"""
from __future__ import annotations

from typing import Callable

from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.engagement import Engagement
from ibvs_control.mavlink.link import MavlinkLink, MavMsgId
from ibvs_control.mavlink.sequencer import Autopilot
from ibvs_control.mavlink.status import EventLog
from ibvs_control.mavlink.telemetry import QuietTelemetry, StreamRequests, streams_for


class TelemetryRates:
    """Which telemetry streams the autopilot sends us, and at which rates."""

    def __init__(self, config: BridgeConfig, link: MavlinkLink, engagement: Engagement,
                 events: EventLog, clock: Callable[[], float]) -> None:
        self.config = config
        self.link = link
        self.engagement = engagement
        self.events = events
        self._clock = clock
        self.streams: StreamRequests | None = None      # once the autopilot is known
        self.quiet: QuietTelemetry | None = None        # with the streams
        self._last_frame_t: float | None = None         # steady time of the last frame status

    def start(self, autopilot: Autopilot) -> None:
        """Set up the streams of ``autopilot`` (now known), their full and quiet rates."""
        c = self.config
        self.streams = StreamRequests(streams_for(
            autopilot.value, c.attitude_rate_hz, c.imu_rate_hz, c.thrust_rate_hz,
            c.status_rate_hz, c.heartbeat_request_hz, c.streams_off,
            ((MavMsgId.RC_CHANNELS, c.pilot_switch.rate_hz),) if c.pilot_switch.enabled else ()))
        imu = MavMsgId.SCALED_IMU if autopilot == Autopilot.ARDUPILOT \
            else MavMsgId.HIGHRES_IMU
        self.quiet = QuietTelemetry(
            {MavMsgId.ATTITUDE_QUATERNION: c.attitude_rate_hz, imu: c.imu_rate_hz,
             MavMsgId.ATTITUDE_TARGET: c.thrust_rate_hz},
            c.quiet_telemetry_rate_hz, c.quiet_telemetry_delay_s)

    @property
    def slowed(self) -> bool:
        """Whether the high-rate streams are at their rate at rest."""
        return bool(self.quiet and self.quiet.active)

    def on_frame(self) -> None:
        """Note a frame evaluated (``ibvs/supervisor_status``): full rates now if slowed."""
        self._last_frame_t = self._clock()
        if self.slowed:
            self.request(self._last_frame_t)

    @property
    def at_rest(self) -> bool:
        """Whether the telemetry may slow down: nothing to engage and no frames.

        No frame evaluated (``ibvs/supervisor_status``) for ``quiet_telemetry_delay_s``
        either: with the cameras on, the window detection of IDLE (the start's check, the
        preflight's) derotates with the attitude at each image stamp, which a 10 Hz stream
        cannot give within the nodes' extrapolation bound. Whether our setpoint stream is held
        or the clocks are synced does not matter.
        """
        frames = self._last_frame_t is not None and \
            self._clock() - self._last_frame_t < self.config.quiet_telemetry_delay_s
        return self.engagement.resting and not frames

    def request(self, now: float) -> None:
        """Send the next stream request, one at a time, at full or quiet rates (at_rest)."""
        if self.streams is None or not self.link.link_up:
            return
        rates = self.quiet.update(self.at_rest, now)
        if rates is not None:
            changed = [i for i, r in rates.items() if self.streams.set_rate(i, r)]
            if changed:
                self.events.add('info', 'telemetry streams ' + (
                    f'slowed to {self.config.quiet_telemetry_rate_hz:g} Hz at rest (disarmed, '
                    'nothing engaging)' if self.quiet.active
                    else 'back to their full rates') + f': messages {changed}')
        req = self.streams.step(now)
        if req is not None:
            self.link.set_message_interval(*req)

    def restart(self) -> None:
        """Ask for every stream again at its full rate (link back, autopilot rebooted)."""
        if self.streams is not None:
            for msg_id, rate in self.quiet.reset().items():
                self.streams.set_rate(msg_id, rate)
            self.streams.reset()

    def on_ack(self, result: int) -> None:
        """Take the COMMAND_ACK of a SET_MESSAGE_INTERVAL."""
        warning = self.streams.on_ack(result) if self.streams else ''
        if warning:
            self.events.add('warn', warning)
