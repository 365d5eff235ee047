"""The plant under a firmware's motor outputs, in lockstep: :class:`FirmwarePlant`.

The plant (:class:`~ibvs_sim.core.dynamics.QuadrotorPlant`, 500 Hz) integrates under the
firmware's last motor outputs, with the wind, and checks contacts; an exchange gets the
outputs, each firmware its own way:

- :class:`Px4Exchange`: every sensor period (250 Hz) the plant sends PX4 the sensors of the
  current state (HIL_SENSOR; motion capture every ``mocap_period``) and waits for the outputs
  PX4 computes from them;
- :class:`ArduPilotExchange`: ArduPilot sends its outputs (a servo packet) at every step and
  waits for the state after the step (the JSON answer).

The firmware's clock is the sim's, so a slow machine costs wall time, never realism. Waits
are on the wall clock (``time.monotonic`` through socket timeouts) with named limits.
ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Callable, Protocol

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import rot_z
from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.autopilot import VehicleStateView
from ibvs_sim.core.dynamics import PlantParams, QuadrotorPlant, State, Wind, WindConfig
from ibvs_sim.core.events import ContactMonitor, SimEvent
from ibvs_sim.core.firmware.ardupilot_json import ArduPilotJsonLink, servo_outputs, state_json
from ibvs_sim.core.firmware.motors import MotorModel
from ibvs_sim.core.radio import PilotSwitchRadio
from ibvs_sim.core.firmware.px4_hil import (ActuatorOutputs, FirmwareLinkError, Px4Sensors,
                                            Px4SimLink)
from ibvs_sim.core.world import WorldConfig

#: PX4 takes time_usec = 0 as "no time": the firmware's clock is sim time + this (us).
BOOT_OFFSET_US = 1_000_000


@dataclass(frozen=True)
class LockstepConfig:
    """Rates and wall-clock limits of the exchange with the firmware."""

    sensor_rate_hz: float = 250.0        # HIL_SENSOR (PX4's IMU_INTEG_RATE default)
    mocap_rate_hz: float = 50.0          # motion capture (ODOMETRY)
    rc_rate_hz: float = 50.0             # the pilot's radio (RC_CHANNELS), when given
    #: wall clock, s: the firmware's answer to one HIL_SENSOR once it has answered any; a
    #: firmware this late is taken for dead (FirmwareLinkError)
    outputs_timeout_s: float = 10.0
    #: wall clock, s: PX4, the wait for an answer while it boots (it answers no HIL_SENSOR
    #: before its modules run; the plant goes on with zero outputs meanwhile); ArduPilot,
    #: the wait for its first servo packet
    boot_wait_s: float = 0.02
    first_packet_timeout_s: float = 60.0


class Exchange(Protocol):
    """How a firmware and the plant trade outputs and sensors around one physics step."""

    def before_step(self, plant: 'FirmwarePlant') -> ActuatorOutputs | None:
        """Return the outputs for the coming step (None: keep the last ones)."""

    def after_step(self, plant: 'FirmwarePlant') -> None:
        """Hand the firmware the state after the step, where its protocol wants it."""


class FirmwarePlant:
    """The plant stepped under a firmware's motor outputs, in lockstep (see module doc).

    ``start_I``: the start on the floor (x, y of {I}; the body rests on the floor), yaw
    ``start_yaw`` (rad). ``t_ns``: sim time since boot; ``state``: the ground truth;
    ``outputs``: the last motor outputs; ``armed``: the firmware's arming state as its
    outputs say; ``exchanges``: the outputs received.
    """

    def __init__(self, world: WorldConfig, vehicle: VehicleConfig, exchange: Exchange,
                 motors: MotorModel, start_I: np.ndarray, start_yaw: float = 0.0,
                 wind: WindConfig | None = None) -> None:
        self.params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
        self.plant = QuadrotorPlant(self.params)
        self.exchange, self.motors = exchange, motors
        self.wind = Wind(wind or WindConfig())
        self._world, self._vehicle = world, vehicle
        self.contacts = ContactMonitor(world, vehicle)
        self.dt_ns = int(round(NS_PER_S / self.params.physics_rate_hz))
        xi0 = np.array([float(start_I[0]), float(start_I[1]), self.plant.z_rest])
        self.state = State(xi0, np.zeros(3), rot_z(float(start_yaw)), np.zeros(3),
                           np.zeros(len(motors.output_to_rotor)))
        self.t_ns = 0
        self.step_index = 0
        self.outputs = np.zeros(len(motors.output_to_rotor))
        self.armed = False
        self.exchanges = 0             # outputs received
        self.wall_s = 0.0
        self.z_home = float(self.state.xi_I[2])    # the firmware's home: the rest at start

    @property
    def t(self) -> float:
        """Return the sim time since boot, seconds."""
        return self.t_ns / NS_PER_S

    def reset_contacts(self) -> None:
        """Watch contacts afresh (the monitor reports one touchdown: the start's is not it)."""
        self.contacts = ContactMonitor(self._world, self._vehicle)

    @property
    def time_us(self) -> int:
        """Return the firmware's clock now (us)."""
        return self.t_ns // 1000 + BOOT_OFFSET_US

    def substep(self) -> SimEvent | None:
        """One physics step (and the exchange with the firmware when due); a contact event."""
        t0 = time.perf_counter()
        try:
            out = self.exchange.before_step(self)
            if out is not None:
                self.exchanges += 1
                self.outputs = out.controls[:len(self.outputs)]
                self.armed = out.armed
            cmd = self.motors.rotor_commands(self.outputs)
            self.state = self.plant.step(self.state, cmd, self.wind.force_I(self.t))
            self.t_ns += self.dt_ns
            self.step_index += 1
            self.exchange.after_step(self)
            return self.contacts.check(self.t, self.state, self.plant.last_impact_speed)
        finally:
            self.wall_s += time.perf_counter() - t0


def steps_per(physics_rate_hz: float, rate_hz: float) -> int:
    """Return the physics steps per period of ``rate_hz``; ValueError unless it divides."""
    steps = physics_rate_hz / float(rate_hz)
    if not (rate_hz > 0.0 and abs(steps - round(steps)) < 1e-9 and steps >= 1):
        raise ValueError(f'rate {rate_hz} Hz must divide the physics rate {physics_rate_hz} Hz')
    return int(round(steps))


class Px4Exchange:
    """PX4 (simulator_mavlink): sensors of the state now, then wait for PX4's outputs."""

    def __init__(self, link: Px4SimLink, sensors: Px4Sensors,
                 config: LockstepConfig | None = None,
                 radio: PilotSwitchRadio | None = None) -> None:
        self.link, self.sensors = link, sensors
        self.config = config or LockstepConfig()
        self.radio = radio             # the pilot's radio (None: PX4 has no RC)
        self.mission_origin_s: float | None = None   # plant time of the mission's t = 0
        self.answered = False          # PX4 has answered a HIL_SENSOR (it has booted)

    def before_step(self, plant: FirmwarePlant) -> ActuatorOutputs | None:
        """Every sensor period: send HIL_SENSOR (and motion capture), wait for the outputs."""
        rate = plant.params.physics_rate_hz
        k = plant.step_index
        if k % steps_per(rate, self.config.sensor_rate_hz):
            return None
        mav, t_us = self.link.mav, plant.time_us
        if self.radio is not None and k % steps_per(rate, self.config.rc_rate_hz) == 0:
            origin = self.mission_origin_s
            self.link.send(self.radio.message(
                mav, t_us, None if origin is None else plant.t - origin))
        self.link.send(self.sensors.hil_sensor(mav, t_us, plant.state,
                                               plant.plant.last_specific_force_B))
        if k % steps_per(rate, self.config.mocap_rate_hz) == 0:
            self.link.send(self.sensors.odometry(mav, t_us, plant.state))
        timeout = self.config.outputs_timeout_s if self.answered else self.config.boot_wait_s
        out = self.link.receive_outputs(timeout)
        if out is None and self.answered:
            raise FirmwareLinkError(f'PX4 sent no motor outputs within {timeout:.1f} s '
                                    f'(wall) of the HIL_SENSOR at {t_us} us')
        self.answered = self.answered or out is not None
        return out

    def after_step(self, plant: FirmwarePlant) -> None:
        """Nothing: PX4 reads the next state at the next sensor period."""


class ArduPilotExchange:
    """ArduPilot (JSON backend): its servo packet before each step, the state after it."""

    def __init__(self, link: ArduPilotJsonLink, config: LockstepConfig | None = None) -> None:
        self.link = link
        self.config = config or LockstepConfig()
        self.packets = 0

    def before_step(self, plant: FirmwarePlant) -> ActuatorOutputs:
        """Wait for ArduPilot's servo packet (its outputs at its clock, the sim's)."""
        timeout = (self.config.outputs_timeout_s if self.packets
                   else self.config.first_packet_timeout_s)
        packet = self.link.receive(timeout)
        if packet is None:
            raise FirmwareLinkError(f'ArduPilot sent no servo packet within {timeout:.1f} s '
                                    f'(wall) at sim time {plant.t:.3f} s')
        self.packets += 1
        return servo_outputs(packet, plant.time_us)

    def after_step(self, plant: FirmwarePlant) -> None:
        """Answer with the state after the step: ArduPilot's clock moves to its timestamp."""
        self.link.answer(state_json(plant.time_us * 1e-6, plant.state,
                                    plant.plant.last_specific_force_B, plant.z_home))


class FirmwarePhysics:
    """A :class:`FirmwarePlant` behind :class:`~ibvs_sim.core.physics.PhysicsLoop`'s interface.

    The sim's clock (``t_ns``) starts at 0 once the pre-roll is over: the firmware booted,
    took off and holds at the start (:meth:`preroll`, called by the sim before its first
    frame). ``origin_ns``: the plant's time then; the firmware's clock is the sim's plus
    ``origin_ns`` plus :data:`BOOT_OFFSET_US` (:attr:`boot_offset_ms`).
    """

    def __init__(self, plant: FirmwarePlant, pilot, link: Px4SimLink | ArduPilotJsonLink,
                 connect_timeout_s: float = 60.0, name: str = 'PX4') -> None:
        self.plant = plant
        self.pilot = pilot
        self.link = link
        self.name = name
        self.connect_timeout_s = float(connect_timeout_s)   # wall, s, the firmware's link
        #: called after each physics step of the mission (the relay's TIMESYNC hand-on)
        self.after_substep: Callable[[], None] | None = None
        self._waiting_since: float | None = None
        self.origin_ns: int | None = None
        self.params = plant.params

    @property
    def ready(self) -> bool:
        """Whether the pre-roll is over (the sim's clock runs)."""
        return self.origin_ns is not None

    def preroll(self, steps: int) -> bool:
        """Step the plant with the pilot for up to ``steps`` steps; True once at the start.

        First waits (a little per call, wall clock) for the firmware's link (PX4 connects,
        ArduPilot sends its first servo packet); FirmwareLinkError when it has not within
        ``connect_timeout_s`` or the pre-roll fails.
        """
        if self.ready:
            return True
        if not self.link.try_accept(0.05):
            now = time.monotonic()
            self._waiting_since = self._waiting_since or now
            if now - self._waiting_since > self.connect_timeout_s:
                raise FirmwareLinkError(f'{self.name} did not connect to port {self.link.port} '
                                        f'within {self.connect_timeout_s:.0f} s (wall)')
            return False
        for _ in range(int(steps)):
            self.plant.substep()
            if self.plant.step_index % 10 == 0 and self.pilot.step(self.plant.t,
                                                                   self.plant.state):
                self.origin_ns = self.plant.t_ns
                self.plant.reset_contacts()     # the mission's touchdown is the one to report
                if isinstance(self.plant.exchange, Px4Exchange):
                    self.plant.exchange.mission_origin_s = self.plant.t   # the radio's clock
                return True
            if self.plant.t > self.pilot.hold.timeout_s:
                raise FirmwareLinkError(
                    f'pre-roll: not holding at the start {self.plant.t:.0f} s after boot '
                    f'(armed {self.pilot.armed}, truth {self.plant.state.xi_I.round(2)}, '
                    f'{self.name} said {self.pilot.texts})')
        return False

    def status(self) -> str:
        """One line on the pre-roll: plant time, armed, height, PX4's last words."""
        s = self.plant.state
        return (f'plant t = {self.plant.t:.1f} s, connected {self.link.connected}, armed '
                f'{self.pilot.armed}, xi_I {np.round(s.xi_I, 2).tolist()}, {self.name} said '
                f'{self.pilot.texts[-2:]}')

    @property
    def boot_offset_ms(self) -> int:
        """Return the firmware's clock minus the sim's (ms), once the pre-roll is over."""
        return (int(self.origin_ns or 0) // 1000 + BOOT_OFFSET_US) // 1000

    @property
    def dt_ns(self) -> int:
        """Return the physics step (ns)."""
        return self.plant.dt_ns

    @property
    def t_ns(self) -> int:
        """Return the sim time (ns) since the pre-roll ended (0 before)."""
        return 0 if self.origin_ns is None else self.plant.t_ns - self.origin_ns

    @property
    def t(self) -> float:
        """Return the sim time (s)."""
        return self.t_ns / NS_PER_S

    @property
    def state(self) -> State:
        """Return the ground truth."""
        return self.plant.state

    @property
    def wall_s(self) -> float:
        """Return the wall clock (s) spent stepping the plant and waiting for the firmware."""
        return self.plant.wall_s

    def state_view(self) -> VehicleStateView:
        """Return the ground truth as the autopilot interface sees it (sim time)."""
        s = self.plant.state
        return VehicleStateView(self.t, s.xi_I.copy(), s.v_I.copy(), s.R_IB.copy(),
                                s.Omega_B.copy(), self.plant.plant.last_specific_force_B.copy())

    def substep(self, receive: bool = True) -> SimEvent | None:
        """One physics step in lockstep with the firmware; a contact event."""
        event = self.plant.substep()
        if self.after_substep is not None:
            self.after_substep()
        return event

    def close(self) -> None:
        """Close the pilot's and the firmware's links."""
        self.pilot.close()
        self.link.close()


def px4_lockstep(world: WorldConfig, vehicle: VehicleConfig, instance: int,
                 start_I: np.ndarray, start_yaw: float, wind: WindConfig | None = None,
                 seed: int = 0, home_alt_m: float | None = None,
                 radio: PilotSwitchRadio | None = None) -> FirmwarePhysics:
    """Return the plant under PX4 (instance ``instance``) with its start pilot; opens the link.

    ``radio``: the pilot's radio that PX4 gets as RC input (None: no RC, as before).

    The plant starts on the floor below ``start_I`` with yaw ``start_yaw``; PX4 must boot
    with MIS_TAKEOFF_ALT = the start's height above that rest (:func:`takeoff_altitude`).
    """
    from ibvs_sim.core.firmware.pilot import Px4StartPilot
    from ibvs_sim.core.firmware.px4_hil import px4_motor_model
    from ibvs_sim.core.px4_plant import SIH_DEFAULT_HOME
    plant_params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
    link = Px4SimLink(instance)
    link.open()
    sensors = Px4Sensors(SIH_DEFAULT_HOME[2] if home_alt_m is None else home_alt_m,
                         world.floor_z, seed=seed)
    plant = FirmwarePlant(world, vehicle, Px4Exchange(link, sensors, radio=radio),
                          px4_motor_model(plant_params), start_I, start_yaw, wind)
    pilot = Px4StartPilot(instance, np.asarray(start_I, float))
    return FirmwarePhysics(plant, pilot, link)


def ardupilot_lockstep(world: WorldConfig, vehicle: VehicleConfig, instance: int,
                       start_I: np.ndarray, start_yaw: float,
                       wind: WindConfig | None = None) -> FirmwarePhysics:
    """Return the plant under ArduCopter (JSON backend, ``instance``) with its start pilot.

    Binds the JSON port (9002 + 10 instance) and the pilot's GCS port; ArduPilot is started
    by the caller afterwards (``ardupilot-sitl start --json``), so that its first servo
    packet finds the port. The plant starts on the floor below ``start_I`` with yaw
    ``start_yaw``; the pilot takes off to the start's height above that rest. ArduPilot
    makes its own IMU, GPS, barometer and compass from the state: no sensor noise seed.
    """
    from ibvs_sim.core.firmware.ardupilot_json import ardupilot_motor_model
    from ibvs_sim.core.firmware.pilot import ArduPilotStartPilot
    plant_params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
    link = ArduPilotJsonLink(instance)
    link.open()
    plant = FirmwarePlant(world, vehicle, ArduPilotExchange(link),
                          ardupilot_motor_model(plant_params), start_I, start_yaw, wind)
    # home is the plant's rest below the start: the position ArduPilot gets is relative to it
    pilot = ArduPilotStartPilot(instance, np.asarray(start_I, float), plant.z_home,
                                plant.z_home - float(start_I[2]))
    return FirmwarePhysics(plant, pilot, link, name='ArduPilot')


def takeoff_altitude(world: WorldConfig, vehicle: VehicleConfig, start_I) -> float:
    """Return the start's height (m) above the body origin at rest on the floor below it."""
    rest_z = world.floor_z - vehicle.envelope_height / 2.0
    return float(rest_z - float(start_I[2]))
