"""Armed state, flight mode and failsafes of the sim autopilot: PX4's commander, as far as flown.

No I/O: the command handlers and the facade turn the answers into MAVLink. Transitions:

- arm: always, except in OFFBOARD without a healthy setpoint stream; arming in a hold mode
  holds where the vehicle is;
- disarm: when landed, or forced (PX4's 21196) in the air;
- OFFBOARD: once setpoints have streamed for ``offboard_stream_min_s`` (or already in it);
  POSCTL / AUTO_LOITER hold where they were entered; AUTO_LAND descends;
- offboard loss (armed in OFFBOARD, latest setpoint older than ``offboard_timeout_s`` sim time
  or ``offboard_timeout_wall_s`` wall clock): AUTO_LAND as a failsafe, which stays until the
  companion switches to OFFBOARD again;
- auto-disarm: landed for ``auto_disarm_landed_s`` of sim time in AUTO_LAND (PX4
  COM_DISARM_LAND). Landed = body origin at most ``landed_height`` above ``floor_z`` with
  |v_z| <= ``landed_speed``, on ground truth.
"""
from __future__ import annotations

from typing import Callable

from ibvs_sim.core.autopilot.config import (AutopilotConfig, AutopilotCounters, finite, LOG,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.protocol import FlightMode, HOLD_MODES
from ibvs_sim.core.autopilot.setpoints import OffboardSetpoints


class FlightModeMachine:
    """Armed state and flight mode, their transitions, the failsafes (sim time, ground truth)."""

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 setpoints: OffboardSetpoints,
                 on_hold_entry: Callable[[VehicleStateView], None]) -> None:
        """Start in POSCTL, armed if ``config.start_armed``.

        ``setpoints`` tells whether the offboard stream is healthy or lost; ``on_hold_entry`` is
        called with the ground truth when a hold mode starts holding (entered, or armed in).
        """
        self.config = config
        self.counters = counters
        self._setpoints = setpoints
        self._on_hold_entry = on_hold_entry
        self.armed: bool = bool(config.start_armed)
        self.mode: FlightMode = FlightMode.POSCTL
        self.failsafe_active = False                 # AUTO_LAND entered by the offboard loss
        self._landed_since_t: float | None = None    # sim time, s

    def landed(self, state: VehicleStateView) -> bool:
        """Tell whether the vehicle is landed, on ground truth (``state`` must be finite)."""
        c = self.config
        height = c.floor_z - float(state.xi_I[2])
        return height <= c.landed_height and abs(float(state.v_I[2])) <= c.landed_speed

    def arm(self, state: VehicleStateView) -> bool:
        """Arm (already armed: nothing); False when refused: OFFBOARD without a setpoint stream."""
        if self.armed:
            return True
        if self.mode is FlightMode.OFFBOARD and not self._setpoints.healthy(float(state.t)):
            return False
        self.armed = True
        if self.mode in HOLD_MODES:
            self._on_hold_entry(state)
        LOG.info('armed (%s)', self.mode.name)
        return True

    def disarm(self, state: VehicleStateView, forced: bool) -> bool:
        """Disarm (already disarmed: nothing); False when refused: in the air, not ``forced``."""
        if not self.armed:
            return True
        if not forced and not self.landed(state):
            return False
        self.armed = False
        LOG.info('disarmed%s', ' (forced, in the air)' if not self.landed(state) else '')
        return True

    def request_offboard(self, state: VehicleStateView) -> bool:
        """Switch to OFFBOARD; False when refused: no healthy setpoint stream (and not in it)."""
        if self.mode is FlightMode.OFFBOARD or self._setpoints.healthy(float(state.t)):
            self.set_mode(FlightMode.OFFBOARD, state)
            return True
        return False

    def set_mode(self, mode: FlightMode, state: VehicleStateView, failsafe: bool = False) -> None:
        """Enter ``mode`` (a hold mode entered anew holds where the vehicle is now)."""
        if mode in HOLD_MODES and mode is not self.mode:
            self._on_hold_entry(state)
        if mode is not self.mode:
            LOG.info('mode %s -> %s%s', self.mode.name, mode.name,
                     ' (failsafe)' if failsafe else '')
        self.mode = mode
        self.failsafe_active = failsafe
        self._landed_since_t = None

    def check_offboard_loss(self, state: VehicleStateView) -> bool:
        """Enter the AUTO_LAND failsafe if armed in OFFBOARD and the stream is lost at state.t.

        Return True when it was entered now (the caller tells the companion).
        """
        if not (self.armed and self.mode is FlightMode.OFFBOARD):
            return False
        lost_sim, lost_wall = self._setpoints.lost(state.t)
        if not (lost_sim or lost_wall):
            return False
        self.counters.failsafe_events += 1
        LOG.warning('offboard setpoints lost (%s): failsafe AUTO_LAND',
                    'sim time' if lost_sim else 'wall clock')
        self.set_mode(FlightMode.AUTO_LAND, state, failsafe=True)
        return True

    def check_auto_disarm(self, state: VehicleStateView) -> None:
        """Disarm after auto_disarm_landed_s (sim time) landed in AUTO_LAND."""
        if not (self.armed and self.mode is FlightMode.AUTO_LAND):
            self._landed_since_t = None
            return
        if not finite(state.xi_I, state.v_I) or not self.landed(state):
            self._landed_since_t = None
            return
        if self._landed_since_t is None:
            self._landed_since_t = state.t
        elif state.t - self._landed_since_t >= self.config.auto_disarm_landed_s:
            LOG.info('landed for %.1f s in AUTO_LAND: disarming', state.t - self._landed_since_t)
            self.armed = False
            self._landed_since_t = None
