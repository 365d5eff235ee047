"""The setpoint stream: force + heading setpoints -> SET_ATTITUDE_TARGET on the link (ROS-free).

Each force leaves at once with the heading of its stamp and the content of its frame's
supervisor mode; the latest target is repeated when none left for 1 / ``stream_rate_hz``; the
sequencer decides whether anything is sent at all (:mod:`~ibvs_control.mavlink.setpoints`
builds the targets).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ibvs_common.core.modes import Mode
from ibvs_common.core.stamps import NS_PER_S
from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.engagement import Engagement
from ibvs_control.mavlink.hover import HoverThrust
from ibvs_control.mavlink.link import MavlinkLink
from ibvs_control.mavlink.sequencer import EngageState
from ibvs_control.mavlink.setpoints import (
    AttitudeTarget, HeadingPairing, RateMeter, SetpointShaper, SetpointSource, ShaperConfig,
    yaw_from_heading_quat)
from ibvs_control.mavlink.status import EventLog
from ibvs_control.mavlink.telemetry import Telemetry
from ibvs_control.mavlink.time_sync import RosTime, TimeSync

NS_PER_MS = 1_000_000
STREAM_GAP_S = 0.5          # a longer pause in sending restarts the stream count
STREAM_EPS_S = 1e-3         # s, slack of the repeat period (timer jitter)
STATUS_MODES_KEPT = 32      # supervisor modes by stamp kept to pair with forces (0.64 s)


class SetpointStream:
    """Force and heading setpoints in, attitude targets out (sent while the sequencer streams)."""

    def __init__(self, config: BridgeConfig, link: MavlinkLink, time_sync: TimeSync,
                 ros: RosTime, telemetry: Telemetry, hover: HoverThrust,
                 engagement: Engagement, events: EventLog,
                 clock: Callable[[], float]) -> None:
        self.config = config
        self.link = link
        self.time_sync = time_sync
        self.ros = ros
        self.telemetry = telemetry
        self.hover = hover
        self.engagement = engagement
        self.events = events
        self._clock = clock
        self.shaper = SetpointShaper(ShaperConfig(
            config.mass, config.max_thrust_factor, config.max_force_factor,
            config.max_tilt_rad, config.hold_last_s, config.shutdown_ramp_s,
            config.max_force_age_s))
        self.pairing = HeadingPairing()
        self.rate = RateMeter()
        self.source = SetpointSource.NONE
        # False: build the targets but send none (the node holds the stream until the IMU's
        # consumers are matched, so that a lockstep sim starts only when they hear every sample)
        self.enabled = True
        self.current: AttitudeTarget | None = None
        self.stamp_ns: int | None = None             # latest stamp of a force sent (ROS ns)
        self._status_modes: dict[int, Mode] = {}     # stamp ns -> supervisor mode of that frame
        self._stream_start: float | None = None
        self._last_send_t: float | None = None
        self._reported_missing = 0

    # --- inputs ------------------------------------------------------------------------
    def on_supervisor_status(self, stamp_ns: int, mode: int | None) -> str:
        """Note the supervisor's mode for the frame of ``stamp_ns``; '' or why it is refused."""
        try:
            m = Mode(int(mode))
        except (TypeError, ValueError):
            return f'unknown supervisor mode {mode!r}'
        self._status_modes[int(stamp_ns)] = m
        while len(self._status_modes) > STATUS_MODES_KEPT:
            del self._status_modes[min(self._status_modes)]
        return ''

    def on_heading(self, stamp_ns: int, q_wxyz_enu_flu: np.ndarray) -> str:
        """Take a heading setpoint of ``stamp_ns`` (base_link in map); '' or why refused."""
        try:
            yaw: float | None = yaw_from_heading_quat(q_wxyz_enu_flu)
            reason = ''
        except ValueError as exc:
            self.shaper.rejected += 1
            yaw, reason = None, str(exc)
        self.pairing.on_heading(stamp_ns, yaw)
        return reason

    def on_force(self, stamp_ns: int, F_I: np.ndarray) -> str:
        """Take a force setpoint (in {I}): sent at once with the heading of its stamp.

        Returns '' or why the force was refused (then the held/fallback setpoint is sent at
        once, with the new stamp, so that a lockstep sim keeps advancing).
        """
        vehicle = self.ros.vehicle_s
        p = self.pairing.on_force(stamp_ns, F_I)
        yaw = self.telemetry.yaw_now if p.yaw is None else p.yaw
        reason = self.shaper.on_force(vehicle or 0.0, p.F_I, yaw,
                                      self.hover_for_stamp(p.stamp_ns), p.stamp_ns / NS_PER_S)
        if not reason:
            self.engagement.safety.on_force(vehicle)
        if self.stamp_ns is None or p.stamp_ns > self.stamp_ns:
            self.stamp_ns = p.stamp_ns
        self.send(new=True)
        return reason

    def pop_heading_warning(self) -> str:
        """Text about forces flown without their heading since the last call, or ''."""
        n = self.pairing.missing - self._reported_missing
        if n <= 0:
            return ''
        self._reported_missing = self.pairing.missing
        return (f'{n} force setpoint(s) without the heading of their stamp: flown at once with '
                f'the latest heading ({self.pairing.missing} in all, {self.pairing.late} late '
                'headings)')

    # --- content -----------------------------------------------------------------------
    def content_mode(self) -> Mode:
        """Return the mode whose content (F, shutdown ramp) the target carries.

        The supervisor's mode reported for the stamp of the latest force, so that e.g. the
        shutdown ramp starts on the SHUTDOWN frame itself, not on whichever setpoint follows the
        ``ibvs/mode`` message (lockstep runs then repeat to the end). Without that status, or
        once the forces stopped for ``hold_last_s`` (controller silent: the latest mode must
        still act), the latest ``ibvs/mode``.
        """
        eng = self.engagement
        if self.stamp_ns is not None and not eng.safety.inputs_lost(self.ros.vehicle_s):
            mode = self._status_modes.get(self.stamp_ns)
            if mode is not None:
                return mode
        return eng.supervisor_mode

    def hover_for_stamp(self, stamp_ns: int | None) -> float:
        """Hover thrust for the setpoint of ``stamp_ns``: the estimate as of its samples.

        In boot time, the samples at least ``margin_s`` older than the stamp (deterministic in
        a lockstep sim); unsynced or unknown: the latest; no seed yet: the configured value.
        """
        boot = None if stamp_ns is None else self.time_sync.ros_ns_to_boot_ms(stamp_ns)
        return self.hover.at_boot_ns(None if boot is None else boot * NS_PER_MS)

    def stamp_to_boot_ms(self, stamp_ns: int) -> int | None:
        """ROS stamp -> autopilot time_boot_ms (>= 0; None while the clocks are not synced)."""
        ms = self.time_sync.ros_ns_to_boot_ms(stamp_ns)
        return None if ms is None else max(0, ms)

    # --- sending -----------------------------------------------------------------------
    def may_stream(self) -> bool:
        """Whether targets are sent now: link up, stream enabled, the sequencer streaming."""
        return self.link.link_up and self.enabled and self.engagement.streaming

    def streaming_s(self, now: float) -> float:
        """How long targets have been sent without a gap (steady s)."""
        if self._stream_start is None:
            return 0.0
        return now - self._stream_start

    def stopped(self) -> None:
        """Count the stream's length from 0 again (the sequencer stopped it)."""
        self._stream_start = None

    def repeat(self) -> None:
        """Send the latest target again if none left for 1 / stream_rate_hz."""
        period = 1.0 / self.config.stream_rate_hz
        if self._last_send_t is not None \
                and self._clock() - self._last_send_t < period - STREAM_EPS_S:
            return
        self.send(new=False)

    def send(self, new: bool) -> None:
        """Build the target for the current state and mode; send it if the policy streams."""
        now = self._clock()
        seq = self.engagement.sequencer
        # Every target carries the stamp of the latest controller output (0 before any), never
        # the autopilot's current time: a fallback (level hover before the first force, hold,
        # shutdown ramp) is not an answer to a newer camera frame, so the sim's lockstep keeps
        # waiting for the controller instead of running ahead of the graph. Mapped at each
        # send: a repeat sent once the clocks are synced carries the mapped value (0 before).
        stamp = self.stamp_ns
        ms = (self.stamp_to_boot_ms(stamp) if stamp is not None else None) or 0
        t_stamp = 0.0 if stamp is None else stamp / NS_PER_S
        target = self.shaper.target(
            self.ros.vehicle_s, self.content_mode(), self.telemetry.yaw_now,
            self.hover.current(), ms, t_stamp, now,
            engaged=bool(seq and seq.state == EngageState.ENGAGED),
            level_hold=bool(seq and seq.level_hold))
        if target.source == SetpointSource.HOLD_LAST and new:
            self.events.add('error', f'force setpoint refused ({self.shaper.last_error}): '
                                     'holding the last valid one')
        if target.source != self.source:
            self.events.add('info' if target.source == SetpointSource.IBVS else 'warn',
                            f'setpoint source {self.source.value} -> {target.source.value}')
            self.source = target.source
        self.current = target
        if not self.may_stream():
            self._stream_start = None
            return
        if self.link.send_attitude_target(target.time_boot_ms, target.q_wxyz, target.thrust,
                                          target.type_mask):
            self.rate.tick(now)
            if self._stream_start is None or (self._last_send_t is not None
                                              and now - self._last_send_t > STREAM_GAP_S):
                self._stream_start = now
            self._last_send_t = now
