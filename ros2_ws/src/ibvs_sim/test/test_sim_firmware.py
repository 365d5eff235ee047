"""Core tests of the firmware lockstep parts: motor map, thrust curve, PX4's parameters, sensors.

Independent values: the rotors' torques from PX4's documented CA_* convention (a rotor at
(PX, PY) with moment coefficient KM gives roll -PY T, pitch PX T, yaw KM T per newton, KM > 0
counter-clockwise) against the plant's own mixer; the ISA pressure table; a level vehicle at
rest measures -g on z (FRD).
"""
import math

import numpy as np
import pytest

from ibvs_common.core.config import load_vehicle
from ibvs_common.core.frames import GRAVITY, rot_from_quat, rot_z
from ibvs_sim.core.dynamics import Mixer, PlantParams, State
from ibvs_sim.core.firmware.motors import (MotorMapError, MotorModel, plant_rotor_for,
                                           PX4_QUAD_X)
from ibvs_sim.core.firmware.px4_hil import (HIL_ACCEL, HIL_BARO, HIL_GYRO, HIL_MAG,
                                            isa_pressure_hpa, mavlink, px4_hil_parameters,
                                            px4_motor_model, Px4Sensors, SensorNoise)


@pytest.fixture(scope='module')
def plant():
    return PlantParams.from_vehicle(load_vehicle())


def test_px4_geometry_gives_the_plants_torques(plant):
    """Each PX4 rotor, as its CA_* parameters place it, drives the plant rotor that makes the
    same roll / pitch / yaw torque per newton (PX4's convention, not the plant's formula)."""
    p = px4_hil_parameters(load_vehicle(), plant)
    motors = px4_motor_model(plant)
    M = Mixer(plant).M
    for i in range(4):
        px, py, km = p[f'CA_ROTOR{i}_PX'], p[f'CA_ROTOR{i}_PY'], p[f'CA_ROTOR{i}_KM']
        expected = np.array([-py, px, km])
        np.testing.assert_allclose(M[1:, motors.output_to_rotor[i]], expected, atol=1e-4)


def test_px4_quad_x_order():
    """PX4's quad X: output 0 front-right, 1 rear-left, 2 front-left, 3 rear-right; the
    plant's rotors: 0 front-right, 1 rear-right, 2 rear-left, 3 front-left."""
    assert MotorModel.for_layout(PX4_QUAD_X, 8.0).output_to_rotor == (0, 2, 3, 1)
    with pytest.raises(MotorMapError):
        plant_rotor_for((1.0, 1.0), -1)          # front-right spins counter-clockwise
    with pytest.raises(MotorMapError):
        MotorModel((0, 0, 1, 2), 8.0)


def test_thrust_curve_and_inverse():
    """T(u) = T_max ((1 - k) u + k u^2): closed-form points; output_for inverts it."""
    m = MotorModel((0, 1, 2, 3), 10.0, curve=0.5)
    np.testing.assert_allclose(m.thrust([0.0, 0.5, 1.0]), [0.0, 10 * (0.25 + 0.125), 10.0])
    for t in (0.0, 1.0, 3.75, 9.99):
        assert m.thrust(m.output_for(t)) == pytest.approx(t, abs=1e-9)
    assert MotorModel((0, 1, 2, 3), 10.0).output_for(4.0) == pytest.approx(0.4)
    # out-of-range and NaN outputs: clipped, NaN is a stopped motor (never a NaN thrust)
    np.testing.assert_allclose(m.thrust([-0.3, 1.7, math.nan]), [0.0, 10.0, 0.0])


def test_rotor_commands_follow_the_map():
    m = MotorModel((0, 2, 3, 1), 8.0)
    np.testing.assert_allclose(m.rotor_commands([0.1, 0.2, 0.3, 0.4, 0.9, 0.9]),
                               [0.8, 3.2, 1.6, 2.4])
    with pytest.raises(MotorMapError):
        m.rotor_commands([0.5, 0.5])


def test_hover_output_balances_weight(plant):
    """MPC_THR_HOVER: four rotors at that output lift m g, for a linear and a curved motor."""
    for k in (0.0, 0.6):
        p = px4_hil_parameters(load_vehicle(), plant, curve=k)
        thrust = px4_motor_model(plant, k).thrust(p['MPC_THR_HOVER'])
        assert 4 * thrust == pytest.approx(plant.mass * GRAVITY, rel=1e-3)
        assert p['THR_MDL_FAC'] == k


def test_isa_pressure_table():
    """ICAO standard atmosphere table: 101325 Pa at 0 m, 89875 at 1000 m, 79495 at 2000 m."""
    assert isa_pressure_hpa(0.0) == pytest.approx(1013.25)
    assert isa_pressure_hpa(1000.0) == pytest.approx(898.75, abs=0.02)
    assert isa_pressure_hpa(2000.0) == pytest.approx(794.95, abs=0.02)


