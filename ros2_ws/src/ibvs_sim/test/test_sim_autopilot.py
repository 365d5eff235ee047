"""Tests of the sim's PX4-like MAVLink autopilot (ibvs_sim.core.autopilot).

The autopilot runs on a real UDP endpoint on 127.0.0.1 (a free port per test); the client is a
plain pymavlink connection, as a companion computer would open it. The autopilot is driven with
a fake ground-truth state and a fake wall clock (no plant). Every wait is bounded. Expected
values are written out independently (PX4's custom_mode numbers, MAV_RESULT codes, physics of a
point mass), never recomputed with the autopilot's own code.
"""
from __future__ import annotations

from dataclasses import dataclass
import os
import socket
import time

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from ibvs_common.core.frames import GRAVITY, rot_x  # noqa: E402
from ibvs_sim.testing import hover_state, INITIAL_XI  # noqa: E402
from ibvs_sim.core.autopilot import (Autopilot, AutopilotConfig,  # noqa: E402
                                     VehicleStateView)
from pymavlink import mavutil  # noqa: E402

mavlink = mavutil.mavlink

CLIENT_SYS = 255
CLIENT_COMP = 191                  # MAV_COMP_ID_ONBOARD_COMPUTER
MAX_DRAIN = 20000
ACK_WAIT_S = 2.0                   # wall bound of every request/answer exchange


class FakeWallClock:
    """A wall clock the test advances by hand (s)."""

    def __init__(self, t0: float = 1000.0) -> None:
        self.now = t0

    def __call__(self) -> float:
        return self.now


@dataclass
class Rig:
    """An autopilot, its fake wall clock, a client and the sim time of the last poll."""

    ap: Autopilot
    wall: FakeWallClock
    client: mavutil.mavfile
    t: float = 0.0
    state_fn: object = None

    def state(self, t: float | None = None) -> VehicleStateView:
        t = self.t if t is None else t
        return self.state_fn(t) if self.state_fn else hover_state(t)

    def poll(self, dt: float = 0.0, wall_dt: float | None = None) -> None:
        """Advance sim time by dt (and the wall clock by wall_dt, default dt), then poll."""
        self.t += dt
        self.wall.now += dt if wall_dt is None else wall_dt
        self.ap.poll(self.state())

    def drain(self) -> list:
        """All messages the client has received so far (non-blocking)."""
        out = []
        for _ in range(MAX_DRAIN):
            m = self.client.recv_msg()
            if m is None:
                break
            out.append(m)
        return out

    def exchange(self, send, want: str, match=lambda m: True, wait_s: float = ACK_WAIT_S):
        """Send with ``send()``, poll (sim time frozen) until a ``want`` message arrives.

        Returns (the message or None, every message received meanwhile).
        """
        send()
        seen = []
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            self.poll()
            for m in self.drain():
                seen.append(m)
                if m.get_type() == want and match(m):
                    return m, seen
            time.sleep(0.001)
        return None, seen

    def command(self, command: int, p1=0.0, p2=0.0, p3=0.0, p4=0.0, p5=0.0, p6=0.0, p7=0.0,
                target_system: int = 1, target_component: int = 1, wait_s: float = ACK_WAIT_S):
        """Send a COMMAND_LONG and return its COMMAND_ACK (or None)."""
        ack, _ = self.exchange(
            lambda: self.client.mav.command_long_send(target_system, target_component, command,
                                                      0, p1, p2, p3, p4, p5, p6, p7),
            'COMMAND_ACK', lambda m: m.command == command, wait_s)
        return ack

    def heartbeat(self):
        """A fresh HEARTBEAT of the autopilot (asks for one with REQUEST_MESSAGE)."""
        self.drain()
        hb, _ = self.exchange(
            lambda: self.client.mav.command_long_send(
                1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_HEARTBEAT,
                0, 0, 0, 0, 0, 0),
            'HEARTBEAT', lambda m: m.get_srcSystem() == 1)
        return hb

    def send_setpoint(self, time_boot_ms: int, q=(1.0, 0.0, 0.0, 0.0), thrust: float = 0.5,
                      type_mask: int = 0b111) -> None:
        self.client.mav.set_attitude_target_send(time_boot_ms, 1, 1, type_mask,
                                                 [float(x) for x in q], 0.0, 0.0, 0.0,
                                                 float(thrust))

    def stream_setpoints(self, duration_s: float, period_s: float = 0.02, dt: float = 0.002,
                         **kw) -> None:
        """Stream setpoints every period_s of sim time for duration_s, polling every dt."""
        steps_per_sp = int(round(period_s / dt))
        for i in range(int(round(duration_s / dt))):
            if i % steps_per_sp == 0:
                self.send_setpoint(int(round(self.t * 1000)), **kw)
            self.poll(dt)
            if i % 50 == 0:
                self.drain()

    def close(self) -> None:
        self.client.close()
        self.ap.close()


def make_rig(signing_key_file: str | None = None, client_key: bytes | None = None,
             client_link_id: int = 1, state_fn=None, **config) -> Rig:
    """Autopilot on a port the kernel picks + a client that has already said hello."""
    wall = FakeWallClock()
    ap = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0',
                                   signing_key_file=signing_key_file, **config),
                   wall_clock=wall)
    client = mavutil.mavlink_connection(f'udpout:127.0.0.1:{ap.local_port}',
                                        source_system=CLIENT_SYS, source_component=CLIENT_COMP,
                                        dialect='common')
    if client_key is not None:
        client.setup_signing(client_key, sign_outgoing=True, link_id=client_link_id)
    rig = Rig(ap, wall, client, state_fn=state_fn)
    client.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                              0, 0, mavlink.MAV_STATE_ACTIVE)
    return rig


# --- independent expected values --------------------------------------------------------------
POSCTL_CUSTOM_MODE = 0x00030000       # PX4: main 3 in bits 16-23
OFFBOARD_CUSTOM_MODE = 0x00060000     # PX4: main 6
AUTO_LAND_CUSTOM_MODE = 0x06040000    # PX4: main 4 (AUTO), sub 6 (LAND) in bits 24-31
RESULT_ACCEPTED = 0
RESULT_TEMPORARILY_REJECTED = 1
RESULT_DENIED = 2
RESULT_UNSUPPORTED = 3
RESULT_FAILED = 4
CMD_ARM_DISARM = 400
CMD_DO_SET_MODE = 176
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512
MSG_ID_ATTITUDE_QUATERNION = 31
MSG_ID_HIGHRES_IMU = 105
FLAG_CUSTOM = 1
FLAG_ARMED = 128


