"""PX4 on its simulator interface (simulator_mavlink, lockstep): parameters, sensors, link.

The Pelican's PX4 parameters, the sensors PX4 reads, and the TCP link PX4 connects to.

PX4 v1.16 SITL (``../shared/px4-sitl/px4-hil``) connects to the simulator's TCP server on
127.0.0.1:(4560 + instance). Each HIL_SENSOR (``id`` 0) sets PX4's clock to its ``time_usec``
and lets PX4 run up to it; PX4 answers with HIL_ACTUATOR_CONTROLS, its motor outputs after
its own mixer (zero while disarmed). PX4 also takes ODOMETRY on this link: with
``estimator_type`` VISION it feeds EKF2's external vision, the motion capture of the paper's
lab. Units as MAVLink defines them (HIL_SENSOR: m/s^2, rad/s, gauss, hPa, m, degC).
docs/firmware_lockstep.md.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import os
import socket
from typing import Any

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import GRAVITY, quat_from_rot
from ibvs_sim.core.dynamics import PlantParams, State
from ibvs_sim.core.firmware.motors import MotorModel, PX4_QUAD_X
from ibvs_sim.core.px4_plant import MOCAP_EKF2_PARAMETERS

os.environ.setdefault('MAVLINK20', '1')
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402  (after MAVLINK20)

SIM_TCP_PORT_BASE = 4560            # PX4 connects to 127.0.0.1:(4560 + instance)
#: HIL_SENSOR.fields_updated bits (MAVLink HIL_SENSOR_UPDATED_FLAGS)
HIL_ACCEL = 0b111
HIL_GYRO = 0b111 << 3
HIL_MAG = 0b111 << 6
HIL_BARO = (1 << 9) | (1 << 11) | (1 << 12)     # abs pressure, pressure altitude, temperature
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VISION = 2
HIL_MODE_ARMED = 128                # HIL_ACTUATOR_CONTROLS.mode: MAV_MODE_FLAG_SAFETY_ARMED
# International Standard Atmosphere, troposphere (ICAO Doc 7488)
ISA_P0_HPA = 1013.25
ISA_T0_K = 288.15
ISA_LAPSE_K_PER_M = 0.0065
ISA_EXPONENT = 5.25588              # g M / (R L)
#: PX4 parameters of this interface: motion capture instead of GNSS and magnetometer
#: (MOCAP_EKF2_PARAMETERS), no magnetometer expected, no RC (the harness is the pilot's GCS).
PX4_HIL_FIXED_PARAMETERS = {**MOCAP_EKF2_PARAMETERS, 'SYS_HAS_MAG': 0, 'EKF2_EV_DELAY': 0,
                            'COM_RC_IN_MODE': 4, 'NAV_DLL_ACT': 0}


class FirmwareLinkError(RuntimeError):
    """The firmware's simulator link failed: no connection, closed, or silent."""


def isa_pressure_hpa(altitude_m: float) -> float:
    """Return the ISA static pressure (hPa) at geopotential altitude ``altitude_m`` (m AMSL)."""
    return ISA_P0_HPA * (1.0 - ISA_LAPSE_K_PER_M * altitude_m / ISA_T0_K) ** ISA_EXPONENT


def isa_temperature_c(altitude_m: float) -> float:
    """Return the ISA temperature (degC) at ``altitude_m`` (m AMSL)."""
    return ISA_T0_K - ISA_LAPSE_K_PER_M * altitude_m - 273.15


def px4_motor_model(plant: PlantParams, curve: float = 0.0) -> MotorModel:
    """Return PX4's quad X outputs -> the plant's rotors, with the plant's rotor thrust."""
    return MotorModel.for_layout(PX4_QUAD_X, plant.rotor_thrust_max, curve)


