"""ArduPilot on its JSON physics backend (lockstep): parameters, servo packets, state answers.

ArduCopter 4.5 SITL started with ``--model JSON:127.0.0.1`` (``../shared/ardupilot-sitl
start --json``) sends, at each of its physics frames, a binary servo packet by UDP to
127.0.0.1:(9002 + 10 instance): uint16 magic 18458 (16 channels; 29569: 32), uint16 frame
rate (Hz), uint32 frame count, then the PWM values (us), little-endian. The physics answers
the sender with one JSON object, preceded and followed by a newline: ``timestamp`` (s, the
physics' clock, which becomes ArduPilot's), ``imu.gyro`` (rad/s, body FRD), ``imu.
accel_body`` (m/s^2, body FRD, specific force), ``position`` (m, NED from home), ``velocity``
(m/s, NED) and ``quaternion`` (w, x, y, z; body FRD -> NED). ArduPilot makes its own GPS,
barometer and compass from these and waits for each answer. docs/firmware_lockstep.md.
"""
from __future__ import annotations

from dataclasses import dataclass
import json
import socket
import struct

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import GRAVITY, quat_from_rot
from ibvs_sim.core.dynamics import PlantParams, State
from ibvs_sim.core.firmware.motors import MotorModel, PX4_QUAD_X
from ibvs_sim.core.firmware.px4_hil import ActuatorOutputs, FirmwareLinkError

JSON_PORT_BASE = 9002               # ArduPilot sends to 127.0.0.1:(9002 + 10 instance)
SERVO_MAGIC = {18458: 16, 29569: 32}    # magic -> channels
SERVO_HEADER = struct.Struct('<HHI')
#: ArduCopter's quad X (FRAME_CLASS 1, FRAME_TYPE 1): motor 1 front-right CCW, 2 rear-left
#: CCW, 3 front-left CW, 4 rear-right CW on SERVO1..4: the same layout as PX4's quad X.
ARDUPILOT_QUAD_X = PX4_QUAD_X
PWM_MIN_US, PWM_MAX_US = 1000.0, 2000.0      # MOT_PWM_MIN / MOT_PWM_MAX
SPIN_MIN, SPIN_MAX = 0.15, 0.95              # MOT_SPIN_MIN / MOT_SPIN_MAX (ArduCopter defaults)
#: ArduCopter's main loop (Hz): one loop per physics step of the plant (500 Hz); at its default
#: 400 Hz a 2 ms physics frame gives it 333 Hz and the arming check 'Main loop slow' fails
SCHED_LOOP_RATE_HZ = 500


@dataclass
class ServoPacket:
    """One servo packet: ArduPilot's frame rate (Hz), frame count, PWM values (us)."""

    frame_rate_hz: int
    frame_count: int
    pwm_us: np.ndarray


def parse_servo_packet(data: bytes) -> ServoPacket:
    """Decode one servo packet; raise ValueError for a wrong magic or length."""
    if len(data) < SERVO_HEADER.size:
        raise ValueError(f'servo packet of {len(data)} bytes: shorter than its header')
    magic, rate, count = SERVO_HEADER.unpack_from(data)
    channels = SERVO_MAGIC.get(magic)
    if channels is None:
        raise ValueError(f'servo packet magic {magic}: not one of {sorted(SERVO_MAGIC)}')
    size = SERVO_HEADER.size + 2 * channels
    if len(data) != size:
        raise ValueError(f'servo packet of {len(data)} bytes, {size} expected for '
                         f'{channels} channels')
    pwm = np.array(struct.unpack_from(f'<{channels}H', data, SERVO_HEADER.size), float)
    return ServoPacket(int(rate), int(count), pwm)


def pwm_to_output(pwm_us: np.ndarray) -> np.ndarray:
    """Return the normalised motor outputs u in [0, 1] of PWM values (us, 1000-2000)."""
    return np.clip((np.asarray(pwm_us, float) - PWM_MIN_US) / (PWM_MAX_US - PWM_MIN_US),
                   0.0, 1.0)


def state_json(t_s: float, state: State, specific_force_B: np.ndarray,
               z_home: float) -> bytes:
    """Return the physics' answer: newline, the JSON object, newline (ArduPilot's framing).

    ``z_home``: the {I} height of home (the body origin at rest at the start): {I} is NED
    with x north, so the position is ``xi_I`` less home's height.
    """
    xi = np.asarray(state.xi_I, float)
    obj = {'timestamp': float(t_s),
           'imu': {'gyro': [float(v) for v in state.Omega_B],
                   'accel_body': [float(v) for v in specific_force_B]},
           'position': [float(xi[0]), float(xi[1]), float(xi[2] - z_home)],
           'velocity': [float(v) for v in state.v_I],
           'quaternion': [float(v) for v in quat_from_rot(state.R_IB)]}
    return ('\n' + json.dumps(obj, separators=(',', ':')) + '\n').encode()