@pytest.fixture
def rig():
    r = make_rig()
    r.poll()
    yield r
    r.close()


def go_offboard(r: Rig) -> None:
    r.stream_setpoints(0.6)
    ack = r.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6, 0)
    assert ack is not None and ack.result == RESULT_ACCEPTED


def angle_between(q_a, q_b) -> float:
    """Rotation angle (rad) between two unit quaternions, sign-insensitive."""
    d = abs(float(np.dot(np.asarray(q_a, float), np.asarray(q_b, float))))
    return 2.0 * float(np.arccos(min(1.0, d)))


# --- heartbeat ----------------------------------------------------------------------------------

def test_heartbeat_px4_quadrotor_armed_posctl(rig):
    msgs = rig.drain()
    hbs = [m for m in msgs if m.get_type() == 'HEARTBEAT']
    assert hbs, 'a new peer is greeted with a HEARTBEAT at once'
    hb = hbs[0]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.type == 2 and hb.autopilot == 12          # QUADROTOR, PX4
    assert hb.base_mode == FLAG_CUSTOM | FLAG_ARMED
    assert hb.custom_mode == POSCTL_CUSTOM_MODE
    assert hb.system_status == 4                         # MAV_STATE_ACTIVE
    assert hb.get_msgbuf()[0] == 0xFD                    # MAVLink 2 frame


def test_heartbeat_is_1hz_wall_clock_whatever_sim_time(rig):
    rig.drain()
    count = 0
    for _ in range(350):          # 3.5 s of wall clock, sim time frozen
        rig.poll(0.0, wall_dt=0.01)
        count += sum(m.get_type() == 'HEARTBEAT' for m in rig.drain())
    assert count in (3, 4)


# --- commands -----------------------------------------------------------------------------------

def test_arm_when_already_armed_is_accepted(rig):
    ack = rig.command(CMD_ARM_DISARM, 1)
    assert ack.result == RESULT_ACCEPTED
    assert ack.target_system == CLIENT_SYS and ack.target_component == CLIENT_COMP
    assert rig.ap.armed


def test_offboard_rejected_without_setpoint_stream(rig):
    ack = rig.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6, 0)
    assert ack.result == RESULT_TEMPORARILY_REJECTED
    assert rig.heartbeat().custom_mode == POSCTL_CUSTOM_MODE


def test_offboard_rejected_with_too_short_stream(rig):
    rig.stream_setpoints(0.2)
    ack = rig.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6, 0)
    assert ack.result == RESULT_TEMPORARILY_REJECTED


def test_packed_offboard_mode_is_acked_and_ignored(rig):
    rig.stream_setpoints(0.6)
    ack = rig.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6 << 16, 0)
    assert ack.result == RESULT_ACCEPTED
    assert rig.heartbeat().custom_mode == POSCTL_CUSTOM_MODE
    assert rig.ap.attitude_reference(rig.state()).source == 'hold'


def test_offboard_accepted_with_stream_and_setpoint_is_the_reference(rig):
    go_offboard(rig)
    hb = rig.heartbeat()
    assert hb.custom_mode == OFFBOARD_CUSTOM_MODE and hb.base_mode & FLAG_ARMED
    # roll 0.1 rad, pitch -0.2 rad, yaw 0.5 rad: quaternion written out (ZYX, w x y z)
    q = np.array([0.96388, 0.06615, -0.08271, 0.24572])
    q /= np.linalg.norm(q)
    rig.send_setpoint(12345, q=q, thrust=0.62)
    rig.poll()
    for _ in range(100):
        if rig.ap.last_setpoint_time_boot_ms == 12345:
            break
        time.sleep(0.001)
        rig.poll()
    assert rig.ap.last_setpoint_time_boot_ms == 12345
    ref = rig.ap.attitude_reference(rig.state())
    assert ref.source == 'offboard'
    assert angle_between(ref.q_IB_wxyz, q) < 1e-5
    assert ref.thrust_norm == pytest.approx(0.62, abs=1e-6)
    assert rig.ap.counters.setpoints_applied >= 1


def test_setpoints_before_offboard_are_recorded_but_not_flown(rig):
    rig.send_setpoint(777, q=(0.9, 0.3, 0.0, np.sqrt(1 - 0.81 - 0.09)), thrust=0.9)
    for _ in range(100):
        rig.poll()
        if rig.ap.last_setpoint_time_boot_ms == 777:
            break
        time.sleep(0.001)
    assert rig.ap.last_setpoint_time_boot_ms == 777
    ref = rig.ap.attitude_reference(rig.state())
    assert ref.source == 'hold'
    assert angle_between(ref.q_IB_wxyz, (1, 0, 0, 0)) < 1e-6     # at the hold point: level
    assert ref.thrust_norm == pytest.approx(0.5, abs=1e-9)        # and hover thrust
    assert rig.ap.counters.setpoints_applied == 0


def test_type_mask_ignored_fields_keep_their_last_value(rig):
    go_offboard(rig)
    q1 = np.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0])           # roll 0.4 rad
    rig.send_setpoint(1, q=q1, thrust=0.55)
    rig.send_setpoint(2, q=(1, 0, 0, 0), thrust=0.7, type_mask=0b111 | 128)   # attitude ignored
    rig.send_setpoint(3, q=(0, 1, 0, 0), thrust=0.1, type_mask=0b111 | 64 | 128)  # both ignored
    for _ in range(100):
        rig.poll()
        if rig.ap.last_setpoint_time_boot_ms == 3:
            break
        time.sleep(0.001)
    ref = rig.ap.attitude_reference(rig.state())
    assert angle_between(ref.q_IB_wxyz, q1) < 1e-6
    assert ref.thrust_norm == pytest.approx(0.7, abs=1e-6)


def test_out_of_range_setpoints_are_counted_and_ignored(rig):
    go_offboard(rig)
    rig.send_setpoint(10, q=(1, 0, 0, 0), thrust=0.6)
    bad = [dict(q=(float('nan'), 0, 0, 0)), dict(q=(2.0, 0, 0, 0)), dict(q=(0, 0, 0, 0)),
           dict(thrust=1.5), dict(thrust=-0.1), dict(thrust=float('nan'))]
    for i, kw in enumerate(bad):
        rig.send_setpoint(100 + i, **kw)
    for _ in range(200):
        rig.poll()
        if rig.ap.counters.setpoints_invalid == len(bad):
            break
        time.sleep(0.001)
    assert rig.ap.counters.setpoints_invalid == len(bad)
    assert rig.ap.last_setpoint_time_boot_ms == 10
    ref = rig.ap.attitude_reference(rig.state())
    assert ref.source == 'offboard' and ref.thrust_norm == pytest.approx(0.6, abs=1e-6)
    assert np.all(np.isfinite(ref.q_IB_wxyz))


