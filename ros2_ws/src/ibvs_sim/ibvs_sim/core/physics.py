"""The vehicle between camera frames: plant, inner attitude loop, wind, autopilot, contacts.

:class:`PhysicsLoop` advances the ground truth by one physics step (``PlantParams.
physics_rate_hz``, 500 Hz): the autopilot is polled with the ground truth, its attitude
reference is tracked by the inner loop (the estimate error it reports is flown, as on a real
autopilot), the plant integrates with the wind's force, and the envelope is checked for
contacts. Sim time is integer nanoseconds since boot. ROS-free.
"""
from __future__ import annotations

import math
import time
from typing import Protocol

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import rot_from_quat, rot_z
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.autopilot import AttitudeReference, VehicleStateView
from ibvs_sim.core.dynamics import (AttitudeController, PlantParams, QuadrotorPlant, Wind,
                                    WindConfig, hover_state)
from ibvs_sim.core.events import ContactMonitor, SimEvent
from ibvs_sim.core.world import WorldConfig


class ReferenceSource(Protocol):
    """What the simulation needs from the autopilot (ibvs_sim.core.autopilot.Autopilot)."""

    last_setpoint_time_boot_ms: int | None
    awaits_setpoints: bool

    def poll(self, state: VehicleStateView, receive: bool = True,
             telemetry: bool = True) -> None: ...

    def attitude_reference(self, state: VehicleStateView) -> AttitudeReference: ...

    def estimate_error(self, t: float) -> np.ndarray:
        """R_err (3x3) at sim time t: the autopilot's attitude estimate is R_IB R_err."""


class PhysicsLoop:
    """Step the plant under the autopilot's reference; keep the ground truth and sim time.

    The start is the hover state at ``initial_position_I`` with yaw ``initial_yaw`` (None:
    world.yaml's initial condition). ``wall_s`` is the wall clock (perf_counter, s) spent in
    the steps: the physics' share of a run (``sim/stats``).
    """

    def __init__(self, world: WorldConfig, vehicle: VehicleConfig,
                 autopilot: ReferenceSource, wind: WindConfig,
                 initial_position_I: tuple | None = None,
                 initial_yaw: float | None = None) -> None:
        self.autopilot = autopilot
        self.params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
        self.plant = QuadrotorPlant(self.params)
        self.controller = AttitudeController(self.params)
        self.wind = Wind(wind)
        self.contacts = ContactMonitor(world, vehicle)
        self.dt_ns = int(round(NS_PER_S / self.params.physics_rate_hz))
        xi0 = np.asarray(initial_position_I if initial_position_I is not None
                         else world.initial_position_I, float)
        yaw0 = world.initial_yaw if initial_yaw is None else float(initial_yaw)
        if xi0.shape != (3,) or not np.all(np.isfinite(xi0)) or not math.isfinite(yaw0):
            raise ValueError(f'invalid initial condition {xi0}, yaw {yaw0}')
        self.state = hover_state(self.params, xi0, rot_z(yaw0))
        self.t_ns = 0
        self.reference: AttitudeReference | None = None
        self.wall_s = 0.0

    @property
    def t(self) -> float:
        """Return the sim time since boot, seconds."""
        return self.t_ns / NS_PER_S

    def state_view(self) -> VehicleStateView:
        """Ground truth as the autopilot sees it."""
        s = self.state
        return VehicleStateView(self.t, s.xi_I.copy(), s.v_I.copy(), s.R_IB.copy(),
                                s.Omega_B.copy(), self.plant.last_specific_force_B.copy())

    def substep(self, receive: bool) -> SimEvent | None:
        """One physics step: autopilot, inner loop, plant, contacts; return a contact event.

        ``receive``: whether the autopilot reads its MAVLink input at this step.
        """
        t0 = time.perf_counter()
        try:
            return self._step(receive)
        finally:
            self.wall_s += time.perf_counter() - t0

    def _step(self, receive: bool) -> SimEvent | None:
        view = self.state_view()
        self.autopilot.poll(view, receive=receive)
        self.reference = self.autopilot.attitude_reference(view)
        # The autopilot's loop drives its estimate R_IB R_err to the reference R_d, so the
        # truth settles at R_d R_err^T: an estimate error is flown, as on a real autopilot.
        R_d = rot_from_quat(self.reference.q_IB_wxyz)
        cmd = self.controller.rotor_commands(
            self.state, R_d @ self.autopilot.estimate_error(self.t).T,
            self.reference.thrust_norm)
        self.state = self.plant.step(self.state, cmd, self.wind.force_I(self.t))
        self.t_ns += self.dt_ns
        return self.contacts.check(self.t, self.state, self.plant.last_impact_speed)
