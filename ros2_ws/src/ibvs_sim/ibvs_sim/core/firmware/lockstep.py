"""The plant under a firmware's motor outputs, in lockstep: :class:`FirmwarePlant`.

Every ``sensor_period`` of sim time the plant sends the firmware its sensors of the current
state (HIL_SENSOR; motion capture every ``mocap_period``) and waits for the motor outputs
that the firmware computes from them; the plant then integrates the next physics steps
(:class:`~ibvs_sim.core.dynamics.QuadrotorPlant`, 500 Hz) under those outputs, with the
wind, and checks contacts. The firmware's clock is the sim's (``time_usec`` = sim time +
``BOOT_OFFSET_US``), so a slow machine costs wall time, never realism. Waits are on the wall
clock (``time.monotonic``) with named limits. ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass
import time

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import rot_z
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.dynamics import PlantParams, QuadrotorPlant, State, Wind, WindConfig
from ibvs_sim.core.events import ContactMonitor, SimEvent
from ibvs_sim.core.firmware.motors import MotorModel
from ibvs_sim.core.firmware.px4_hil import FirmwareLinkError, Px4Sensors, Px4SimLink
from ibvs_sim.core.world import WorldConfig

#: PX4 takes time_usec = 0 as "no time": the firmware's clock is sim time + this (us).
BOOT_OFFSET_US = 1_000_000


@dataclass(frozen=True)
class LockstepConfig:
    """Rates and wall-clock limits of the exchange with the firmware."""

    sensor_rate_hz: float = 250.0        # HIL_SENSOR (PX4's IMU_INTEG_RATE default)
    mocap_rate_hz: float = 50.0          # motion capture (ODOMETRY)
    #: wall clock, s: the firmware's answer to one HIL_SENSOR once it has answered any; a
    #: firmware this late is taken for dead (FirmwareLinkError)
    outputs_timeout_s: float = 10.0
    #: wall clock, s: the wait for an answer while the firmware boots (it answers no
    #: HIL_SENSOR before its modules run); the plant goes on with zero outputs meanwhile
    boot_wait_s: float = 0.02


class FirmwarePlant:
    """The plant stepped under a firmware's motor outputs, in lockstep (see module doc).

    ``start_I``: the start on the floor (x, y of {I}; the body rests on the floor), yaw
    ``start_yaw`` (rad). ``t_ns``: sim time since boot; ``state``: the ground truth;
    ``outputs``: the last motor outputs; ``armed``: the firmware's arming state as its
    outputs say; ``exchanges`` / ``late_answers``: counters.
    """

    def __init__(self, world: WorldConfig, vehicle: VehicleConfig, link: Px4SimLink,
                 motors: MotorModel, sensors: Px4Sensors, start_I: np.ndarray,
                 start_yaw: float = 0.0, wind: WindConfig | None = None,
                 config: LockstepConfig | None = None) -> None:
        self.config = config or LockstepConfig()
        self.params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
        self.plant = QuadrotorPlant(self.params)
        self.link, self.motors, self.sensors = link, motors, sensors
        self.wind = Wind(wind or WindConfig())
        self.contacts = ContactMonitor(world, vehicle)
        self.dt_ns = int(round(NS_PER_S / self.params.physics_rate_hz))
        self.steps_per_sensor = self._steps(self.config.sensor_rate_hz)
        self.steps_per_mocap = self._steps(self.config.mocap_rate_hz)
        xi0 = np.array([float(start_I[0]), float(start_I[1]), self.plant.z_rest])
        self.state = State(xi0, np.zeros(3), rot_z(float(start_yaw)), np.zeros(3),
                           np.zeros(len(motors.output_to_rotor)))
        self.t_ns = 0
        self.step_index = 0
        self.outputs = np.zeros(len(motors.output_to_rotor))
        self.armed = False
        self.answered = False          # the firmware has answered a HIL_SENSOR
        self.exchanges = 0
        self.wall_s = 0.0

    def _steps(self, rate_hz: float) -> int:
        steps = self.params.physics_rate_hz / float(rate_hz)
        if not (rate_hz > 0.0 and abs(steps - round(steps)) < 1e-9 and steps >= 1):
            raise ValueError(f'rate {rate_hz} Hz must divide the physics rate '
                             f'{self.params.physics_rate_hz} Hz')
        return int(round(steps))

    @property
    def t(self) -> float:
        """Return the sim time since boot, seconds."""
        return self.t_ns / NS_PER_S

    @property
    def time_us(self) -> int:
        """Return the firmware's clock now (us)."""
        return self.t_ns // 1000 + BOOT_OFFSET_US

    def substep(self) -> SimEvent | None:
        """One physics step (and the exchange with the firmware when due); a contact event."""
        t0 = time.perf_counter()
        try:
            if self.step_index % self.steps_per_sensor == 0:
                self._exchange()
            cmd = self.motors.rotor_commands(self.outputs)
            self.state = self.plant.step(self.state, cmd, self.wind.force_I(self.t))
            self.t_ns += self.dt_ns
            self.step_index += 1
            return self.contacts.check(self.t, self.state, self.plant.last_impact_speed)
        finally:
            self.wall_s += time.perf_counter() - t0

    def _exchange(self) -> None:
        """Send the sensors of now, wait for the firmware's outputs computed from them."""
        mav = self.link.mav
        self.link.send(self.sensors.hil_sensor(mav, self.time_us, self.state,
                                               self.plant.last_specific_force_B))
        if self.step_index % self.steps_per_mocap == 0:
            self.link.send(self.sensors.odometry(mav, self.time_us, self.state))
        timeout = self.config.outputs_timeout_s if self.answered else self.config.boot_wait_s
        out = self.link.receive_outputs(timeout)
        if out is None:
            if self.answered:
                raise FirmwareLinkError(f'no motor outputs within {timeout:.1f} s (wall) '
                                        f'of the HIL_SENSOR at {self.time_us} us')
            return
        self.answered = True
        self.exchanges += 1
        self.outputs = out.controls[:len(self.outputs)]
        self.armed = out.armed