def test_disarm_in_air_needs_force(rig):
    ack = rig.command(CMD_ARM_DISARM, 0)
    assert ack.result == RESULT_TEMPORARILY_REJECTED and rig.ap.armed
    ack = rig.command(CMD_ARM_DISARM, 0, 21196)
    assert ack.result == RESULT_ACCEPTED and not rig.ap.armed
    ref = rig.ap.attitude_reference(rig.state())
    assert ref.source == 'disarmed' and ref.thrust_norm == 0.0
    assert not rig.heartbeat().base_mode & FLAG_ARMED


def test_disarm_on_the_ground_is_accepted():
    r = make_rig(state_fn=lambda t: hover_state(t, xi=(0.0, 0.0, -0.10)))
    try:
        assert r.command(CMD_ARM_DISARM, 0).result == RESULT_ACCEPTED
        assert not r.ap.armed
        assert r.command(CMD_ARM_DISARM, 1).result == RESULT_ACCEPTED
        assert r.ap.armed
    finally:
        r.close()


def test_unsupported_and_foreign_commands(rig):
    assert rig.command(22).result == RESULT_UNSUPPORTED                  # NAV_TAKEOFF
    assert rig.command(CMD_SET_MESSAGE_INTERVAL, 30, 10000).result == RESULT_FAILED  # ATTITUDE
    assert rig.command(CMD_ARM_DISARM, 0.5 + 2).result == RESULT_DENIED
    assert rig.command(CMD_ARM_DISARM, 0, target_system=42, wait_s=0.2) is None
    assert rig.ap.counters.foreign_target == 1


# --- telemetry ----------------------------------------------------------------------------------

def count_over_sim_time(r: Rig, duration_s: float, dt: float = 0.001) -> dict:
    counts = {'ATTITUDE_QUATERNION': 0, 'HIGHRES_IMU': 0}
    stamps = {'ATTITUDE_QUATERNION': [], 'HIGHRES_IMU': []}
    for i in range(int(round(duration_s / dt))):
        r.poll(dt)
        if i % 10 == 0:
            for m in r.drain():
                if m.get_type() in counts:
                    counts[m.get_type()] += 1
                    stamps[m.get_type()].append(m.time_boot_ms if m.get_type()
                                                == 'ATTITUDE_QUATERNION' else m.time_usec)
    for m in r.drain():
        if m.get_type() in counts:
            counts[m.get_type()] += 1
    return counts, stamps


def test_default_telemetry_50hz_in_sim_time_and_stamped_with_sim_time(rig):
    counts, stamps = count_over_sim_time(rig, 1.0)
    assert counts['ATTITUDE_QUATERNION'] in (50, 51)
    assert counts['HIGHRES_IMU'] in (50, 51)
    ms = np.array(stamps['ATTITUDE_QUATERNION'])
    assert np.all(np.diff(ms) == 20)          # every 20 ms of sim time
    assert ms[-1] <= 1000


def test_set_message_interval_changes_the_rate(rig):
    ack = rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, 4000)     # 250 Hz
    assert ack.result == RESULT_ACCEPTED
    ack = rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_ATTITUDE_QUATERNION, -1)  # off
    assert ack.result == RESULT_ACCEPTED
    counts, stamps = count_over_sim_time(rig, 1.0)
    assert counts['HIGHRES_IMU'] in (250, 251)
    assert counts['ATTITUDE_QUATERNION'] == 0
    assert np.all(np.diff(stamps['HIGHRES_IMU']) == 4000)   # us
    rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, 0)             # default
    rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_ATTITUDE_QUATERNION, 10000)  # 100 Hz
    counts, _ = count_over_sim_time(rig, 0.5)
    assert counts['HIGHRES_IMU'] in (25, 26)
    assert counts['ATTITUDE_QUATERNION'] in (50, 51)


def test_thrust_landed_state_and_prearm_telemetry_as_px4_reports_them(rig):
    # ATTITUDE_TARGET: the reference's thrust (PX4 reports |thrust_body| in any mode), 50 Hz;
    # EXTENDED_SYS_STATE (landed state) and SYS_STATUS (pre-arm check passed) at 5 Hz.
    msgs = []
    for _ in range(1000):                       # 1 s of sim time
        rig.poll(0.001)
        msgs += rig.drain()
    kinds = [m.get_type() for m in msgs]
    assert kinds.count('ATTITUDE_TARGET') in (50, 51)
    assert kinds.count('EXTENDED_SYS_STATE') in (5, 6) and kinds.count('SYS_STATUS') in (5, 6)
    ref = rig.ap.attitude_reference(rig.state())
    target = [m for m in msgs if m.get_type() == 'ATTITUDE_TARGET'][-1]
    assert target.thrust == pytest.approx(ref.thrust_norm, abs=1e-6)   # POSCTL hold thrust
    assert target.thrust == pytest.approx(0.5, abs=0.01)              # hovering at rest
    ext = [m for m in msgs if m.get_type() == 'EXTENDED_SYS_STATE'][-1]
    assert ext.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    status = [m for m in msgs if m.get_type() == 'SYS_STATUS'][-1]
    assert status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    # on the floor (body origin at the floor, still): on ground
    rig.state_fn = lambda t: hover_state(t, xi=(0.0, 0.0, -0.05))
    for _ in range(400):
        rig.poll(0.001)
    ext = [m for m in rig.drain() if m.get_type() == 'EXTENDED_SYS_STATE'][-1]
    assert ext.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_asking_for_the_same_interval_again_keeps_the_streams_phase(rig):
    # The bridge asks after every link-up: in lockstep that lands at a load-dependent frame,
    # which must not move the samples' times.
    for _ in range(7):
        rig.poll(0.001)
    before = [m.time_boot_ms for m in rig.drain() if m.get_type() == 'ATTITUDE_QUATERNION']
    ack = rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_ATTITUDE_QUATERNION, 20000)   # = default
    assert ack.result == RESULT_ACCEPTED
    _, stamps = count_over_sim_time(rig, 0.1)
    assert all(ms % 20 == before[0] % 20 for ms in stamps['ATTITUDE_QUATERNION'])


