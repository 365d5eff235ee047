"""The MAVLink bridge core against a pymavlink peer autopilot on 127.0.0.1.

The peer (FakeAutopilot) is written here from the MAVLink message definitions, not from the
bridge: it runs in a thread, sends HEARTBEAT and ATTITUDE_QUATERNION, answers parameter reads and
commands, answers TIMESYNC as PX4 does, and records every SET_ATTITUDE_TARGET with its arrival
time. Its boot clock is a :class:`FrameClock` (whole 20 ms frames, as the lockstep sim's), and the
bridge's ROS clock is the same clock plus a chosen offset: a TIMESYNC round trip inside one frame
measures the offset exactly, one across a frame boundary has an rtt of 20 ms and is rejected, so
mapped times are exact. Expected values come from geometry (a pure yaw rotation, the nose-down
pitch needed to accelerate forward), from the clocks' offset, and from the MAVLink/PX4/ArduPilot
documentation (param2 = 6, custom_mode 20, GUID_OPTIONS bit 3, 21196).
"""
import os
import select
import socket
import threading
import time

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

from ibvs_control.core.frames import GRAVITY, quat_multiply  # noqa: E402
from ibvs_control.core.mavlink_bridge import (  # noqa: E402
    BridgeConfig, HeadingPairing, MavlinkBridge, SetpointSource)
from ibvs_control.core.mavlink_link import LinkConfig  # noqa: E402
from ibvs_control.core.mavlink_sequencer import EngageState, SequencerConfig  # noqa: E402
from ibvs_control.core.modes import Mode  # noqa: E402

MASS = 1.676
PX4_OFFBOARD = 6 << 16
PX4_POSCTL = 3 << 16
KEY = bytes(range(32))
MS = 1_000_000                                  # ns
OFFSET = 1_700_000_000_123_456_789              # ns, ROS (system time) - autopilot boot time
FRAME_NS = 20 * MS


class FrameClock:
    """An autopilot boot clock in whole 20 ms frames (ns), 1 s at creation, never 0."""

    def __init__(self, start_ns=1_000 * MS):
        self.start_ns = start_ns
        self.t0 = time.monotonic_ns()

    def __call__(self):
        return self.start_ns + (time.monotonic_ns() - self.t0) // FRAME_NS * FRAME_NS


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def rotmat(q):
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class FakeAutopilot:
    """A minimal PX4- or ArduPilot-like autopilot speaking MAVLink 2 on udpin."""

    def __init__(self, port, kind='px4', armed=True, params=None, key=None,
                 refuse_disarm_unforced=False, yaw_ned=0.0, boot_clock=None,
                 timesync_on=True, timesync_requests=False):
        self.kind = kind
        self.boot_clock = boot_clock if boot_clock is not None else FrameClock()
        self.timesync_on = timesync_on              # answer TIMESYNC requests
        self.timesync_requests = timesync_requests  # send our own, as PX4 does
        self.timesync_seen = []    # requests (tc1 == 0) received: msg
        self.timesync_answers = []  # (boot ns at receipt, msg) answers to our requests
        self.attitude_ms = []      # time_boot_ms of every ATTITUDE_QUATERNION sent
        self.conn = mavutil.mavlink_connection(f'udpin:127.0.0.1:{port}', source_system=1,
                                               source_component=1)
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.armed = armed
        self.custom_mode = PX4_POSCTL if kind == 'px4' else 0
        self.params = params or {}
        self.refuse_disarm_unforced = refuse_disarm_unforced
        self.yaw_ned = yaw_ned
        self.heartbeats_on = True
        self.setpoints = []        # (t_rx, msg)
        self.commands = []         # (t_rx, msg)
        self.signed = []           # _signed flag of every message received
        self.t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()

    def boot_ms(self):
        return self.boot_clock() // MS

    def _run(self):
        next_hb = next_att = next_ts = 0.0
        kind = {'px4': mavutil.mavlink.MAV_AUTOPILOT_PX4,
                'ardupilot': mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA}[self.kind]
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 0.1
                if self.heartbeats_on and self.conn.clients:
                    base = 1 | (128 if self.armed else 0)
                    self.conn.mav.heartbeat_send(2, kind, base, self.custom_mode, 4)
            if now >= next_att and self.conn.clients:
                next_att = now + 0.02
                if self.heartbeats_on:
                    h = self.yaw_ned / 2.0
                    ms = self.boot_ms()
                    self.attitude_ms.append(ms)
                    self.conn.mav.attitude_quaternion_send(ms, np.cos(h), 0.0, 0.0,
                                                           np.sin(h), 0.1, 0.2, 0.3)
            if self.timesync_requests and now >= next_ts and self.conn.clients:
                next_ts = now + 0.2
                self.conn.mav.timesync_send(0, self.boot_clock())
            msg = self.conn.recv_msg()
            if msg is None:
                select.select([self.conn.port], [], [], 0.001)   # wake on a datagram
                continue
            self._handle(msg, now)

    def _handle(self, msg, now):
        kind = msg.get_type()
        if kind == 'BAD_DATA':
            return
        self.signed.append(bool(getattr(msg, '_signed', False)))
        if kind == 'SET_ATTITUDE_TARGET':
            self.setpoints.append((now, msg))
        elif kind == 'TIMESYNC':
            if msg.tc1 == 0:
                self.timesync_seen.append(msg)
                if self.timesync_on:           # PX4: tc1 = boot time (ns), ts1 echoed
                    self.conn.mav.timesync_send(self.boot_clock(), msg.ts1)
            else:
                self.timesync_answers.append((self.boot_clock(), msg))
        elif kind == 'PARAM_REQUEST_READ':
            name = msg.param_id
            if name in self.params:
                self.conn.mav.param_value_send(name.encode(), float(self.params[name]), 9,
                                               len(self.params), 0)
        elif kind == 'COMMAND_LONG':
            self.commands.append((now, msg))
            self.conn.mav.command_ack_send(msg.command, self._command(msg))

    def _command(self, msg):
        if msg.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE:
            if self.kind == 'px4' and int(msg.param2) == 6:
                self.custom_mode = PX4_OFFBOARD
            elif self.kind == 'ardupilot':
                self.custom_mode = int(msg.param2)
            return 0  # PX4 also ACKs the packed 6 << 16 and ignores it
        if msg.command == mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 == 1.0:
                self.armed = True
                return 0
            if self.refuse_disarm_unforced and int(msg.param2) != 21196:
                return 2  # MAV_RESULT_DENIED: "in the air"
            self.armed = False
            return 0
        return 0

    def set_mode_commands(self):
        return [(t, m) for t, m in self.commands
                if m.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE]

    def arm_commands(self):
        return [(t, m) for t, m in self.commands
                if m.command == mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM]