def _encoded(msg):
    """Round-trip a message through the wire format (what PX4 decodes)."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)
    return mavlink.MAVLink(None).parse_buffer(msg.pack(mav))[0]


def test_hil_sensor_at_rest_without_noise():
    """A level vehicle at rest: accel (0, 0, -g) FRD, zero rates, pressure of its altitude."""
    quiet = SensorNoise(0.0, 0.0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sensors = Px4Sensors(home_alt_m=500.0, floor_z=0.0, noise=quiet)
    s = State(np.array([1.0, 2.0, -0.1]), np.zeros(3), rot_z(0.3), np.zeros(3))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)
    m = _encoded(sensors.hil_sensor(mav, 1_234_000, s, np.array([0.0, 0.0, -GRAVITY])))
    assert m.time_usec == 1_234_000 and m.id == 0
    assert (m.xacc, m.yacc) == (0.0, 0.0) and m.zacc == pytest.approx(-GRAVITY, abs=1e-5)
    assert (m.xgyro, m.ygyro, m.zgyro) == (0.0, 0.0, 0.0)
    assert m.pressure_alt == pytest.approx(500.1, abs=1e-3)
    assert m.abs_pressure == pytest.approx(isa_pressure_hpa(500.1), abs=1e-3)
    assert m.fields_updated == HIL_ACCEL | HIL_GYRO | HIL_BARO
    assert not m.fields_updated & HIL_MAG                # SYS_HAS_MAG 0: no magnetometer


def test_sensor_noise_is_seeded_and_sized():
    """Same seed, same samples; the spread is the configured one (5000 samples)."""
    s = State(np.zeros(3), np.zeros(3), np.eye(3), np.zeros(3))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)

    def gyro_x(seed, n):
        sensors = Px4Sensors(0.0, 0.0, seed=seed)
        return np.array([_encoded(sensors.hil_sensor(mav, 1, s, np.zeros(3))).xgyro
                         for _ in range(n)])
    np.testing.assert_array_equal(gyro_x(3, 20), gyro_x(3, 20))
    g = gyro_x(4, 5000)
    noise = SensorNoise()
    assert np.std(g) == pytest.approx(noise.gyro_std, rel=0.05)
    assert np.mean(g) == pytest.approx(noise.gyro_bias[0], abs=4 * noise.gyro_std / 70)


def test_odometry_is_the_pose_in_ned():
    """ODOMETRY: position of {I} (PX4's local NED), quaternion of R_IB, VISION estimator."""
    R = rot_z(0.7) @ np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.1), -math.sin(0.1)],
                               [0.0, math.sin(0.1), math.cos(0.1)]])
    s = State(np.array([-2.0, 0.1, -1.5]), np.zeros(3), R, np.zeros(3))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)
    m = _encoded(Px4Sensors.odometry(mav, 5_000_000, s))
    np.testing.assert_allclose([m.x, m.y, m.z], [-2.0, 0.1, -1.5], atol=1e-6)
    np.testing.assert_allclose(rot_from_quat(np.array(m.q)), R, atol=1e-6)
    assert (m.frame_id, m.child_frame_id, m.estimator_type) == (1, 12, 2)
    assert math.isnan(m.vx) and math.isnan(m.pose_covariance[0])


def test_servo_packet_decoding():
    """ArduPilot's servo packet: magic 18458, rate, count, 16 PWM values (little-endian)."""
    import struct
    from ibvs_sim.core.firmware.ardupilot_json import parse_servo_packet, pwm_to_output
    pwm = [1000, 1500, 2000, 1250] + [0] * 12
    packet = parse_servo_packet(struct.pack('<HHI16H', 18458, 500, 77, *pwm))
    assert (packet.frame_rate_hz, packet.frame_count) == (500, 77)
    np.testing.assert_allclose(pwm_to_output(packet.pwm_us[:4]), [0.0, 0.5, 1.0, 0.25])
    for bad in (b'\x00' * 4, struct.pack('<HHI16H', 1234, 500, 1, *pwm),
                struct.pack('<HHI15H', 18458, 500, 1, *pwm[:15])):
        with pytest.raises(ValueError):
            parse_servo_packet(bad)