def test_telemetry_waits_for_sim_time(rig):
    rig.drain()
    for _ in range(200):              # wall time passes, sim time does not
        rig.poll(0.0, wall_dt=0.01)
    msgs = rig.drain()
    assert sum(m.get_type() == 'HIGHRES_IMU' for m in msgs) <= 1


def test_request_message_sends_one_even_when_disabled(rig):
    rig.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, -1)
    ack, seen = rig.exchange(
        lambda: rig.client.mav.command_long_send(1, 1, CMD_REQUEST_MESSAGE, 0,
                                                 MSG_ID_HIGHRES_IMU, 0, 0, 0, 0, 0, 0),
        'COMMAND_ACK', lambda m: m.command == CMD_REQUEST_MESSAGE)
    assert ack.result == RESULT_ACCEPTED
    assert sum(m.get_type() == 'HIGHRES_IMU' for m in seen) == 1


def test_telemetry_noise_and_fields():
    yaw = 0.7
    r = make_rig(state_fn=lambda t: hover_state(t, yaw=yaw, omega=(0.1, -0.2, 0.3)))
    try:
        r.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, 4000)
        r.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_ATTITUDE_QUATERNION, 4000)
        imu, att = [], []
        for i in range(2000):
            r.poll(0.001)
            if i % 10 == 0:
                for m in r.drain():
                    (imu if m.get_type() == 'HIGHRES_IMU' else att).append(m)
        att = [m for m in att if m.get_type() == 'ATTITUDE_QUATERNION']
        assert len(imu) > 400 and len(att) > 400
        assert all(m.fields_updated == 0b111111 for m in imu)
        gyro = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in imu])
        acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
        np.testing.assert_allclose(gyro.mean(axis=0), [0.1, -0.2, 0.3], atol=0.002)
        np.testing.assert_allclose(gyro.std(axis=0), 0.005, rtol=0.25)
        np.testing.assert_allclose(acc.mean(axis=0), [0.0, 0.0, -9.80665], atol=0.02)
        np.testing.assert_allclose(acc.std(axis=0), 0.05, rtol=0.25)
        rates = np.array([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in att])
        np.testing.assert_allclose(rates.mean(axis=0), [0.1, -0.2, 0.3], atol=0.002)
        q_true = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        q_att = [np.array([m.q1, m.q2, m.q3, m.q4]) for m in att]
        errs = np.degrees([angle_between(q, q_true) for q in q_att])
        cfg = r.ap.config
        std_deg, tau = np.degrees(cfg.attitude_noise_std), cfg.attitude_noise_tau_s
        assert 0.0 < errs.max() < 5 * std_deg * np.sqrt(3)
        # the estimator-like error wanders slowly: the process steps every 10 ms (NOISE_GRID_S)
        # by std * sqrt(3 (1 - exp(-2 * 0.01 / tau))) rms (0.12 deg at 0.7 deg, 2 s), so two
        # samples 4 ms apart differ by at most that; white noise per sample would differ by
        # std * sqrt(6) rms (1.7 deg)
        grid_step = std_deg * np.sqrt(3.0 * (1.0 - np.exp(-2.0 * 0.01 / tau)))
        steps = np.degrees([angle_between(a, b) for a, b in zip(q_att[:-1], q_att[1:])])
        assert np.sqrt(np.mean(steps ** 2)) < grid_step < 0.1 * std_deg * np.sqrt(6.0)
    finally:
        r.close()


def test_the_gyro_noise_is_per_body_axis():
    """gyro_noise_std (FRD x, y, z): PX4 SIH's imu/data sizes, on both rate streams."""
    std = (0.083, 0.040, 0.017)
    r = make_rig(state_fn=lambda t: hover_state(t, omega=(0.1, -0.2, 0.3)), gyro_noise_std=std)
    try:
        r.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, 4000)
        r.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_ATTITUDE_QUATERNION, 4000)
        msgs = []
        for i in range(2000):
            r.poll(0.001)
            if i % 10 == 0:
                msgs += r.drain()
        imu = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in msgs
                        if m.get_type() == 'HIGHRES_IMU'])
        att = np.array([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in msgs
                        if m.get_type() == 'ATTITUDE_QUATERNION'])
        for rates in (imu, att):
            assert len(rates) > 400
            np.testing.assert_allclose(rates.std(axis=0), std, rtol=0.15)
            np.testing.assert_allclose(rates.mean(axis=0), [0.1, -0.2, 0.3], atol=0.015)
    finally:
        r.close()


def test_a_static_estimate_offset_is_reported_as_that_rotation_and_checked():
    """attitude_estimate_offset_rad (roll, pitch) is R_err = exp((roll, pitch, 0)^): reported.

    Noise off, so the error is the offset alone; independent values: the rotation built from
    the elementary rotations for a roll-only offset, and an accelerometer bias b along x_B
    read level by an estimate tilted b / g in pitch (the estimate's gravity f_I = R_IB R_err
    f_B is vertical while the true f_B has the bias), the physics the offset stands for.
    """
    delta = np.radians(1.7)
    ap = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0', attitude_noise_std=0.0,
                                   attitude_estimate_offset_rad=(delta, 0.0)))
    try:
        np.testing.assert_allclose(ap.estimate_error(3.0), rot_x(delta), atol=1e-12)
        q = ap._noisy_attitude(np.eye(3), 3.0)
        assert q == pytest.approx([np.cos(delta / 2), np.sin(delta / 2), 0.0, 0.0], abs=1e-12)
    finally:
        ap.close()
    b = 0.3                                                   # m/s^2 along x_B (FRD)
    ap = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0', attitude_noise_std=0.0,
                                   attitude_estimate_offset_rad=(0.0, np.arcsin(b / GRAVITY))))
    try:
        f_B = np.array([b, 0.0, -np.sqrt(GRAVITY ** 2 - b ** 2)])  # level vehicle + bias
        f_I = ap.estimate_error(0.0) @ f_B
        assert f_I[:2] == pytest.approx([0.0, 0.0], abs=1e-12)   # the estimate reads it level
    finally:
        ap.close()
    for bad in ((0.3, 0.0), (np.nan, 0.0), (0.01,)):
        with pytest.raises(ValueError, match='attitude_estimate_offset_rad'):
            AutopilotConfig(attitude_estimate_offset_rad=bad)


@pytest.mark.parametrize('std, tau', [(None, None), (np.radians(0.2), 5.0)],
                         ids=['default', 'until-2026-11-28'])