def make_bridge(port, autopilot='auto', source='config', hover=0.5, key=None,
                hold_last_s=5.0, clock=None, ros_clock=None, **kw):
    """A bridge on udpout to ``port``; ``ros_clock()`` (ns) is what spin() passes to poll()."""
    link = LinkConfig(url=f'udpout:127.0.0.1:{port}', heartbeat_timeout_s=0.5,
                      reconnect_period_s=0.3, signing_key=key)
    seq = SequencerConfig(prestream_s=1.0, command_retry_s=0.3, max_attempts=5,
                          disarm_force_after_s=0.3)
    cfg = BridgeConfig(link=link, mass=MASS, max_thrust_factor=2.0,
                       configured_hover_thrust=hover, autopilot=autopilot,
                       hover_thrust_source=source, param_timeout_s=1.0, param_retry_s=0.2,
                       hold_last_s=hold_last_s, sequencer=seq, **kw)
    bridge = MavlinkBridge(cfg) if clock is None else MavlinkBridge(cfg, clock)
    bridge.test_ros_clock = ros_clock
    return bridge


class FrozenClock:
    """A monotonic clock that only moves when the test advances it."""

    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t


def ros_now(bridge):
    """The bridge's ROS time for poll() (None: the bridge was made without a ROS clock)."""
    clock = getattr(bridge, 'test_ros_clock', None)
    return None if clock is None else clock()


def spin(bridge, seconds, until=None, stream_hz=60.0, force_fn=None, on_tick=None):
    """Tick the bridge like the node's timers; stop early when until() is true.

    ``force_fn(now)``: called at the stream rate, e.g. to feed forces like the controller.
    ``on_tick()``: called every loop (e.g. to move a FrozenClock on).
    """
    t_end = time.monotonic() + seconds
    next_stream = next_hb = 0.0
    samples = []
    while time.monotonic() < t_end:
        now = time.monotonic()
        if force_fn is not None and now >= next_stream:
            force_fn(now)
        if on_tick is not None:
            on_tick()
        if now >= next_hb:
            next_hb = now + 0.2
            bridge.heartbeat()
        samples += bridge.poll(ros_now(bridge))
        if now >= next_stream:
            next_stream = now + 1.0 / stream_hz
            bridge.stream()
        if until is not None and until():
            return True, samples
        time.sleep(0.002)
    return False, samples


def heading_msg_quat(yaw_ned):
    """Heading quaternion (w, x, y, z) of base_link in map for a NED yaw, by hand.

    A NED yaw psi (clockwise from north seen from above) is the ENU yaw pi/2 - psi.
    """
    a = (np.pi / 2 - yaw_ned) / 2.0
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])


@pytest.fixture
def peer_bridge(request):
    made = []

    def factory(peer_kw=None, bridge_kw=None, ros_offset_ns=0, ros_clock=None):
        """Peer + bridge; the bridge's ROS clock = the peer's boot clock + ros_offset_ns."""
        port = free_udp_port()
        peer_kw = dict(peer_kw or {})
        boot = peer_kw.setdefault('boot_clock', FrameClock())
        peer = FakeAutopilot(port, **peer_kw)
        if ros_clock is None:
            def ros_clock():
                return boot() + ros_offset_ns
        bridge = make_bridge(port, ros_clock=ros_clock, **(bridge_kw or {}))
        made.append((peer, bridge))
        return peer, bridge
    yield factory
    for peer, bridge in made:
        bridge.close()
        peer.close()