def test_state_json_framing_and_frames():
    """The answer is newline, JSON, newline; NED position from home; quaternion of R_IB."""
    import json
    from ibvs_sim.core.firmware.ardupilot_json import state_json
    s = State(np.array([1.0, -2.0, -1.6]), np.array([0.1, 0.2, -0.3]), rot_z(0.5),
              np.array([0.01, 0.02, 0.03]))
    raw = state_json(12.5, s, np.array([0.0, 0.0, -GRAVITY]), z_home=-0.1)
    assert raw.startswith(b'\n') and raw.endswith(b'\n') and raw.count(b'\n') == 2
    obj = json.loads(raw)
    assert obj['timestamp'] == 12.5
    np.testing.assert_allclose(obj['position'], [1.0, -2.0, -1.5])
    np.testing.assert_allclose(obj['velocity'], [0.1, 0.2, -0.3])
    np.testing.assert_allclose(obj['imu']['gyro'], [0.01, 0.02, 0.03])
    np.testing.assert_allclose(obj['quaternion'], [math.cos(0.25), 0.0, 0.0, math.sin(0.25)],
                               atol=1e-12)


def test_ardupilot_hover_throttle(plant):
    """MOT_THST_HOVER: the throttle whose output (SPIN_MIN + (SPIN_MAX - SPIN_MIN) x) lifts
    m g with four rotors; ArduCopter's quad X is PX4's layout (motor 1 front-right CCW)."""
    from ibvs_sim.core.firmware.ardupilot_json import (ardupilot_motor_model,
                                                       ardupilot_parameters, SPIN_MAX, SPIN_MIN)
    p = ardupilot_parameters(load_vehicle(), plant)
    u = SPIN_MIN + (SPIN_MAX - SPIN_MIN) * p['MOT_THST_HOVER']
    assert 4 * ardupilot_motor_model(plant).thrust(u) == pytest.approx(plant.mass * GRAVITY,
                                                                       rel=1e-3)
    assert (p['FRAME_CLASS'], p['FRAME_TYPE']) == (1, 1)
    assert ardupilot_motor_model(plant).output_to_rotor == (0, 2, 3, 1)


class _FakeExchange:
    """A firmware that answers every step with fixed outputs (no sockets)."""

    def __init__(self, u: float) -> None:
        from ibvs_sim.core.firmware.px4_hil import ActuatorOutputs
        self.out = ActuatorOutputs(0, np.full(4, u), True)
        self.after = 0

    def before_step(self, plant):
        return self.out

    def after_step(self, plant):
        self.after += 1


class _FakePilot:
    """Settled after ``at_step`` calls."""

    class hold:
        timeout_s = 5.0

    def __init__(self, at_step: int) -> None:
        self.calls, self.at_step = 0, at_step
        self.armed, self.texts = True, []

    def step(self, t, state):
        self.calls += 1
        return self.calls >= self.at_step

    def close(self):
        pass


class _FakeLink:
    port, connected = 0, True

    def try_accept(self, timeout_s):
        return True

    def close(self):
        pass


def _firmware_physics(u: float, settle_at: int):
    from ibvs_sim.core.firmware.lockstep import FirmwarePhysics, FirmwarePlant
    from ibvs_sim.core.world import load_world
    world, vehicle = load_world(), load_vehicle()
    plant_params = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
    motors = MotorModel.for_layout(PX4_QUAD_X, plant_params.rotor_thrust_max)
    plant = FirmwarePlant(world, vehicle, _FakeExchange(u), motors,
                          np.array([-2.0, 0.1, -1.8]), 0.3)
    return FirmwarePhysics(plant, _FakePilot(settle_at), _FakeLink()), plant