def test_attitude_error_is_gauss_markov_with_the_configured_std(std, tau):
    """Stationary std and lag-1 autocorrelation exp(-dt / tau) of the estimate's error.

    The closed forms of a first-order Gauss-Markov process sampled every dt = 20 ms, over
    400 s (>= 80 correlation times), for the default (PX4 SIH's fit) and the old model.
    """
    config = {} if std is None else {'attitude_noise_std': std, 'attitude_noise_tau_s': tau}
    ap = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0', noise_seed=3, **config))
    std, tau = ap.config.attitude_noise_std, ap.config.attitude_noise_tau_s
    try:
        errs = []
        for k in range(20000):               # 400 s of 50 Hz samples
            q = ap._noisy_attitude(np.eye(3), 0.02 * k)
            errs.append(2.0 * np.asarray(q[1:]) * np.sign(q[0]))   # small-angle rotation vector
        errs = np.array(errs)
        np.testing.assert_allclose(errs.std(axis=0), std, rtol=0.2)
        lag1 = np.mean([np.corrcoef(errs[:-1, i], errs[1:, i])[0, 1] for i in range(3)])
        assert lag1 == pytest.approx(np.exp(-0.02 / tau), abs=0.01)
    finally:
        ap.close()


def test_accelerometer_noise_has_its_std_per_body_axis():
    """accel_noise_std per FRD axis (PX4 SIH's 0.28 / 0.95 / 0.80 by the sim node's default)."""
    r = make_rig(state_fn=lambda t: hover_state(t), accel_noise_std=(0.28, 0.95, 0.80))
    try:
        r.command(CMD_SET_MESSAGE_INTERVAL, MSG_ID_HIGHRES_IMU, 4000)
        imu = []
        for i in range(3000):
            r.poll(0.001)
            if i % 10 == 0:
                imu += [m for m in r.drain() if m.get_type() == 'HIGHRES_IMU']
        acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
        assert len(acc) > 600
        np.testing.assert_allclose(acc.std(axis=0), [0.28, 0.95, 0.80], rtol=0.12)
        np.testing.assert_allclose(acc.mean(axis=0), [0.0, 0.0, -9.80665], atol=0.12)
    finally:
        r.close()


def test_a_bad_attitude_noise_setting_is_refused():
    """A negative, NaN or implausible (> 5.7 deg) std, or a negative time constant: ValueError."""
    for bad in (-0.01, np.nan, 0.2):
        with pytest.raises(ValueError, match='attitude_noise_std'):
            AutopilotConfig(attitude_noise_std=bad)
    for bad in (-1.0, np.inf):
        with pytest.raises(ValueError, match='attitude_noise_tau_s'):
            AutopilotConfig(attitude_noise_tau_s=bad)
    assert AutopilotConfig(attitude_noise_std=0.0, attitude_noise_tau_s=0.0)   # off; white


# --- parameters ---------------------------------------------------------------------------------

def test_param_request_read_hover_thrust(rig):
    pv, _ = rig.exchange(
        lambda: rig.client.mav.param_request_read_send(1, 1, b'MPC_THR_HOVER', -1),
        'PARAM_VALUE')
    assert pv.param_id == 'MPC_THR_HOVER'
    assert pv.param_value == pytest.approx(0.5)
    assert pv.param_type == 9                           # MAV_PARAM_TYPE_REAL32


def test_param_request_read_offboard_loss_action_is_land_in_px4s_int32_encoding(rig):
    import struct
    pv, _ = rig.exchange(
        lambda: rig.client.mav.param_request_read_send(1, 1, b'COM_OBL_RC_ACT', -1),
        'PARAM_VALUE')
    assert pv.param_id == 'COM_OBL_RC_ACT'
    assert pv.param_type == 6                           # MAV_PARAM_TYPE_INT32
    # PX4 copies the integer's bytes into the float field (4 = Land mode: the sim's AUTO_LAND)
    assert struct.unpack('<i', struct.pack('<f', pv.param_value))[0] == 4


def test_param_request_read_unknown_name_gets_no_value(rig):
    st, seen = rig.exchange(
        lambda: rig.client.mav.param_request_read_send(1, 1, b'NO_SUCH_PARAM', -1),
        'STATUSTEXT')
    assert st is not None and 'NO_SUCH_PARAM' in st.text
    assert not any(m.get_type() == 'PARAM_VALUE' for m in seen)
    assert rig.ap.counters.param_unknown == 1


# --- clock sync (TIMESYNC) ----------------------------------------------------------------------

def is_answer(m) -> bool:
    """A TIMESYNC answer (tc1 != 0), not one of the autopilot's own requests (tc1 = 0)."""
    return m.get_type() == 'TIMESYNC' and m.tc1 != 0


def own_requests(msgs: list) -> list:
    return [m for m in msgs if m.get_type() == 'TIMESYNC' and m.tc1 == 0]


def test_timesync_requests_of_its_own_at_10_hz_of_sim_time_with_the_boot_time(rig):
    """As PX4: requests (tc1 = 0, ts1 = boot time ns) at timesync_request_hz, sim time."""
    got = []
    for _ in range(50):                               # 0.5 s of 10 ms polls
        rig.poll(0.01)
        got += own_requests(rig.drain())
    assert [m.ts1 for m in got] == [10_000_000 + 100_000_000 * i for i in range(5)]
    assert rig.ap.counters.timesync_requests_sent == 5


def test_timesync_answers_to_its_requests_are_checked_and_counted(rig):
    rig.poll(0.5)
    (request,) = own_requests(rig.drain())
    ros_ns = 1_700_000_000_000_000_000                # the companion's clock
    rig.client.mav.timesync_send(ros_ns, request.ts1)            # a good answer
    rig.client.mav.timesync_send(ros_ns, request.ts1 + 1)        # echoes no request of ours
    rig.client.mav.timesync_send(ros_ns, request.ts1)            # the same one again
    deadline = time.monotonic() + ACK_WAIT_S
    c = rig.ap.counters
    while c.timesync_answers_received + c.timesync_answers_foreign < 3 \
            and time.monotonic() < deadline:
        rig.ap.poll(rig.state())                      # time frozen: no new request
        time.sleep(0.001)
    assert (c.timesync_answers_received, c.timesync_answers_foreign) == (1, 2)
    assert c.timesync_answered == 0                   # none of them was a request


def test_timesync_requests_off_at_zero_hz_and_a_negative_rate_refused():
    r = make_rig(timesync_request_hz=0.0)
    try:
        for _ in range(30):
            r.poll(0.01)
        assert own_requests(r.drain()) == [] and r.ap.counters.timesync_requests_sent == 0
    finally:
        r.close()
    with pytest.raises(ValueError, match='timesync_request_hz'):
        make_rig(timesync_request_hz=-1.0)