def wait_link(bridge):
    """Spin until the link is up and the clocks are synced (a FrozenClock is moved on)."""
    clock = bridge._clock

    def on_tick():
        if isinstance(clock, FrozenClock):
            clock.t += 0.002
    ok, _ = spin(bridge, 3.0, until=lambda: bridge.link.link_up
                 and bridge.sequencer is not None and bridge.time_sync.synced,
                 on_tick=on_tick)
    assert ok, f'link never came up or never synced: {bridge.time_sync.status()}'


def last_setpoint(peer):
    assert peer.setpoints, 'no SET_ATTITUDE_TARGET received'
    return peer.setpoints[-1][1]


def same_rotation(q_a, q_b, atol=1e-6):
    return np.allclose(rotmat(q_a), rotmat(q_b), atol=atol)


def test_setpoint_up_with_yaw_90_is_a_pure_yaw_rotation(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    assert bridge.on_heading(1_234_000_000, heading_msg_quat(np.pi / 2)) == ''
    # Heading of NED yaw 90 deg (east) is the ENU identity: checked independently.
    assert np.allclose(heading_msg_quat(np.pi / 2), [1, 0, 0, 0])
    assert bridge.on_force(1_234_000_000, np.array([0.0, 0.0, MASS * GRAVITY])) == ''
    ok, _ = spin(bridge, 1.0,
                 until=lambda: any(m.time_boot_ms == 1234 for _, m in peer.setpoints))
    assert ok
    m = [m for _, m in peer.setpoints if m.time_boot_ms == 1234][0]
    assert m.type_mask == 7
    assert m.target_system == 1 and m.target_component == 1
    c = np.cos(np.pi / 4)
    assert same_rotation(m.q, [c, 0.0, 0.0, c])
    assert m.thrust == pytest.approx(0.5, abs=1e-6)


def test_forward_tilt_pitches_nose_down(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_heading(2_000_000_000, heading_msg_quat(0.0))
    a = 2.0  # m/s^2 forward (+x of NED): m v_dot = -F + m g e3  =>  F = m (g e3 - a e1)
    F = MASS * np.array([-a, 0.0, GRAVITY])
    bridge.on_force(2_000_000_000, F)
    spin(bridge, 0.3)
    m = last_setpoint(peer)
    R = rotmat(m.q)
    assert R[2, 0] > 0.1           # body x (nose) points down (NED z > 0): nose down
    assert R[0, 2] < -0.1          # body z (thrust axis, down) leans back
    pitch = np.arcsin(-R[2, 0])
    assert pitch == pytest.approx(-np.arctan2(a, GRAVITY), abs=1e-6)
    assert abs(R[1, 0]) < 1e-9     # no yaw, no roll
    assert m.thrust == pytest.approx(np.hypot(a, GRAVITY) / GRAVITY * 0.5, rel=1e-6)


def test_thrust_scales_with_configured_and_autopilot_hover(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'hover': 0.4})
    wait_link(bridge)
    bridge.on_heading(3_000_000_000, heading_msg_quat(0.0))
    bridge.on_force(3_000_000_000, np.array([0.0, 0.0, 1.5 * MASS * GRAVITY]))
    spin(bridge, 0.2)
    assert last_setpoint(peer).thrust == pytest.approx(0.6, abs=1e-6)

    peer2, bridge2 = peer_bridge(peer_kw={'params': {'MPC_THR_HOVER': 0.35}},
                                 bridge_kw={'source': 'autopilot'})
    ok, _ = spin(bridge2, 3.0, until=lambda: bridge2.hover.value is not None)
    assert ok and bridge2.hover.value == pytest.approx(0.35, abs=1e-6)
    assert 'MPC_THR_HOVER' in bridge2.status().hover_thrust_source
    bridge2.on_heading(3_000_000_000, heading_msg_quat(0.0))
    bridge2.on_force(3_000_000_000, np.array([0.0, 0.0, MASS * GRAVITY]))
    spin(bridge2, 0.2)
    assert last_setpoint(peer2).thrust == pytest.approx(0.35, abs=1e-6)


def test_setpoint_stream_rate_at_least_50_hz(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_heading(1_000_000_000, heading_msg_quat(0.0))
    bridge.on_force(1_000_000_000, np.array([0.0, 0.0, MASS * GRAVITY]))
    n0 = len(peer.setpoints)
    t0 = time.monotonic()
    spin(bridge, 1.0)
    time.sleep(0.05)
    rate = (len(peer.setpoints) - n0) / (time.monotonic() - t0)
    assert rate >= 50.0, f'measured {rate:.1f} Hz'
    assert bridge.status().setpoint_rate_hz >= 50.0


def test_px4_offboard_after_streaming_then_arm(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'armed': False})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    spin(bridge, 1.3)
    assert peer.set_mode_commands() == []          # IDLE: stream, do not switch
    assert bridge.sequencer.state == EngageState.STANDBY
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 3.0, until=lambda: bridge.sequencer.state == EngageState.ENGAGED)
    assert ok, bridge.sequencer.last_reason
    t_mode, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 6.0)      # custom mode enabled, OFFBOARD main mode
    # > 1 s of stream first (prestream 1.0 s in the bridge clock; the peer stamps receipt, so
    # allow 20 ms of scheduling between the two clocks)
    assert t_mode - peer.setpoints[0][0] > 0.98
    assert peer.custom_mode >> 16 == 6 and peer.armed
    t_arm, arm = peer.arm_commands()[0]
    assert arm.param1 == 1.0 and t_arm > t_mode