def test_preroll_rebases_the_sim_clock(plant):
    """The sim's clock is 0 until the pre-roll ends, then counts from there; the firmware's
    clock is ahead by the pre-roll plus the boot offset (1 s)."""
    from ibvs_sim.core.firmware.lockstep import BOOT_OFFSET_US
    physics, fw = _firmware_physics(0.0, settle_at=3)     # motors off: rests on the floor
    assert not physics.ready and physics.t_ns == 0
    assert not physics.preroll(15)                        # 15 steps: the pilot asked once
    assert physics.preroll(100)                           # asked at steps 20 and 30
    assert fw.step_index == 30 and physics.origin_ns == 30 * fw.dt_ns
    assert physics.t_ns == 0 and physics.ready
    assert physics.boot_offset_ms == (30 * fw.dt_ns // 1000 + BOOT_OFFSET_US) // 1000
    physics.substep()
    assert physics.t_ns == fw.dt_ns and fw.exchange.after == 31
    view = physics.state_view()
    assert view.t == pytest.approx(fw.dt_ns / 1e9)
    np.testing.assert_allclose(view.accel_B_specific, [0.0, 0.0, -GRAVITY], atol=1e-9)


def test_firmware_plant_starts_on_the_floor_below_the_start_and_obeys_the_motors(plant):
    """At rest on the floor below the start with its yaw; outputs above hover lift it (the
    thrust the motor model gives through the plant's own integration)."""
    physics, fw = _firmware_physics(0.6, settle_at=10 ** 9)
    z_rest = fw.plant.z_rest
    np.testing.assert_allclose(fw.state.xi_I, [-2.0, 0.1, z_rest])
    np.testing.assert_allclose(fw.state.R_IB, rot_z(0.3))
    for _ in range(250):                                  # 0.5 s at 0.6 > hover 0.5
        fw.substep()
    assert fw.state.xi_I[2] < z_rest - 0.05 and fw.armed and fw.exchanges == 250


def test_preroll_that_never_settles_fails_with_the_reason(plant):
    from ibvs_sim.core.firmware.px4_hil import FirmwareLinkError
    physics, fw = _firmware_physics(0.0, settle_at=10 ** 9)
    with pytest.raises(FirmwareLinkError, match='pre-roll'):
        physics.preroll(10 ** 6)
    assert fw.t <= 5.0 + 2 * fw.dt_ns / 1e9


def test_pilot_radio_switch_off_then_on_at_its_mission_time_in_rc_channels():
    """The simulated pilot's radio (--pilot-switch): 8 channels, sticks centred, the switch
    OFF through the pre-roll (no mission time yet) and before on_at_s, ON from then (until
    off_at_s); sent as PX4's simulator_mavlink takes RC input (RC_CHANNELS)."""
    from ibvs_sim.core.radio import PilotSwitchRadio
    radio = PilotSwitchRadio(channel=7, on_at_s=1.0, off_at_s=5.0)
    assert [radio.switch_us(t) for t in (None, 0.0, 0.999, 1.0, 4.9, 5.0)] == \
        [1100, 1100, 1100, 1900, 1900, 1100]
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)
    m = _encoded(radio.message(mav, 3_456_789, 2.0))
    assert m.get_type() == 'RC_CHANNELS' and m.time_boot_ms == 3456 and m.chancount == 8
    raw = [getattr(m, f'chan{i}_raw') for i in range(1, 19)]
    assert raw == [1500] * 6 + [1900, 1500] + [0xFFFF] * 10
    with pytest.raises(ValueError, match='channels 1-8'):
        PilotSwitchRadio(channel=9, on_at_s=1.0)
    # no schedule: the pilot's flips (sim/pilot_switch); the last event by a time holds
    hand = PilotSwitchRadio(channel=7, off_at_s=6.0)
    hand.flip(True, 2.5)
    assert [hand.switch_us(t) for t in (2.4, 2.5, 5.9, 6.0)] == [1100, 1900, 1900, 1100]
    hand.flip(True, 7.0)
    assert hand.switch_us(7.5) == 1900


def test_a_pilot_switch_flip_without_a_radio_is_refused_with_its_reason():
    """sim/pilot_switch with pilot_switch_channel 0: the sim node logs the reason (no crash);
    with a radio the flip lands at the sim's time."""
    from types import SimpleNamespace
    from ibvs_sim.core.radio import PilotSwitchRadio
    from ibvs_sim.driver import SimDriver
    no_radio = SimpleNamespace(radio=None, sim=SimpleNamespace(t=2.0))
    assert 'no radio' in SimDriver.flip_pilot_switch(no_radio, True)
    radio = PilotSwitchRadio(channel=7)
    with_radio = SimpleNamespace(radio=radio, sim=SimpleNamespace(t=2.0))
    assert SimDriver.flip_pilot_switch(with_radio, True) == ''
    assert (radio.switch_us(1.99), radio.switch_us(2.0)) == (1100, 1900)


def test_ardupilot_json_link_try_accept_peeks_and_keeps_the_packet():
    """The pre-roll's "has ArduPilot started" check leaves the first servo packet for the
    exchange, and says no (after its wait) while nothing came."""
    import socket
    import struct
    from ibvs_sim.core.firmware.ardupilot_json import ArduPilotJsonLink
    link = None
    for instance in range(9, 0, -1):
        try:
            link = ArduPilotJsonLink(instance)
            link.open()
            break
        except OSError:
            link = None
    if link is None:
        pytest.skip('no free ArduPilot JSON port (9012-9092)')
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert not link.try_accept(0.01) and not link.connected
        pwm = [1000] * 16
        pwm[0] = 1500
        sender.sendto(struct.pack('<HHI16H', 18458, 500, 7, *pwm), ('127.0.0.1', link.port))
        assert link.try_accept(1.0)
        packet = link.receive(1.0)          # the packet peeked at is still there
        assert packet is not None and packet.frame_count == 7 and packet.pwm_us[0] == 1500
        assert link.connected and link.try_accept(0.0)
    finally:
        sender.close()
        link.close()
