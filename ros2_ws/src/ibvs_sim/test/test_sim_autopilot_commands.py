"""The sim autopilot's COMMAND_LONG, parameter, TIMESYNC and stream handling in isolation.

ibvs_sim.core.autopilot.{commands, params, timesync, telemetry} on a fake link that records
what would be sent (no socket). Expected values are PX4's numbers written out (MAV_RESULT
codes, command ids, custom_mode layout), not recomputed with the module's code.
"""
from __future__ import annotations

import math
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from ibvs_common.core.frames import GRAVITY
from ibvs_sim.core.autopilot.commands import CommandHandler
from ibvs_sim.core.autopilot.config import (AttitudeReference, AutopilotConfig,
                                            AutopilotCounters, RateLimitedLog,
                                            VehicleStateView)
from ibvs_sim.core.autopilot.modes import FlightModeMachine
from ibvs_sim.core.autopilot.noise import SensorNoise
from ibvs_sim.core.autopilot.params import ParamServer
from ibvs_sim.core.autopilot.protocol import FlightMode
from ibvs_sim.core.autopilot.setpoints import OffboardSetpoints
from ibvs_sim.core.autopilot.telemetry import Telemetry
from ibvs_sim.core.autopilot.timesync import TimesyncResponder

ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
ARM_DISARM, DO_SET_MODE, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE = 400, 176, 511, 512
ID_HEARTBEAT, ID_ATTITUDE_QUATERNION, ID_HIGHRES_IMU, ID_ATTITUDE_TARGET = 0, 31, 105, 83
ID_EXTENDED_SYS_STATE, ID_SYS_STATUS, ID_GPS_RAW_INT = 245, 1, 24
CUSTOM_MODE_ENABLED = 1
SEVERITY_CRITICAL, SEVERITY_INFO = 2, 6


class FakeMav:
    """Record every ``<message>_send`` call as (message, args)."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, tuple]] = []

    def __getattr__(self, name: str):
        if not name.endswith('_send'):
            raise AttributeError(name)
        return lambda *args: self.sent.append((name[:-len('_send')], args))


class FakeLink:
    """The link's interface, addressed as system 1 component 1, peer always known."""

    def __init__(self) -> None:
        self.mav = FakeMav()
        self.texts: list[tuple[int, str]] = []

    def for_us(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, 1) and target_component in (0, 1)

    def statustext(self, severity: int, text: str) -> None:
        self.texts.append((severity, text))

    def peer_known(self) -> bool:
        return True

    def sent(self, name: str) -> list[tuple]:
        return [args for n, args in self.mav.sent if n == name]


class Wall:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def state(t: float = 2.0, z: float = -1.82) -> VehicleStateView:
    return VehicleStateView(t=t, xi_I=np.array([0.0, 0.0, z]), v_I=np.zeros(3), R_IB=np.eye(3),
                            Omega_B=np.zeros(3), accel_B_specific=np.array([0, 0, -GRAVITY]))


def command(cmd: int, *params: float, target=(1, 1)) -> SimpleNamespace:
    p = list(params) + [0.0] * (7 - len(params))
    return SimpleNamespace(command=cmd, target_system=target[0], target_component=target[1],
                           param1=p[0], param2=p[1], param3=p[2], param4=p[3], param5=p[4],
                           param6=p[5], param7=p[6], get_srcSystem=lambda: 255,
                           get_srcComponent=lambda: 191)


class Rig:
    def __init__(self, **cfg) -> None:
        self.config = AutopilotConfig(**cfg)
        self.wall = Wall()
        self.counters = AutopilotCounters()
        warn = RateLimitedLog(5.0, self.wall)
        self.link = FakeLink()
        self.setpoints = OffboardSetpoints(self.config, self.counters, warn, self.wall)
        self.modes = FlightModeMachine(self.config, self.counters, self.setpoints,
                                       lambda s: None)
        self.reference = AttitudeReference(np.array([1.0, 0.0, 0.0, 0.0]), 0.42, 'hold')
        self.telemetry = Telemetry(self.config, self.counters, warn, self.link,
                                   SensorNoise(self.config), self.modes,
                                   lambda s: self.reference, self.wall)
        self.commands = CommandHandler(self.counters, warn, self.link, self.modes,
                                       self.telemetry)

    def ack(self, msg, st: VehicleStateView | None = None) -> int:
        """Send msg, return the COMMAND_ACK result (and check it went to the sender)."""
        before = len(self.link.sent('command_ack'))
        self.commands.on_command_long(msg, st or state())
        acks = self.link.sent('command_ack')
        assert len(acks) == before + 1
        cmd, result, _progress, _param2, target_system, target_component = acks[-1]
        assert (cmd, target_system, target_component) == (msg.command, 255, 191)
        return result