def test_px4_switch_requested_immediately_still_waits_for_stream(peer_bridge):
    peer, bridge = peer_bridge()
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer is not None
                 and bridge.sequencer.state == EngageState.ENGAGED)
    assert ok
    t_mode, _ = peer.set_mode_commands()[0]
    assert t_mode - peer.setpoints[0][0] > 0.98
    assert peer.arm_commands() == []               # already armed: no arm command


def test_ardupilot_guided_nogps_with_guid_options_bit3(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.3}, 'armed': False},
        bridge_kw={'source': 'autopilot'})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer.state == EngageState.ENGAGED)
    assert ok, bridge.sequencer.last_reason
    _, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 20.0)
    assert peer.custom_mode == 20 and peer.armed
    assert bridge.hover.value == pytest.approx(0.3)


@pytest.mark.parametrize('guid_options', [0, 7, None])
def test_ardupilot_refuses_without_guid_options_bit3(peer_bridge, guid_options):
    params = {'MOT_THST_HOVER': 0.3}
    if guid_options is not None:
        params['GUID_OPTIONS'] = guid_options
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': params})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 2.5, until=lambda: bridge.sequencer.state == EngageState.REFUSED)
    assert ok
    assert 'GUID_OPTIONS' in bridge.sequencer.last_reason
    spin(bridge, 0.3)
    assert peer.set_mode_commands() == [] and peer.arm_commands() == []


def test_signing_right_key_accepted(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'key': KEY}, bridge_kw={'key': KEY})
    wait_link(bridge)
    spin(bridge, 0.3)
    assert bridge.link.counters.received > 0
    assert peer.signed and all(peer.signed)        # everything we send is signed


def test_signing_unsigned_or_wrong_key_rejected(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'key': KEY})                 # unsigned peer
    peer2, bridge2 = peer_bridge(peer_kw={'key': bytes(32)}, bridge_kw={'key': KEY})
    spin(bridge, 1.0)
    spin(bridge2, 0.5)
    for b in (bridge, bridge2):
        assert not b.link.link_up
        assert b.link.counters.received == 0 and b.link.counters.bad_data > 0
        assert b.sequencer is None


def test_link_loss_then_reengage_only_when_still_flying(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer.state == EngageState.ENGAGED)
    assert ok
    n_modes = len(peer.set_mode_commands())
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up)
    assert ok and bridge.sequencer.state == EngageState.NO_LINK
    spin(bridge, 0.7)
    assert bridge.link.counters.reconnects >= 1 and bridge.link.counters.link_losses == 1
    peer.custom_mode = PX4_POSCTL                  # the autopilot's failsafe took over
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer.state == EngageState.ENGAGED)
    assert ok, bridge.sequencer.last_reason
    assert len(peer.set_mode_commands()) > n_modes

    # Same again, but the supervisor went to FAILSAFE meanwhile: no re-engagement.
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up)
    assert ok
    bridge.on_supervisor_mode(Mode.FAILSAFE)
    peer.custom_mode = PX4_POSCTL
    n_modes = len(peer.set_mode_commands())
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 3.0, until=lambda: bridge.sequencer.state == EngageState.HELD)
    assert ok
    spin(bridge, 1.5)
    assert len(peer.set_mode_commands()) == n_modes
    assert bridge.sequencer.state == EngageState.HELD


def test_shutdown_ramps_thrust_then_forces_disarm(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'refuse_disarm_unforced': True},
                               bridge_kw={'shutdown_ramp_s': 0.6})
    wait_link(bridge)
    bridge.on_heading(1_000_000_000, heading_msg_quat(0.0))
    bridge.on_force(1_000_000_000, np.array([0.0, 0.0, MASS * GRAVITY]))
    bridge.on_supervisor_mode(Mode.LANDING)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer.state == EngageState.ENGAGED)
    assert ok
    bridge.on_supervisor_mode(Mode.SHUTDOWN)
    t_sd = time.monotonic()
    # the controller keeps answering frames: the vehicle time (stamps) runs at wall speed here
    hover = np.array([0.0, 0.0, MASS * GRAVITY])
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.sequencer.state == EngageState.DONE,
                 force_fn=lambda now: bridge.on_force(int(1e9 + (now - t_sd) * 1e9), hover))
    assert ok, bridge.sequencer.last_reason
    assert not peer.armed
    ramp = [(t, m.thrust) for t, m in peer.setpoints if t >= t_sd]
    thrusts = np.array([th for _, th in ramp])
    assert thrusts[0] == pytest.approx(0.5, abs=0.05)
    assert np.all(np.diff(thrusts) <= 1e-6)        # monotonic ramp down
    t_zero = min(t for t, th in ramp if th == 0.0)
    assert 0.5 <= t_zero - t_sd <= 0.9             # ramp of 0.6 s
    disarms = [(t, m) for t, m in peer.arm_commands() if m.param1 == 0.0]
    assert disarms[0][0] >= t_zero - 0.05          # disarm only after the ramp
    assert int(disarms[0][1].param2) == 0          # first a normal disarm (refused) ...
    assert int(disarms[-1][1].param2) == 21196     # ... then forced
    assert bridge.sequencer.disarm_forced