def px4_hil_parameters(vehicle: VehicleConfig, plant: PlantParams | None = None,
                       curve: float = 0.0) -> dict:
    """Return the PX4 parameters that make the Pelican of vehicle.yaml, as a user sets them.

    Control allocation (PX4's CA_*): 4 rotors of PX4's quad X at the plant's arm length
    (``CA_ROTORn_PX/PY`` = +-arm_length sin 45 deg, m, body FRD), ``CA_ROTORn_KM`` = +-the
    rotors' moment constant (m; > 0 counter-clockwise seen from above). ``THR_MDL_FAC`` =
    ``curve`` (the thrust curve's k, :mod:`~ibvs_sim.core.firmware.motors`).
    ``MPC_THR_HOVER``: the output that holds m g, the hover-thrust estimator's start value.
    Plus :data:`PX4_HIL_FIXED_PARAMETERS`.
    """
    p = plant or PlantParams.from_vehicle(vehicle)
    motors = px4_motor_model(p, curve)
    arm = float(p.arm_length) * math.sin(math.pi / 4.0)
    out: dict = {'CA_AIRFRAME': 0, 'CA_ROTOR_COUNT': len(PX4_QUAD_X)}
    for i, ((x, y), spin) in enumerate(PX4_QUAD_X):
        out[f'CA_ROTOR{i}_PX'] = round(arm * x, 5)
        out[f'CA_ROTOR{i}_PY'] = round(arm * y, 5)
        out[f'CA_ROTOR{i}_KM'] = round(spin * float(p.moment_constant), 5)
    hover = motors.output_for(p.mass * GRAVITY / len(PX4_QUAD_X))
    if not 0.05 < hover < 0.95:
        raise ValueError(f'the rotors hover at output {hover:.3f}: outside (0.05, 0.95)')
    out.update({'THR_MDL_FAC': float(curve), 'MPC_THR_HOVER': round(hover, 4)})
    out.update(PX4_HIL_FIXED_PARAMETERS)
    return out


@dataclass(frozen=True)
class SensorNoise:
    """White noise (1 sigma per sample) and constant biases of the simulated IMU and barometer.

    Defaults: Gazebo Classic's iris IMU (gyro 0.00018 rad/s/sqrt(Hz), accel 0.004 m/s^2/
    sqrt(Hz), at 250 Hz) and a 0.1 m barometer; biases of a calibrated MEMS IMU.
    """

    gyro_std: float = 0.0028            # rad/s
    accel_std: float = 0.063            # m/s^2
    baro_std_m: float = 0.1             # m
    gyro_bias: tuple = (0.001, -0.0015, 0.0005)     # rad/s, body FRD
    accel_bias: tuple = (0.02, -0.03, 0.01)         # m/s^2, body FRD


class Px4Sensors:
    """Ground truth -> HIL_SENSOR and ODOMETRY (motion capture), noise from a seeded stream.

    ``home_alt_m``: the floor's altitude AMSL (m); heights come from ``floor_z`` ({I}, z down).
    """

    def __init__(self, home_alt_m: float, floor_z: float, noise: SensorNoise | None = None,
                 seed: int = 0) -> None:
        self.home_alt_m = float(home_alt_m)
        self.floor_z = float(floor_z)
        self.noise = noise or SensorNoise()
        self.rng = np.random.default_rng(seed)

    def altitude_m(self, state: State) -> float:
        """Return the body origin's altitude AMSL (m)."""
        return self.home_alt_m + (self.floor_z - float(state.xi_I[2]))

    def hil_sensor(self, mav: Any, t_us: int, state: State,
                   specific_force_B: np.ndarray) -> Any:
        """Return the HIL_SENSOR (id 0) of ``state`` at ``t_us``: IMU and barometer, no mag."""
        n = self.noise
        f = np.asarray(specific_force_B, float) + n.accel_bias \
            + self.rng.normal(0.0, n.accel_std, 3)
        w = np.asarray(state.Omega_B, float) + n.gyro_bias + self.rng.normal(0.0, n.gyro_std, 3)
        alt = self.altitude_m(state) + float(self.rng.normal(0.0, n.baro_std_m))
        return mav.hil_sensor_encode(
            int(t_us), *map(float, f), *map(float, w), 0.0, 0.0, 0.0,
            isa_pressure_hpa(alt), 0.0, alt, isa_temperature_c(alt),
            HIL_ACCEL | HIL_GYRO | HIL_BARO, 0)

    @staticmethod
    def odometry(mav: Any, t_us: int, state: State) -> Any:
        """Return the motion-capture pose (ODOMETRY, VISION): position in {I}, R_IB; no twist.

        {I} is PX4's local NED frame here (x_I north), so the pose goes as it is; the
        covariance is left unknown (NaN first element: PX4 uses EKF2_EVP_NOISE / EVA_NOISE).
        """
        q = quat_from_rot(state.R_IB)
        unknown = [math.nan] + [0.0] * 20
        nan = math.nan
        return mav.odometry_encode(int(t_us), MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD,
                                   *map(float, state.xi_I), [float(v) for v in q],
                                   nan, nan, nan, nan, nan, nan, unknown, unknown, 0,
                                   MAV_ESTIMATOR_TYPE_VISION, 100)


