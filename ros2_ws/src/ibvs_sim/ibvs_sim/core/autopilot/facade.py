"""The sim autopilot: its parts composed behind the API the sim node uses (see the package doc).

Every physics step the sim calls :meth:`Autopilot.poll` with the ground truth (sim time
``state.t``): read and answer MAVLink, check the offboard stream and the landing, send due
telemetry and the heartbeat; then :meth:`Autopilot.attitude_reference` for the inner loop.
"""
from __future__ import annotations

from collections import deque
import time
from typing import Callable

import numpy as np

from ibvs_sim.core.autopilot.commands import CommandHandler
from ibvs_sim.core.autopilot.config import (AttitudeReference, AutopilotConfig,
                                            AutopilotCounters, LOG, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_sim.core.autopilot.modes import FlightModeMachine
from ibvs_sim.core.autopilot.noise import NoiseStream, SensorNoise
from ibvs_sim.core.autopilot.params import ParamServer
from ibvs_sim.core.autopilot.protocol import FlightMode, MAV_SEVERITY_CRITICAL
from ibvs_sim.core.autopilot.references import AttitudeReferences
from ibvs_sim.core.autopilot.setpoints import OffboardSetpoints
from ibvs_sim.core.autopilot.telemetry import Telemetry
from ibvs_sim.core.autopilot.timesync import TimesyncRequester, TimesyncResponder


class Autopilot:
    """PX4-like autopilot on a MAVLink 2 UDP endpoint (see the package docstring)."""

    def __init__(self, config: AutopilotConfig,
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        """Open the endpoint (``config.url``) and start armed in POSCTL (or disarmed).

        ``wall_clock`` (s, monotonic) paces the heartbeat and bounds the offboard loss; tests may
        inject a fake one.
        """
        self.config = config
        self._noise = SensorNoise(config)
        self._warn = RateLimitedLog(config.log_period_wall_s, wall_clock)
        self.counters = AutopilotCounters()
        self._setpoints = OffboardSetpoints(config, self.counters, self._warn, wall_clock)
        self._references = AttitudeReferences(config, self.counters, self._warn)
        self._modes = FlightModeMachine(config, self.counters, self._setpoints,
                                        self._references.set_hold_target)
        self._link = AutopilotLink(config, self.counters, self._warn)
        self._telemetry = Telemetry(config, self.counters, self._warn, self._link, self._noise,
                                    self._modes, self.attitude_reference, wall_clock)
        self._commands = CommandHandler(self.counters, self._warn, self._link, self._modes,
                                        self._telemetry)
        self._params = ParamServer(config, self.counters, self._link)
        self._timesync = TimesyncResponder(self.counters, self._link)
        self._timesync_requests = TimesyncRequester(config.timesync_request_hz, self.counters,
                                                    self._link)
        self._was_offboard = False              # OFFBOARD seen at a poll (awaits_setpoints)
        self._handlers = {'COMMAND_LONG': self._commands.on_command_long,
                          'SET_ATTITUDE_TARGET': self._on_set_attitude_target,
                          'PARAM_REQUEST_READ': self._params.on_request_read,
                          'PARAM_REQUEST_LIST': self._params.on_request_list,
                          'TIMESYNC': self._on_timesync}
        LOG.info('sim autopilot on %s (sys %d comp %d), %s, %s, signing %s', config.url,
                 config.system_id, config.component_id,
                 'armed' if self.armed else 'disarmed', self.mode.name,
                 'on' if config.signing_key_file else 'off')

    # --- state ----------------------------------------------------------------------------------

    @property
    def armed(self) -> bool:
        """Tell whether the vehicle is armed."""
        return self._modes.armed

    @property
    def mode(self) -> FlightMode:
        """Flight mode now (HEARTBEAT.custom_mode reports it)."""
        return self._modes.mode

    @property
    def failsafe(self) -> bool:
        """True while the offboard-loss failsafe flies the vehicle (reported as AUTO_LAND)."""
        return self._modes.failsafe_active

    @property
    def awaits_setpoints(self) -> bool:
        """Whether the graph's setpoints fly the vehicle: OFFBOARD, or before it first was.

        False once the autopilot flies a mode of its own after OFFBOARD (its failsafe land, a
        land or hold commanded by the bridge): the lockstep sim then stops waiting for an
        answer to each frame.
        """
        return self.mode is FlightMode.OFFBOARD or not self._was_offboard

    @property
    def last_setpoint_time_boot_ms(self) -> int | None:
        """time_boot_ms (the sender's clock, ms) of the latest well-formed SET_ATTITUDE_TARGET."""
        return self._setpoints.last_time_boot_ms

    @property
    def last_attitude_ms(self) -> int | None:
        """time_boot_ms (sim time, ms) of the newest valid ATTITUDE_QUATERNION sent, or None."""
        return self._telemetry.last_attitude_ms

    @property
    def new_setpoints(self) -> deque:
        """(time_boot_ms, wall s) of each valid setpoint with a new time_boot_ms; pop them."""
        return self._setpoints.new_setpoints

    # --- cycle ----------------------------------------------------------------------------------

    def fileno(self) -> int:
        """File descriptor of the MAVLink socket (to wait on it with select)."""
        return self._link.fileno()

    @property
    def local_port(self) -> int | None:
        """UDP port the autopilot listens on (the kernel's pick for ``udpin:HOST:0``)."""
        return self._link.local_port

    def next_telemetry_t(self) -> float | None:
        """Sim time (s) at which a telemetry stream is next due; None before the first send.

        A wall-clock server may sleep until then (or a datagram), instead of polling.
        """
        return self._telemetry.next_due_t()

    def poll(self, state: VehicleStateView, receive: bool = True,
             telemetry: bool = True) -> None:
        """Do one autopilot cycle at sim time ``state.t``; never blocks.

        Reads every pending datagram and answers it (unless ``receive`` is False: the
        lockstep sim reads only between frames), checks the offboard stream (failsafe),
        auto-disarms after a landing, sends due telemetry and TIMESYNC requests (sim-time
        rates; not with ``telemetry`` False: the sim before its first frame) and the heartbeat
        (wall clock).
        """
        self._was_offboard = self._was_offboard or self.mode is FlightMode.OFFBOARD
        self._references.ensure_hold_target(state)
        if receive:
            self._link.receive(state, self._handlers, self._telemetry.greet_new_peer)
        if self._modes.check_offboard_loss(state):
            self._link.statustext(MAV_SEVERITY_CRITICAL, 'Failsafe: offboard lost, landing')
        self._modes.check_auto_disarm(state)
        self._telemetry.send_heartbeat_if_due()
        if telemetry:
            self._telemetry.send_due(state)
            self._timesync_requests.send_if_due(state)

    def _on_timesync(self, msg, state: VehicleStateView) -> None:
        """Give TIMESYNC to both parts: each takes its own kind (request tc1 = 0, answer)."""
        self._timesync.on_timesync(msg, state)
        self._timesync_requests.on_answer(msg, state)

    def attitude_reference(self, state: VehicleStateView) -> AttitudeReference:
        """Return the inner-loop reference for the current mode (does not change the mode)."""
        return self._references.reference(state, self._modes.armed, self._modes.mode,
                                          self._setpoints.q_wxyz, self._setpoints.thrust)

    def estimate_error(self, t: float) -> np.ndarray:
        """Return R_err (3x3) at sim time t: this autopilot's attitude estimate is R_IB R_err.

        It reports that estimate (ATTITUDE_QUATERNION) and its attitude loop flies it: the
        loop drives the estimate, not the truth, to the reference (``PhysicsLoop`` tracks
        ``R_d R_err^T`` in truth). See ``noise.SensorNoise``.
        """
        return self._noise.attitude_error(t)

    def imu_fault_at(self, t: float) -> str:
        """Return the injected IMU fault at sim time ``t``: 'off', 'nan' or ''."""
        return self.config.imu_fault_at(t)

    def close(self) -> None:
        """Close the UDP endpoint."""
        self._link.close()

    # --- wiring ---------------------------------------------------------------------------------

    def _on_set_attitude_target(self, msg, state: VehicleStateView) -> None:
        if not self._link.for_us(msg.target_system, msg.target_component):
            return
        if (self._setpoints.receive(msg, state)
                and self._modes.armed and self._modes.mode is FlightMode.OFFBOARD):
            self.counters.setpoints_applied += 1

    # The noise model's entry points, as ibvs_sim/test/test_sim_autopilot.py reaches them.

    def _noisy_attitude(self, R_IB: np.ndarray, t: float) -> np.ndarray:
        return self._noise.noisy_attitude(R_IB, t)

    def _rng_at(self, stream: NoiseStream, index: int) -> np.random.Generator:
        return self._noise.rng_at(stream, index)