def test_shutdown_ramp_runs_on_vehicle_time_and_on_the_wall_after_a_stall():
    from ibvs_control.core.mavlink_bridge import RAMP_STALL_S, ShutdownRamp
    r = ShutdownRamp(0.5, t_vehicle=10.0, t_wall=100.0)
    r.advance(10.2, 100.9)                 # lockstep: 0.2 s of vehicle time in 0.9 s of wall
    assert r.elapsed(100.9) == pytest.approx(0.2)
    r.advance(10.2, 101.5)                 # stamps stopped: nothing yet ...
    assert r.elapsed(101.5) == pytest.approx(0.2)
    assert r.elapsed(100.9 + RAMP_STALL_S + 0.5) == pytest.approx(0.7)   # ... then the wall


def test_bad_force_is_never_sent_held_then_level_hover(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'yaw_ned': 0.5}, bridge_kw={'hold_last_s': 0.3})
    wait_link(bridge)
    bridge.on_heading(1_000_000_000, heading_msg_quat(0.0))
    F = MASS * np.array([-1.0, 0.0, GRAVITY])
    assert bridge.on_force(1_000_000_000, F) == ''
    spin(bridge, 0.1)
    good_q = np.array(last_setpoint(peer).q)
    for bad in (np.array([np.nan, 0.0, 9.0]), np.array([0.0, 0.0, 1e4]),
                np.array([0.0, 0.0, -5.0])):
        assert bridge.on_force(1_020_000_000, bad) != ''
    spin(bridge, 0.1)
    assert bridge.setpoint_source == SetpointSource.HOLD_LAST
    assert same_rotation(last_setpoint(peer).q, good_q)
    assert last_setpoint(peer).time_boot_ms == 1020     # answered with the new stamp
    spin(bridge, 0.4)
    assert bridge.setpoint_source == SetpointSource.LEVEL_HOVER
    m = last_setpoint(peer)
    assert same_rotation(m.q, [np.cos(0.25), 0.0, 0.0, np.sin(0.25)])   # level, yaw 0.5
    assert m.thrust == pytest.approx(0.5)
    for _, m in peer.setpoints:
        assert np.all(np.isfinite(m.q)) and np.isfinite(m.thrust)
    assert bridge.on_heading(1_040_000_000, np.array([np.nan, 0, 0, 1.0])) != ''
    assert bridge.on_heading(1_060_000_000, np.array([2.0, 0, 0, 0])) != ''


def test_failsafe_level_at_current_yaw_below_hover(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'yaw_ned': -1.0})
    wait_link(bridge)
    bridge.on_heading(1_000_000_000, heading_msg_quat(0.7))
    bridge.on_force(1_000_000_000, MASS * np.array([-2.0, 1.0, GRAVITY]))
    bridge.on_supervisor_mode(Mode.FAILSAFE)
    spin(bridge, 0.2)
    m = last_setpoint(peer)
    assert same_rotation(m.q, [np.cos(-0.5), 0.0, 0.0, np.sin(-0.5)])
    assert m.thrust == pytest.approx(0.9 * 0.5)
    assert bridge.setpoint_source == SetpointSource.FAILSAFE


def test_imu_held_until_synced_then_stamped_boot_time_plus_offset(peer_bridge):
    # The autopilot does not answer TIMESYNC yet: its attitude is received, never published.
    peer, bridge = peer_bridge(peer_kw={'yaw_ned': np.pi / 2, 'timesync_on': False},
                               ros_offset_ns=OFFSET)
    ok, samples = spin(bridge, 2.0, until=lambda: bridge.link.link_up
                       and bridge.imu_dropped_unsynced >= 10)
    assert ok and samples == []
    assert peer.timesync_seen, 'the bridge asks'
    assert all(m.ts1 > OFFSET for m in peer.timesync_seen)       # ts1 = its ROS time
    st = bridge.status()
    assert not st.time_sync.synced and st.time_sync.offset_ns is None
    warnings = [text for level, text in bridge.pop_events() if level == 'warn']
    assert any('imu/data' in w and 'not synced' in w for w in warnings)
    # Answered now: synced from the median of 5, then every sample stamped boot + offset.
    peer.timesync_on = True
    ok, _ = spin(bridge, 2.0, until=lambda: bridge.time_sync.synced)
    assert ok
    assert bridge.time_sync.offset_ns == OFFSET                  # exact: rtt 0 in a frame
    _, samples = spin(bridge, 0.3)
    assert len(samples) >= 5
    sent_ns = {ms * MS for ms in peer.attitude_ms}
    for s in samples:
        assert s.stamp_ns - OFFSET in sent_ns                    # boot time of a sample + offset
    assert [s.stamp_ns for s in samples] == sorted(s.stamp_ns for s in samples)
    s = samples[-1]
    # Facing east: base_link coincides with map (ENU) -> identity quaternion.
    assert same_rotation(s.q_wxyz, [1.0, 0.0, 0.0, 0.0], atol=1e-6)
    assert np.allclose(s.angular_velocity_flu, [0.1, -0.2, -0.3])
    assert same_rotation(quat_multiply([1, 0, 0, 0], s.q_wxyz), s.q_wxyz)
    st = bridge.status()
    assert st.time_sync.accepted >= 5 and st.time_sync.last_rtt_ns is not None