def test_arm_disarm_results():
    r = Rig()
    assert r.ack(command(ARM_DISARM, 1)) == ACCEPTED                     # already armed
    assert r.ack(command(ARM_DISARM, 0)) == TEMPORARILY_REJECTED         # in the air
    assert r.link.texts[-1] == (SEVERITY_CRITICAL, 'Disarming denied: not landed')
    assert r.ack(command(ARM_DISARM, 0, 21196)) == ACCEPTED and not r.modes.armed
    assert r.ack(command(ARM_DISARM, 2)) == DENIED
    assert r.ack(command(ARM_DISARM, math.nan)) == DENIED
    assert r.ack(command(ARM_DISARM, 1, math.inf)) == DENIED
    assert r.ack(command(ARM_DISARM, 1)) == ACCEPTED and r.modes.armed
    assert r.counters.commands == 7 and r.counters.commands_rejected == 4


def test_arm_in_offboard_without_stream_is_temporarily_rejected():
    r = Rig(start_armed=False)
    r.modes.set_mode(FlightMode.OFFBOARD, state())
    assert r.ack(command(ARM_DISARM, 1)) == TEMPORARILY_REJECTED
    assert r.link.texts == [(SEVERITY_CRITICAL, 'Arming denied: no offboard signal')]


def test_set_mode_results_and_px4s_uint8_cast():
    r = Rig()
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 6)) == TEMPORARILY_REJECTED
    assert r.link.texts[-1][1] == 'Switching to Offboard is currently not available'
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 4, 3)) == ACCEPTED
    assert r.modes.mode is FlightMode.AUTO_LOITER
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 4, 6)) == ACCEPTED
    assert r.modes.mode is FlightMode.AUTO_LAND
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 3)) == ACCEPTED
    assert r.modes.mode is FlightMode.POSCTL
    for main, sub in ((1, 0), (2, 0), (5, 0), (7, 0), (10, 0), (4, 2), (4, 5)):
        assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, main, sub)) == \
            TEMPORARILY_REJECTED, (main, sub)
    assert r.modes.mode is FlightMode.POSCTL
    # 6 << 16 read as uint8_t is 0, an unknown main mode: accepted, nothing changes
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, float(6 << 16))) == ACCEPTED
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 11)) == ACCEPTED
    assert r.modes.mode is FlightMode.POSCTL
    # 256 + 6 reads as 6 (offboard), still without stream; no custom-mode flag: unsupported
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, 262)) == TEMPORARILY_REJECTED
    assert r.ack(command(DO_SET_MODE, 0, 3)) == UNSUPPORTED
    assert r.ack(command(DO_SET_MODE, CUSTOM_MODE_ENABLED, math.nan)) == DENIED


def test_unknown_and_foreign_commands():
    r = Rig()
    assert r.ack(command(21, 0)) == UNSUPPORTED                          # NAV_LAND
    assert r.counters.commands_unsupported == 1
    r.commands.on_command_long(command(ARM_DISARM, 0, 21196, target=(2, 1)), state())
    r.commands.on_command_long(command(ARM_DISARM, 0, 21196, target=(1, 5)), state())
    assert len(r.link.sent('command_ack')) == 1 and r.modes.armed        # not answered
    assert r.ack(command(ARM_DISARM, 1, target=(0, 0))) == ACCEPTED      # broadcast


def test_message_intervals():
    r = Rig(telemetry_default_hz=50.0)
    streams = r.telemetry.streams
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_HIGHRES_IMU, 10_000)) == ACCEPTED
    assert streams[ID_HIGHRES_IMU].interval_s == pytest.approx(0.01)
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_HIGHRES_IMU, 1000)) == ACCEPTED
    assert streams[ID_HIGHRES_IMU].interval_s == pytest.approx(1 / 250)  # clamped to 250 Hz
    assert r.counters.interval_clamped == 1
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_HIGHRES_IMU, -1)) == ACCEPTED
    assert streams[ID_HIGHRES_IMU].interval_s is None
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_HIGHRES_IMU, 0)) == ACCEPTED
    assert streams[ID_HIGHRES_IMU].interval_s == pytest.approx(0.02)
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_HIGHRES_IMU, -2)) == DENIED
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_GPS_RAW_INT, 100_000)) == FAILED
    assert r.ack(command(SET_MESSAGE_INTERVAL, math.nan, 0)) == DENIED
    # the same interval again keeps the phase, a new one restarts it
    streams[ID_ATTITUDE_TARGET].next_due_t = 7.0
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_ATTITUDE_TARGET, 20_000)) == ACCEPTED
    assert streams[ID_ATTITUDE_TARGET].next_due_t == 7.0
    assert r.ack(command(SET_MESSAGE_INTERVAL, ID_ATTITUDE_TARGET, 40_000)) == ACCEPTED
    assert streams[ID_ATTITUDE_TARGET].next_due_t is None