def test_timesync_request_answered_with_the_boot_time_in_ns(rig):
    rig.poll(1.234)                                   # sim time = boot time: 1.234 s
    ts1 = 1_700_000_000_123_456_789                   # the companion's clock, echoed
    reply, _ = rig.exchange(lambda: rig.client.mav.timesync_send(0, ts1), 'TIMESYNC', is_answer)
    assert reply is not None
    assert reply.tc1 == 1_234_000_000 and reply.ts1 == ts1
    assert (reply.get_srcSystem(), reply.get_srcComponent()) == (1, 1)
    # the same clock as time_boot_ms of the telemetry
    att, _ = rig.exchange(
        lambda: rig.client.mav.command_long_send(1, 1, CMD_REQUEST_MESSAGE, 0,
                                                 MSG_ID_ATTITUDE_QUATERNION, 0, 0, 0, 0, 0, 0),
        'ATTITUDE_QUATERNION')
    assert att.time_boot_ms * 1_000_000 == reply.tc1
    assert rig.ap.counters.timesync_answered == 1
    assert rig.ap.counters.unknown_messages == 0


def test_timesync_not_answered_at_time_zero_and_answers_ignored(rig):
    assert rig.t == 0.0
    reply, _ = rig.exchange(lambda: rig.client.mav.timesync_send(0, 5_000_000), 'TIMESYNC',
                            is_answer, wait_s=0.3)
    assert reply is None                              # tc1 = 0 would read as a request
    assert rig.ap.counters.timesync_unanswered == 1
    rig.poll(0.02)
    reply, _ = rig.exchange(lambda: rig.client.mav.timesync_send(7, 5_000_000), 'TIMESYNC',
                            is_answer, wait_s=0.3)
    assert reply is None                              # an answer to nobody: ignored
    assert rig.ap.counters.unknown_messages == 0
    assert rig.ap.counters.timesync_answered == 0
    assert rig.ap.counters.timesync_answers_foreign == 1


def test_timesync_answered_where_messages_are_read_with_that_polls_time(rig):
    # Lockstep: no reading during a frame's physics (receive=False); the request is answered
    # at the next poll that reads, with the sim time of that poll (the frame boundary).
    rig.poll(0.02)
    rig.client.mav.timesync_send(0, 123)
    time.sleep(0.05)
    for k in range(1, 20):                            # a frame's substeps, 1 ms each
        rig.ap.poll(rig.state(0.02 + k * 0.001), receive=False)
    assert [m for m in rig.drain() if is_answer(m)] == []
    rig.t = 0.04
    rig.ap.poll(rig.state())
    replies = [m for m in rig.drain() if is_answer(m)]
    assert [(m.tc1, m.ts1) for m in replies] == [(40_000_000, 123)]


def test_timesync_answered_before_the_first_frame_once_time_is_not_zero():
    # poll_before_start reads with telemetry off: a request is answered there too.
    r = make_rig()
    try:
        r.t = 0.5
        r.client.mav.timesync_send(0, 99)
        deadline = time.monotonic() + ACK_WAIT_S
        replies = []
        while not replies and time.monotonic() < deadline:
            r.ap.poll(r.state(), telemetry=False)
            replies = [m for m in r.drain() if is_answer(m)]
            time.sleep(0.001)
        assert [(m.tc1, m.ts1) for m in replies] == [(500_000_000, 99)]
    finally:
        r.close()


# --- failsafe -----------------------------------------------------------------------------------

def test_offboard_loss_lands_and_needs_an_explicit_switch_back(rig):
    assert rig.ap.awaits_setpoints                      # before any engagement: the graph's
    go_offboard(rig)
    rig.send_setpoint(int(rig.t * 1000), q=(np.cos(0.15), 0.0, np.sin(0.15), 0.0), thrust=0.8)
    for _ in range(450):                 # 0.9 s without setpoints: still offboard
        rig.poll(0.002)
    assert rig.ap.mode.name == 'OFFBOARD'
    for _ in range(60):                  # past COM_OF_LOSS_T (1 s)
        rig.poll(0.002)
    assert rig.ap.mode.name == 'AUTO_LAND'
    assert not rig.ap.awaits_setpoints                  # lockstep no longer waits for them
    hb = rig.heartbeat()
    assert hb.custom_mode == AUTO_LAND_CUSTOM_MODE
    assert hb.system_status == 5                        # MAV_STATE_CRITICAL
    ref = rig.ap.attitude_reference(rig.state())
    assert ref.source == 'failsafe'
    assert angle_between(ref.q_IB_wxyz, (1, 0, 0, 0)) < 1e-6   # level, yaw 0 kept
    assert ref.thrust_norm < 0.5
    assert rig.ap.counters.failsafe_events == 1
    # setpoints come back: the failsafe stays until the companion switches back
    rig.stream_setpoints(0.1)
    assert rig.ap.mode.name == 'AUTO_LAND'
    assert rig.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6, 0).result == \
        RESULT_TEMPORARILY_REJECTED
    rig.stream_setpoints(0.5)
    assert rig.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 6, 0).result == RESULT_ACCEPTED
    assert rig.ap.attitude_reference(rig.state()).source == 'offboard'
    rig.poll(0.002)
    assert rig.ap.awaits_setpoints


def test_failsafe_keeps_yaw():
    r = make_rig(state_fn=lambda t: hover_state(t, yaw=1.2, roll=0.3))
    try:
        r.poll()
        go_offboard(r)
        for _ in range(550):             # 1.1 s without setpoints: the failsafe
            r.poll(0.002)
        ref = r.ap.attitude_reference(r.state())
        q_level_yaw = np.array([np.cos(0.6), 0.0, 0.0, np.sin(0.6)])
        assert ref.source == 'failsafe' and angle_between(ref.q_IB_wxyz, q_level_yaw) < 1e-6
    finally:
        r.close()


def test_offboard_loss_on_the_wall_clock_when_sim_time_stalls(rig):
    go_offboard(rig)
    rig.poll(0.0, wall_dt=1.5)
    assert rig.ap.mode.name == 'OFFBOARD'
    rig.poll(0.0, wall_dt=1.0)          # 2.5 s wall > 2.0 s bound, sim time frozen
    assert rig.ap.mode.name == 'AUTO_LAND' and rig.ap.failsafe