def test_autopilot_reboot_holds_the_imu_until_synced_again(peer_bridge):
    frames = FrameClock(start_ns=100_000 * MS)     # booted 100 s ago
    boot_epoch = [0]                                # ns of `frames` at the last boot

    def boot():
        return frames() - boot_epoch[0]
    peer, bridge = peer_bridge(peer_kw={'boot_clock': boot},
                               ros_clock=lambda: frames() + OFFSET)
    wait_link(bridge)
    assert bridge.time_sync.offset_ns == OFFSET
    # Reboot: the boot clock starts again at 1 s; our ROS clock runs on.
    boot_epoch[0] = frames() - 1_000 * MS
    spin(bridge, 0.1)
    assert bridge.time_sync.resets == 1
    ok, samples = spin(bridge, 2.0, until=lambda: bridge.time_sync.synced)
    assert ok
    new_offset = OFFSET + boot_epoch[0]
    assert bridge.time_sync.offset_ns == new_offset
    _, samples = spin(bridge, 0.2)
    sent_ns = {ms * MS for ms in peer.attitude_ms}
    assert samples and all(s.stamp_ns - new_offset in sent_ns for s in samples)


def test_bridge_answers_the_autopilots_timesync_requests_with_its_ros_time(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'timesync_requests': True}, ros_offset_ns=OFFSET)
    ok, _ = spin(bridge, 3.0, until=lambda: len(peer.timesync_answers) >= 3)
    assert ok
    for boot_at_receipt, m in peer.timesync_answers:
        # ts1 echoed (the autopilot's boot time when it asked); tc1 = our ROS time when we
        # answered, i.e. between its request and its receipt on the autopilot's clock + offset
        assert m.ts1 <= boot_at_receipt
        assert m.ts1 + OFFSET <= m.tc1 <= boot_at_receipt + OFFSET
    assert bridge.status().counters['timesync_answered'] >= 3


def test_no_timesync_while_the_ros_time_is_zero(peer_bridge):
    # Under use_sim_time before the first /clock the node's ROS time is 0: ts1 = 0 or an
    # answer tc1 = 0 (a request!) would be meaningless.
    peer, bridge = peer_bridge(peer_kw={'timesync_requests': True}, ros_clock=lambda: 0)
    ok, samples = spin(bridge, 1.5, until=lambda: bridge.link.link_up
                       and bridge.imu_dropped_unsynced > 20)
    spin(bridge, 0.3)
    assert bridge.link.link_up
    assert peer.timesync_seen == [] and peer.timesync_answers == []
    assert samples == [] and bridge.imu_dropped_unsynced > 0
    assert bridge.status().counters['timesync_answered'] == 0


def test_setpoint_time_boot_ms_is_the_force_stamp_mapped_at_each_send(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'timesync_on': False}, ros_offset_ns=OFFSET)
    ok, _ = spin(bridge, 2.0, until=lambda: bridge.link.link_up and bridge.sequencer)
    assert ok
    bridge.on_heading(OFFSET + 1_234 * MS, heading_msg_quat(0.0))
    bridge.on_force(OFFSET + 1_234 * MS, HOVER_F)
    spin(bridge, 0.2)
    assert peer.setpoints and {m.time_boot_ms for _, m in peer.setpoints} == {0}   # unsynced
    peer.timesync_on = True
    ok, _ = spin(bridge, 2.0, until=lambda: sent_for(peer, 1234))
    assert ok, 'a repeat after the sync carries the mapped stamp'
    # The next frame's stamp 1254.5 ms after boot on the ROS clock: rounded to 1255 (halves up).
    bridge.on_heading(OFFSET + 1_254_500_000, heading_msg_quat(0.0))
    bridge.on_force(OFFSET + 1_254_500_000, HOVER_F)
    assert wait_peer(lambda: sent_for(peer, 1255))
    assert sent_for(peer, 1254) == []


def test_diagnostics_report_the_clock_sync(peer_bridge):
    peer, bridge = peer_bridge(ros_offset_ns=OFFSET)
    wait_link(bridge)
    ts = bridge.status().time_sync
    assert ts.synced and ts.offset_ns == OFFSET and ts.accepted >= 5
    assert ts.last_rtt_ns == 0                    # within one frame of the FrameClock


# --- heading / force pairing by stamp ---------------------------------------------------------

HOVER_F = np.array([0.0, 0.0, MASS * GRAVITY])     # level: the setpoint is a pure yaw
S0, S1, S2 = 1_000_000_000, 1_020_000_000, 1_040_000_000      # 20 ms frames: 1000, 1020, 1040


def level_q(yaw_ned):
    """SET_ATTITUDE_TARGET q of a level attitude with NED yaw (rotation about NED z)."""
    return [np.cos(yaw_ned / 2.0), 0.0, 0.0, np.sin(yaw_ned / 2.0)]


def sent_for(peer, ms):
    return [m for _, m in list(peer.setpoints) if m.time_boot_ms == ms]