def test_request_message_sends_once_even_when_the_stream_is_off():
    r = Rig()
    r.ack(command(SET_MESSAGE_INTERVAL, ID_ATTITUDE_TARGET, -1))
    assert r.ack(command(REQUEST_MESSAGE, ID_ATTITUDE_TARGET), state(1.5)) == ACCEPTED
    (time_boot_ms, type_mask, q, *_rates, thrust), = r.link.sent('attitude_target')
    assert (time_boot_ms, type_mask, q, thrust) == (1500, 7, [1.0, 0.0, 0.0, 0.0], 0.42)
    assert r.ack(command(REQUEST_MESSAGE, ID_HEARTBEAT)) == ACCEPTED
    (mav_type, autopilot, base_mode, custom_mode, status), = r.link.sent('heartbeat')
    # quadrotor (2), PX4 (12), custom mode + armed (1 | 128), POSCTL (3 << 16), ACTIVE (4)
    assert (mav_type, autopilot, base_mode, custom_mode, status) == (2, 12, 129, 0x30000, 4)
    assert r.ack(command(REQUEST_MESSAGE, ID_EXTENDED_SYS_STATE), state(z=-0.1)) == ACCEPTED
    assert r.link.sent('extended_sys_state') == [(0, 1)]               # on ground
    assert r.ack(command(REQUEST_MESSAGE, ID_GPS_RAW_INT)) == UNSUPPORTED
    assert r.ack(command(REQUEST_MESSAGE, math.inf)) == DENIED


def test_streams_fall_due_in_sim_time_and_rephase_when_polled_slowly():
    r = Rig(telemetry_default_hz=50.0)
    for k in range(101):                                      # 1 ms steps, 0..0.1 s
        r.telemetry.send_due(state(k * 0.001))
    stamps = [args[0] for args in r.link.sent('attitude_quaternion')]
    assert stamps == [0, 20, 40, 60, 80, 100]
    assert len(r.link.sent('sys_status')) == 1                # 5 Hz: only at t = 0
    r.telemetry.send_due(state(0.5))                          # a 0.4 s gap: one message, no burst
    r.telemetry.send_due(state(0.51))
    r.telemetry.send_due(state(0.52))
    stamps = [args[0] for args in r.link.sent('attitude_quaternion')]
    assert stamps[6:] == [500, 520]


def test_params_by_name_index_and_list():
    r = Rig(hover_thrust=0.44, offboard_timeout_s=0.5)
    params = ParamServer(r.config, r.counters, r.link)
    read = SimpleNamespace(target_system=1, target_component=1, param_id=b'MPC_THR_HOVER',
                           param_index=-1)
    params.on_request_read(read, state())
    name, value, kind, count, index = r.link.sent('param_value')[-1]
    assert (name, kind, count, index) == (b'MPC_THR_HOVER', 9, 3, 0)   # REAL32 = 9
    assert value == pytest.approx(0.44)
    params.on_request_read(SimpleNamespace(target_system=1, target_component=1,
                                           param_id='', param_index=2), state())
    name, value, kind, count, index = r.link.sent('param_value')[-1]
    assert (name, kind, index) == (b'COM_OBL_RC_ACT', 6, 2)            # INT32 = 6
    assert struct.unpack('<i', struct.pack('<f', value))[0] == 4       # bytewise: Land mode
    params.on_request_read(SimpleNamespace(target_system=1, target_component=1,
                                           param_id=b'NOPE\x00', param_index=-1), state())
    params.on_request_read(SimpleNamespace(target_system=1, target_component=1,
                                           param_id='', param_index=3), state())
    assert r.link.texts[-1] == (SEVERITY_INFO, '[pm] unknown param: NOPE')
    assert r.counters.param_unknown == 2 and len(r.link.sent('param_value')) == 2
    params.on_request_list(SimpleNamespace(target_system=0, target_component=0), state())
    names = [args[0] for args in r.link.sent('param_value')[2:]]
    assert names == [b'MPC_THR_HOVER', b'COM_OF_LOSS_T', b'COM_OBL_RC_ACT']
    params.on_request_list(SimpleNamespace(target_system=3, target_component=0), state())
    assert len(r.link.sent('param_value')) == 5 and r.counters.param_requests == 5


def test_timesync_answers_requests_with_the_sim_time_in_ns():
    r = Rig()
    ts = TimesyncResponder(r.counters, r.link)
    ts.on_timesync(SimpleNamespace(tc1=0, ts1=123456789), state(t=12.345))
    assert r.link.sent('timesync') == [(12_345_000_000, 123456789)]
    ts.on_timesync(SimpleNamespace(tc1=0, ts1=5), state(t=0.0))           # boot time 0
    ts.on_timesync(SimpleNamespace(tc1=99, ts1=5), state(t=3.0))          # an answer
    assert len(r.link.sent('timesync')) == 1
    assert (r.counters.timesync_answered, r.counters.timesync_unanswered) == (1, 1)