def test_failsafe_descent_closed_loop_then_auto_disarm():
    """Point mass in NED, level attitude: dv_z/dt = g - g * thrust / hover."""
    box = {'z': -1.5, 'vz': 0.0}
    r = make_rig(state_fn=lambda t: hover_state(
        t, xi=(0.0, 0.0, box['z']), v=(0.0, 0.0, box['vz'])))
    try:
        r.poll()
        go_offboard(r)
        dt = 0.002
        vz_log = []
        for i in range(int(8.0 / dt)):
            r.poll(dt)
            ref = r.ap.attitude_reference(r.state())
            acc = 9.80665 - 9.80665 * ref.thrust_norm / 0.5
            box['vz'] += acc * dt
            box['z'] += box['vz'] * dt
            if box['z'] >= -0.10:         # on the floor (body origin 0.10 m above it)
                box['z'], box['vz'] = -0.10, 0.0
            vz_log.append(box['vz'])
            if not r.ap.armed:
                break
        assert r.ap.mode.name == 'AUTO_LAND'
        assert max(vz_log) == pytest.approx(0.4, abs=0.03)     # descent rate 0.4 m/s
        assert not r.ap.armed                                   # auto-disarmed 2 s after landing
        assert r.ap.attitude_reference(r.state()).thrust_norm == 0.0
    finally:
        r.close()


# --- hold ---------------------------------------------------------------------------------------

def test_hold_brings_a_displaced_vehicle_back_to_the_hold_point():
    """Point mass in NED with perfect attitude tracking: dv/dt = g e3 - g (thrust/hover) R e3."""
    box = {'xi': np.array(INITIAL_XI), 'v': np.zeros(3), 'R': np.eye(3)}

    def state(t):
        return VehicleStateView(t, box['xi'].copy(), box['v'].copy(), box['R'].copy(),
                                np.zeros(3), np.array([0.0, 0.0, -9.80665]))

    r = make_rig(state_fn=state)
    try:
        r.poll()                                   # hold point = INITIAL_XI
        box['xi'] = box['xi'] + np.array([0.5, -0.3, 0.2])
        box['v'] = np.array([0.2, 0.0, -0.1])
        dt = 0.005
        max_tilt = 0.0
        for _ in range(int(8.0 / dt)):
            ref = r.ap.attitude_reference(r.state())
            assert ref.source == 'hold'
            w, x, y, z = ref.q_IB_wxyz
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
            box['R'] = R
            max_tilt = max(max_tilt, np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
            acc = np.array([0.0, 0.0, 9.80665]) - 9.80665 * ref.thrust_norm / 0.5 * R[:, 2]
            box['v'] = box['v'] + acc * dt
            box['xi'] = box['xi'] + box['v'] * dt
            r.poll(dt)
        np.testing.assert_allclose(box['xi'], INITIAL_XI, atol=0.02)
        assert np.linalg.norm(box['v']) < 0.02
        assert max_tilt <= 35.0 + 1e-6
    finally:
        r.close()


def test_posctl_switch_holds_where_it_was_entered():
    box = {'xi': np.array(INITIAL_XI)}
    r = make_rig(state_fn=lambda t: hover_state(t, xi=box['xi']))
    try:
        r.poll()
        go_offboard(r)
        box['xi'] = np.array([-1.0, 0.5, -1.6])
        assert r.command(CMD_DO_SET_MODE, FLAG_CUSTOM, 3, 0).result == RESULT_ACCEPTED
        assert r.heartbeat().custom_mode == POSCTL_CUSTOM_MODE
        ref = r.ap.attitude_reference(r.state())
        assert ref.source == 'hold'
        assert angle_between(ref.q_IB_wxyz, (1, 0, 0, 0)) < 1e-6 and ref.thrust_norm == 0.5
    finally:
        r.close()


# --- robustness ---------------------------------------------------------------------------------

def test_garbage_unknown_and_truncated_input_is_survived_and_counted(rig):
    port = rig.ap.local_port
    rng = np.random.default_rng(1)
    c = rig.ap.counters
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        # a well-formed MAVLink 2 frame with a message id outside the dialect (0x0ABCDE)
        raw.sendto(bytes([0xFD, 0, 0, 0, 8, 255, 191, 0xDE, 0xBC, 0x0A, 0x12, 0x34]),
                   ('127.0.0.1', port))
        for _ in range(100):
            rig.poll()
            if c.unknown_messages:
                break
            time.sleep(0.001)
        assert c.unknown_messages == 1 and c.malformed == 0
        raw.sendto(bytes([0xFD, 0x40, 0, 0, 7, 255, 191, 76, 0]), ('127.0.0.1', port))  # cut
        for _ in range(20):
            raw.sendto(rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), ('127.0.0.1', port))
        rig.poll()
    ack = rig.command(CMD_ARM_DISARM, 1)           # still answering
    assert ack is not None and ack.result == RESULT_ACCEPTED
    assert c.malformed >= 21


def test_non_finite_state_does_not_crash(rig):
    bad = hover_state(rig.t + 0.1)
    bad.xi_I[0] = np.nan
    bad.R_IB[0, 0] = np.nan
    rig.ap.poll(bad)
    ref = rig.ap.attitude_reference(bad)
    assert np.all(np.isfinite(ref.q_IB_wxyz)) and 0.0 <= ref.thrust_norm <= 1.0
    assert rig.ap.counters.state_invalid >= 1


# --- signing ------------------------------------------------------------------------------------

KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))


@pytest.fixture
def key_file(tmp_path):
    p = tmp_path / 'mavlink.key'
    p.write_bytes(KEY)
    return str(p)


def test_signing_accepts_the_right_key_and_signs_its_messages(key_file):
    r = make_rig(signing_key_file=key_file, client_key=KEY, client_link_id=3)
    try:
        ack = r.command(CMD_ARM_DISARM, 1)
        assert ack is not None and ack.result == RESULT_ACCEPTED
        assert ack.get_signed()
        assert r.ap.counters.signing_rejected == 0
    finally:
        r.close()


def test_signing_key_file_may_be_hex(tmp_path):
    p = tmp_path / 'mavlink.hex'
    p.write_text(KEY.hex() + '\n')
    r = make_rig(signing_key_file=str(p), client_key=KEY, client_link_id=4)
    try:
        assert r.command(CMD_ARM_DISARM, 1).result == RESULT_ACCEPTED
    finally:
        r.close()


