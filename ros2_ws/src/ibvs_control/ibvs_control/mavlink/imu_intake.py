"""The autopilot's telemetry in: imu/data samples, and its specific force for two consumers.

The touchdown rule of the safety monitor (|f| against the thrust commanded) and the online
hover-thrust estimate (samples kept until the hover thrust's seed is known). ROS-free.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from ibvs_common.core.stamps import NS_PER_S
from ibvs_control.mavlink.config import BridgeConfig
from ibvs_control.mavlink.engagement import Engagement
from ibvs_control.mavlink.hover import HoverThrust
from ibvs_control.mavlink.link import MavlinkLink
from ibvs_control.mavlink.setpoint_stream import SetpointStream
from ibvs_control.mavlink.telemetry import (
    AccelSample, ImuSample, LandedState, Telemetry, ThrustSample)

PENDING_ACCEL_KEPT = 500    # IMU samples kept until the hover-thrust seed is known


class ImuIntake:
    """Telemetry messages -> IMU samples; specific force -> touchdown rule, hover estimate."""

    def __init__(self, config: BridgeConfig, link: MavlinkLink, telemetry: Telemetry,
                 hover: HoverThrust, setpoints: SetpointStream,
                 engagement: Engagement) -> None:
        self.config = config
        self.link = link
        self.telemetry = telemetry
        self.hover = hover
        self.setpoints = setpoints
        self.engagement = engagement
        self._pending: deque = deque(maxlen=PENDING_ACCEL_KEPT)
        self.start_estimator()                  # the configured seed is known at once

    def on_message(self, msg, ros_ns: int | None) -> ImuSample | None:
        """Take one telemetry message received at ROS time ``ros_ns``; a new IMU sample or None."""
        imu, accel, _ = self.telemetry.on_message(msg, ros_ns)
        if accel is not None:
            self._on_accel(accel)
        return imu

    def start_estimator(self) -> None:
        """Start the estimate once the seed is known, with the samples kept until then."""
        estimator, seed = self.hover.estimator, self.hover.seed
        if estimator.theta is not None or seed.value is None:
            return
        estimator.start(seed.value)
        pending, self._pending = list(self._pending), deque(maxlen=PENDING_ACCEL_KEPT)
        for a, thr in pending:
            self._estimate(a, thr)

    def _on_accel(self, a: AccelSample) -> None:
        hover = self.hover.current()
        thr = self.telemetry.thrust
        sp = self.setpoints
        commanded = sp.current.thrust if sp.current is not None and sp.may_stream() \
            else (thr.thrust if thr is not None else hover)
        f_norm = float(np.linalg.norm(a.f_frd))
        self.engagement.safety.on_accel(a.boot_ns, f_norm, commanded, hover)
        if self.hover.estimator.theta is None:
            self._pending.append((a, thr))     # replayed once the seed is known
            return
        self._estimate(a, thr)

    def _estimate(self, a: AccelSample, thr: ThrustSample | None) -> None:
        if thr is None or abs(a.boot_ns - thr.boot_ns) > \
                self.config.estimator.max_pairing_s * NS_PER_S:
            return
        hb = self.link.heartbeat
        airborne = bool(hb and hb.armed) and self.telemetry.landed_state in (
            None, LandedState.UNDEFINED, LandedState.IN_AIR, LandedState.TAKEOFF)
        boost = 1.0
        if self.setpoints.shaper.tilt_boost_by_autopilot and a.cos_tilt > 0.5:
            boost = 1.0 / a.cos_tilt
        self.hover.estimator.update(a.boot_ns, float(a.f_frd[2]),
                                    float(np.linalg.norm(a.f_frd)), thr.thrust, boost, airborne)