@dataclass
class ActuatorOutputs:
    """One HIL_ACTUATOR_CONTROLS: PX4's clock (us), the outputs, whether PX4 is armed."""

    time_us: int
    controls: np.ndarray
    armed: bool


class Px4SimLink:
    """The simulator's end of simulator_mavlink: a TCP server PX4 connects to (one client).

    :meth:`open` binds 127.0.0.1:(4560 + instance) before PX4 starts; :meth:`accept` waits
    for PX4 (wall-clock timeout); :meth:`send` writes a message; :meth:`receive_outputs`
    waits (wall clock) for the next HIL_ACTUATOR_CONTROLS.
    """

    def __init__(self, instance: int, system_id: int = 1, component_id: int = 51) -> None:
        self.port = SIM_TCP_PORT_BASE + int(instance)
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._parser = mavlink.MAVLink(None)
        self._server: socket.socket | None = None
        self._conn: socket.socket | None = None
        self.bad_messages = 0

    def open(self) -> None:
        """Listen on the port (raise OSError when it is taken)."""
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(('127.0.0.1', self.port))
        server.listen(1)
        self._server = server

    def accept(self, timeout_s: float) -> None:
        """Wait for PX4's connection (``timeout_s``, wall clock); raise FirmwareLinkError."""
        if self._server is None:
            self.open()
        self._server.settimeout(timeout_s)
        try:
            conn, _ = self._server.accept()
        except socket.timeout:
            raise FirmwareLinkError(f'PX4 did not connect to TCP {self.port} within '
                                    f'{timeout_s:.0f} s') from None
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn

    @property
    def connected(self) -> bool:
        """Whether PX4 has connected."""
        return self._conn is not None

    def try_accept(self, timeout_s: float) -> bool:
        """Accept PX4's connection if it comes within ``timeout_s`` (wall); whether connected."""
        if self._conn is not None:
            return True
        try:
            self.accept(timeout_s)
        except FirmwareLinkError:
            return False
        return True

    def send(self, msg: Any) -> None:
        """Write one message to PX4; raise FirmwareLinkError when the link is gone."""
        try:
            self._conn.sendall(msg.pack(self.mav))
        except (OSError, AttributeError) as exc:
            raise FirmwareLinkError(f'PX4 simulator link lost: {exc!r}') from None

    def receive_outputs(self, timeout_s: float) -> ActuatorOutputs | None:
        """Wait up to ``timeout_s`` (wall) for HIL_ACTUATOR_CONTROLS; None on timeout.

        Other messages (HEARTBEAT, PX4's COMMAND_LONG asking for ground truth) are read and
        dropped; a closed connection raises FirmwareLinkError.
        """
        self._conn.settimeout(timeout_s)
        while True:
            try:
                data = self._conn.recv(4096)
            except socket.timeout:
                return None
            except OSError as exc:
                raise FirmwareLinkError(f'PX4 simulator link lost: {exc!r}') from None
            if not data:
                raise FirmwareLinkError('PX4 closed the simulator link')
            try:
                messages = self._parser.parse_buffer(data) or []
            except mavlink.MAVError:
                self.bad_messages += 1
                continue
            outputs = None
            for m in messages:
                if m.get_type() == 'HIL_ACTUATOR_CONTROLS':
                    outputs = ActuatorOutputs(int(m.time_usec), np.array(m.controls, float),
                                              bool(m.mode & HIL_MODE_ARMED))
            if outputs is not None:
                return outputs

    def close(self) -> None:
        """Close the connection and the server (idempotent)."""
        for s in (self._conn, self._server):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self._conn = self._server = None