def test_signing_rejects_unsigned_commands(key_file):
    r = make_rig(signing_key_file=key_file)
    try:
        assert r.command(CMD_ARM_DISARM, 0, 21196, wait_s=0.3) is None
        assert r.ap.armed
        assert r.ap.counters.signing_rejected >= 2       # the hello heartbeat and the command
        assert r.ap.counters.commands == 0
    finally:
        r.close()


def test_signing_rejects_a_wrong_key(key_file):
    r = make_rig(signing_key_file=key_file, client_key=WRONG_KEY, client_link_id=5)
    try:
        assert r.command(CMD_ARM_DISARM, 0, 21196, wait_s=0.3) is None
        assert r.ap.armed
        assert r.ap.counters.signing_rejected >= 2
    finally:
        r.close()


def test_bad_signing_key_file_is_a_clear_error(tmp_path):
    p = tmp_path / 'short.key'
    p.write_bytes(b'too short')
    with pytest.raises(ValueError, match='32 raw bytes'):
        make_rig(signing_key_file=str(p))


def test_noise_depends_on_sim_time_not_on_the_sampling_history():
    """Lockstep repeatability: rates requested at different times must not change the noise."""
    a = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0', noise_seed=5))
    b = Autopilot(AutopilotConfig(url='udpin:127.0.0.1:0', noise_seed=5))
    try:
        for k in range(300):                     # a sampled at 250 Hz, b at 50 Hz
            a._noisy_attitude(np.eye(3), 0.004 * k)
        for k in range(60):
            b._noisy_attitude(np.eye(3), 0.02 * k)
        qa, qb = a._noisy_attitude(np.eye(3), 1.2), b._noisy_attitude(np.eye(3), 1.2)
        np.testing.assert_allclose(qa, qb, atol=1e-12)
        ga = a._rng_at(3, 1_200_000).normal(size=3)
        gb = b._rng_at(3, 1_200_000).normal(size=3)
        np.testing.assert_array_equal(ga, gb)
    finally:
        a.close()
        b.close()


def test_next_telemetry_time_is_the_earliest_stream_due(rig):
    # Before the first send nothing is due yet; after the first poll at t, the attitude and
    # IMU asked at 200 Hz are next due 5 ms later (the thrust at 50 Hz 20 ms, the status at
    # 5 Hz 200 ms): the earliest is t + 0.005. At 10 Hz, the thrust's 20 ms is the earliest.
    fresh = make_rig()
    try:
        assert fresh.ap.next_telemetry_t() is None
    finally:
        fresh.close()
    for interval_us in (5e3, 1e5):
        for msg_id in (MSG_ID_ATTITUDE_QUATERNION, MSG_ID_HIGHRES_IMU):
            ack = rig.command(CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
            assert ack.result == RESULT_ACCEPTED
        rig.poll(0.5)                   # the changed streams restart their phase now
        t_thrust = rig.ap.next_telemetry_t() if interval_us > 2e4 else None
        rig.poll(0.001)
        if t_thrust is None:
            assert rig.ap.next_telemetry_t() == pytest.approx(rig.t - 0.001 + 0.005)
        else:
            assert rig.ap.next_telemetry_t() == pytest.approx(t_thrust)
            assert t_thrust - rig.t <= 0.02


def test_the_hover_stand_in_sleeps_until_a_stream_is_due_and_serves_it_on_time():
    # The wall-clock stand-in of the benchmarks wakes when a stream is due (or a datagram
    # comes), not every 2 ms: its 100 Hz attitude still arrives at 100 Hz, 10 ms apart.
    from ibvs_sim.core.autopilot.stand_in import HoverStandIn, MAX_WAIT_S, wait_s
    served = HoverStandIn(AutopilotConfig(url='udpin:127.0.0.1:0', telemetry_default_hz=100.0))
    client = mavutil.mavlink_connection(f'udpout:127.0.0.1:{served.local_port}',
                                        source_system=CLIENT_SYS, source_component=CLIENT_COMP,
                                        dialect='common')
    try:
        client.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                  mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)
        arrivals = []
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            m = client.recv_match(type='ATTITUDE_QUATERNION', blocking=True, timeout=0.1)
            if m is not None:
                arrivals.append(time.monotonic())
        late = [t for t in arrivals if t > arrivals[0] + 0.5]          # after the start
        assert 85 <= len(late) / (arrivals[-1] - arrivals[0] - 0.5) <= 115
        assert np.median(np.diff(late)) == pytest.approx(0.01, abs=0.003)
        ap = served.autopilot
        due = ap.next_telemetry_t()
        assert 0.0 <= wait_s(ap, due - 0.004) <= 0.004 + 1e-9      # until the stream is due
        assert wait_s(ap, due + 1.0) == 0.0                         # overdue: at once
        assert wait_s(ap, due - 5.0) == MAX_WAIT_S                  # never longer than this
    finally:
        client.close()
        served.close()


@pytest.mark.parametrize('with_radio', [True, False])
def test_rc_channels_are_the_pilots_radio_once_asked_and_nothing_without_one(with_radio):
    """As PX4: RC_CHANNELS streams only once asked (the onboard link), at the asked rate, with
    the radio's channels at sim time: the mission switch (channel 7) OFF, then ON from 0.5 s.
    Without a radio the request is accepted and nothing is sent (PX4 without RC)."""
    from ibvs_sim.core.radio import PilotSwitchRadio
    radio = PilotSwitchRadio(channel=7, on_at_s=0.5) if with_radio else None
    r = make_rig(radio=radio)
    try:
        r.poll()

        def rc_over(duration_s, dt=0.002):
            got = []
            for i in range(int(round(duration_s / dt))):
                r.poll(dt)
                got += [m for m in r.drain() if m.get_type() == 'RC_CHANNELS']
            return got + [m for m in r.drain() if m.get_type() == 'RC_CHANNELS']
        assert rc_over(0.2) == []                                  # not asked: none
        ack = r.command(CMD_SET_MESSAGE_INTERVAL, 65, 100_000)     # 10 Hz
        assert ack.result == RESULT_ACCEPTED
        got = rc_over(0.8)
        if not with_radio:
            assert got == [] and r.ap.counters.rc_channels_sent == 0
            return
        assert len(got) in (8, 9) and all(m.chancount == 8 for m in got)
        ms = np.array([m.time_boot_ms for m in got])
        assert np.all(np.diff(ms) == 100)                         # 10 Hz of sim time
        assert [m.chan7_raw for m in got] == [1100 if t < 500 else 1900 for t in ms]
        assert {m.chan3_raw for m in got} == {1500} and {m.chan9_raw for m in got} == {0xFFFF}
    finally:
        r.close()