def wait_peer(until, timeout_s=1.0):
    """Wait for the peer's receiving thread, without ticking the bridge."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not until():
        time.sleep(0.005)
    return until()


def test_force_before_its_heading_waits_for_the_heading_of_its_stamp(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'clock': FrozenClock()})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.1))
    bridge.on_force(S0, HOVER_F)                   # frame 0 paired: headings are expected
    assert wait_peer(lambda: sent_for(peer, 1000))
    assert bridge.on_force(S1, HOVER_F) == ''      # frame 1: the force overtook its heading
    bridge.stream()                                # (the clock stands: the wait runs on)
    time.sleep(0.1)
    assert sent_for(peer, 1020) == []              # not sent with the heading of frame 0
    assert bridge.on_heading(S1, heading_msg_quat(0.2)) == ''
    assert wait_peer(lambda: sent_for(peer, 1020))  # sent on the heading, no timer needed
    for _ in range(3):
        bridge.stream()
    assert wait_peer(lambda: len(sent_for(peer, 1020)) >= 4)
    assert all(same_rotation(m.q, level_q(0.2)) for m in sent_for(peer, 1020))
    assert all(same_rotation(m.q, level_q(0.1)) for m in sent_for(peer, 1000))
    c = bridge.status().counters
    assert c['heading_timeouts'] == 0 and c['late_headings'] == 0


def test_heading_before_force_sent_at_once_with_the_heading_of_the_same_stamp(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'clock': FrozenClock()})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.1))
    bridge.on_heading(S1, heading_msg_quat(0.2))   # a newer heading is already there ...
    bridge.on_force(S0, HOVER_F)
    assert wait_peer(lambda: sent_for(peer, 1000))  # ... at once, no timer ...
    assert same_rotation(sent_for(peer, 1000)[0].q, level_q(0.1))   # ... with its own stamp's
    bridge.on_force(S1, HOVER_F)
    assert wait_peer(lambda: sent_for(peer, 1020))
    assert same_rotation(sent_for(peer, 1020)[0].q, level_q(0.2))


def test_missing_heading_sent_after_heading_wait_with_the_latest_heading(peer_bridge):
    clock = FrozenClock()
    peer, bridge = peer_bridge(bridge_kw={'clock': clock, 'heading_wait_s': 0.02})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.3))
    bridge.on_force(S0, HOVER_F)
    bridge.on_force(S1, HOVER_F)                   # its heading never comes
    clock.t += 0.01
    bridge.poll()
    bridge.stream()
    time.sleep(0.1)
    assert sent_for(peer, 1020) == []              # 10 ms < heading_wait_s: still waiting
    clock.t += 0.015
    bridge.poll()                                  # the node's poll timer releases it
    assert wait_peer(lambda: sent_for(peer, 1020))
    assert same_rotation(sent_for(peer, 1020)[0].q, level_q(0.3))   # the latest heading
    assert bridge.status().counters['heading_timeouts'] == 1
    assert 'without the heading' in bridge.pop_heading_warning()
    assert bridge.pop_heading_warning() == ''      # reported once
    # The last force went without its heading: the next one is not held.
    bridge.on_force(S2, HOVER_F)
    assert wait_peer(lambda: sent_for(peer, 1040))
    assert same_rotation(sent_for(peer, 1040)[0].q, level_q(0.3))


def test_late_heading_never_changes_what_was_sent_for_its_stamp(peer_bridge):
    clock = FrozenClock()
    peer, bridge = peer_bridge(bridge_kw={'clock': clock})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.1))
    bridge.on_force(S0, HOVER_F)
    bridge.on_force(S1, HOVER_F)
    clock.t += 0.025
    bridge.stream()                                # wait over: sent with the heading of S0
    assert wait_peer(lambda: sent_for(peer, 1020))
    assert bridge.on_heading(S1, heading_msg_quat(0.5)) == ''   # too late for S1
    for _ in range(5):
        bridge.stream()
    assert wait_peer(lambda: len(sent_for(peer, 1020)) >= 6)
    first = sent_for(peer, 1020)[0]
    for m in sent_for(peer, 1020):                 # every repeat is what was sent
        assert np.allclose(m.q, first.q, atol=0.0) and m.thrust == first.thrust
    assert same_rotation(first.q, level_q(0.1))
    assert bridge.status().counters['late_headings'] == 1
    # The late heading is the latest for later forces; S1 had its heading after all, so the
    # next force waits for its own again (here in vain: then flown with the late one).
    bridge.on_force(S2, HOVER_F)
    time.sleep(0.1)
    assert sent_for(peer, 1040) == []
    clock.t += 0.025
    bridge.stream()
    assert wait_peer(lambda: sent_for(peer, 1040))
    assert same_rotation(sent_for(peer, 1040)[0].q, level_q(0.5))


def test_heading_pairing_exact_stamps_first_force_late_and_newer_inputs():
    F = np.array([0.0, 0.0, 10.0])
    p = HeadingPairing(wait_s=0.02)
    # no heading seen yet: at once, without a heading (the bridge flies the current yaw)
    [f] = p.on_force(10, F, t=0.0)
    assert (f.stamp_ns, f.yaw, f.paired) == (10, None, False)
    assert p.on_heading(10, 0.1) == [] and p.late == 1
    # 10 had its heading (late): 20 waits for its own; a newer force releases it first
    assert p.on_force(20, F, t=1.0) == [] and p.holding
    out = p.on_force(30, F, t=1.005)
    assert [(f.stamp_ns, f.yaw, f.paired) for f in out] == [(20, 0.1, False), (30, 0.1, False)]
    assert p.missing == 1 and not p.holding        # 20 went without: 30 was not held
    # exact stamps: a heading 1 ns away is another frame's
    assert p.on_heading(39, 0.39) == [] and p.on_heading(40, 0.4) == []
    [f] = p.on_force(40, F, t=2.0)
    assert (f.yaw, f.paired) == (0.4, True)
    # a heading newer than the held force's stamp: the held one's heading will not come
    assert p.on_force(50, F, t=3.0) == []
    [f] = p.on_heading(60, 0.6)
    assert (f.stamp_ns, f.yaw, f.paired) == (50, 0.4, False) and p.missing == 2
    [f] = p.on_force(60, F, t=4.0)
    assert (f.stamp_ns, f.yaw, f.paired) == (60, 0.6, True)
    # a refused force never waits
    [f] = p.on_force(70, F, t=5.0, may_wait=False)
    assert (f.stamp_ns, f.yaw) == (70, 0.6)
    # a refused heading (None) releases its force with the latest valid heading
    p.on_heading(70, 0.7)
    assert p.on_force(80, F, t=6.0) == []
    [f] = p.on_heading(80, None)
    assert (f.stamp_ns, f.yaw, f.paired) == (80, 0.7, False)
    # the wait
    assert p.on_force(90, F, t=7.0) == []
    assert p.expire(7.01) == []
    [f] = p.expire(7.03)
    assert (f.stamp_ns, f.yaw, f.paired) == (90, 0.7, False) and p.missing == 3


def test_heading_pairing_zero_wait_never_holds():
    p = HeadingPairing(wait_s=0.0)
    p.on_heading(10, 0.1)
    p.on_force(10, np.array([0.0, 0.0, 1.0]), t=0.0)
    [f] = p.on_force(20, np.array([0.0, 0.0, 1.0]), t=0.1)
    assert (f.stamp_ns, f.yaw, f.paired) == (20, 0.1, False)


def test_mode_change_to_window_sends_do_set_mode_at_once(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.on_heading(S0, heading_msg_quat(0.0))
    bridge.on_force(S0, HOVER_F)
    spin(bridge, 1.3)                              # > prestream_s (1.0 s) of stream
    assert bridge.sequencer.state == EngageState.STANDBY and peer.set_mode_commands() == []
    bridge.on_supervisor_mode(Mode.WINDOW)         # no poll between this and the next force
    assert bridge.sequencer.state == EngageState.SET_MODE
    bridge.on_heading(S1, heading_msg_quat(0.0))
    bridge.on_force(S1, HOVER_F)
    assert wait_peer(lambda: peer.set_mode_commands() and sent_for(peer, 1020))
    t_mode, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 6.0)
    t_sp = min(t for t, sp in list(peer.setpoints) if sp.time_boot_ms == 1020)
    assert t_mode <= t_sp                          # the command left before the setpoint


def test_stream_held_sends_nothing_then_fallback_carries_no_newer_time(peer_bridge):
    # The node holds the stream until imu/data has its readers; a fallback setpoint (level
    # hover before any force) carries time_boot_ms 0, never the autopilot's current time,
    # which a lockstep sim would take for the answer to its newest frame.
    peer, bridge = peer_bridge()
    bridge.stream_enabled = False
    wait_link(bridge)
    spin(bridge, 0.3)
    assert peer.setpoints == []
    bridge.stream_enabled = True
    ok, _ = spin(bridge, 1.0, until=lambda: len(peer.setpoints) >= 3)
    assert ok
    assert {m.time_boot_ms for _, m in peer.setpoints} == {0}


def test_content_follows_the_status_of_the_force_stamp_not_the_latest_mode(peer_bridge):
    # ibvs/mode SHUTDOWN may land before the force of the last LANDING frame: that force is
    # still flown as LANDING (its own status); the SHUTDOWN frame's force starts the ramp.
    peer, bridge = peer_bridge(bridge_kw={'heading_wait_s': 0.0})
    wait_link(bridge)
    hover_F = np.array([0.0, 0.0, MASS * GRAVITY])
    assert bridge.on_supervisor_status(1_000_000_000, int(Mode.LANDING)) == ''
    assert bridge.on_supervisor_status(1_020_000_000, int(Mode.SHUTDOWN)) == ''
    assert bridge.on_supervisor_status(1_040_000_000, 99) != ''      # refused
    bridge.on_supervisor_mode(int(Mode.SHUTDOWN))
    bridge.on_force(1_000_000_000, 1.2 * hover_F)
    assert bridge.content_mode(time.monotonic()) == Mode.LANDING
    assert bridge.setpoint_source == SetpointSource.IBVS
    bridge.on_force(1_020_000_000, 1.2 * hover_F)
    assert bridge.content_mode(time.monotonic()) == Mode.SHUTDOWN
    assert bridge.setpoint_source == SetpointSource.SHUTDOWN_RAMP
    # a force without a status of its own: the latest ibvs/mode
    bridge.on_force(1_060_000_000, hover_F)
    assert bridge.content_mode(time.monotonic()) == Mode.SHUTDOWN