def ardupilot_motor_model(plant: PlantParams, curve: float = 0.0) -> MotorModel:
    """Return ArduCopter's quad X outputs -> the plant's rotors, with the plant's thrust."""
    return MotorModel.for_layout(ARDUPILOT_QUAD_X, plant.rotor_thrust_max, curve)


def ardupilot_parameters(vehicle: VehicleConfig, plant: PlantParams | None = None,
                         curve: float = 0.0) -> dict:
    """Return the ArduCopter parameters of the Pelican, as a user sets them.

    Quad X (FRAME_CLASS 1, FRAME_TYPE 1); the thrust curve's k as MOT_THST_EXPO; MOT_THST_HOVER
    the throttle that holds m g: ArduPilot maps throttle x to the output SPIN_MIN + (SPIN_MAX
    - SPIN_MIN) x (after its curve), so the hover throttle is (u_hover - SPIN_MIN) / (SPIN_MAX
    - SPIN_MIN) with u_hover the output that lifts m g / 4 per rotor.
    """
    p = plant or PlantParams.from_vehicle(vehicle)
    u_hover = ardupilot_motor_model(p, curve).output_for(p.mass * GRAVITY / 4.0)
    hover = (u_hover - SPIN_MIN) / (SPIN_MAX - SPIN_MIN)
    if not 0.05 < hover < 0.9:
        raise ValueError(f'the rotors hover at throttle {hover:.3f}: outside (0.05, 0.9)')
    return {'FRAME_CLASS': 1, 'FRAME_TYPE': 1, 'MOT_THST_EXPO': float(curve),
            'MOT_THST_HOVER': round(hover, 4), 'MOT_PWM_MIN': int(PWM_MIN_US),
            'MOT_PWM_MAX': int(PWM_MAX_US), 'MOT_SPIN_MIN': SPIN_MIN, 'MOT_SPIN_MAX': SPIN_MAX,
            'SCHED_LOOP_RATE': SCHED_LOOP_RATE_HZ}


class ArduPilotJsonLink:
    """The physics' end of the JSON backend: a UDP socket on 9002 + 10 instance."""

    def __init__(self, instance: int) -> None:
        self.port = JSON_PORT_BASE + 10 * int(instance)
        self._sock: socket.socket | None = None
        self._peer = None
        self.bad_packets = 0

    def open(self) -> None:
        """Bind the port (raise OSError when it is taken)."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(('127.0.0.1', self.port))
        self._sock = sock

    @property
    def connected(self) -> bool:
        """Whether a servo packet came (ArduPilot runs on this link)."""
        return self._peer is not None

    def try_accept(self, timeout_s: float) -> bool:
        """Return whether ArduPilot sends: a packet came, or one waits (up to ``timeout_s``).

        The waiting packet stays for :meth:`receive`. The connectionless twin of
        :meth:`~ibvs_sim.core.firmware.px4_hil.Px4SimLink.try_accept`.
        """
        if self.connected:
            return True
        self._sock.settimeout(timeout_s)
        try:
            self._sock.recvfrom(1024, socket.MSG_PEEK)
        except socket.timeout:
            return False
        except OSError as exc:
            raise FirmwareLinkError(f'ArduPilot JSON link: {exc!r}') from None
        return True

    def receive(self, timeout_s: float) -> ServoPacket | None:
        """Wait up to ``timeout_s`` (wall) for the next servo packet; None on timeout."""
        self._sock.settimeout(timeout_s)
        while True:
            try:
                data, peer = self._sock.recvfrom(1024)
            except socket.timeout:
                return None
            except OSError as exc:
                raise FirmwareLinkError(f'ArduPilot JSON link: {exc!r}') from None
            try:
                packet = parse_servo_packet(data)
            except ValueError:
                self.bad_packets += 1
                continue
            self._peer = peer
            return packet

    def answer(self, payload: bytes) -> None:
        """Send the physics' answer to the address of the last servo packet."""
        if self._peer is not None:
            self._sock.sendto(payload, self._peer)

    def close(self) -> None:
        """Close the socket (idempotent)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def servo_outputs(packet: ServoPacket, t_us: int) -> ActuatorOutputs:
    """Return a servo packet as motor outputs; armed when any motor output is above zero."""
    u = pwm_to_output(packet.pwm_us)
    return ActuatorOutputs(int(t_us), u, bool(np.any(u[:4] > 0.0)))


__all__ = ['ArduPilotJsonLink', 'ardupilot_motor_model', 'ardupilot_parameters',
           'parse_servo_packet', 'pwm_to_output', 'ServoPacket', 'servo_outputs',
           'state_json']
