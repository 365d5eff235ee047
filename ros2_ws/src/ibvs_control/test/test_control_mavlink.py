"""The MAVLink bridge core against a pymavlink peer autopilot on 127.0.0.1.

The peer (FakeAutopilot) is written here from the MAVLink message definitions and the measured
PX4 / ArduPilot behaviour (docs/mavlink.md), not from the bridge: it runs in a thread, sends
HEARTBEAT, ATTITUDE_QUATERNION, the IMU's specific force (HIGHRES_IMU as PX4, SCALED_IMU in
milli-g as ArduPilot), ATTITUDE_TARGET (the thrust it applies), EXTENDED_SYS_STATE and
SYS_STATUS, answers parameter reads, commands (plain disarm refused unless landed; arming
refused unless armable; ArduPilot refuses HIGHRES_IMU) and TIMESYNC as PX4 does, and records
every SET_ATTITUDE_TARGET and COMMAND_LONG with its arrival time. Nothing waits in real time:
the bridge and the peer share one test clock (:class:`FrozenClock`) that :func:`spin` moves on
by 2 ms per step, stepping the peer, then the bridge (loopback datagrams are queued by the time
sendto returns). The peer's boot clock is a :class:`FrameClock` of it (whole 20 ms frames, as
the lockstep sim's), and the bridge's ROS clock is that clock plus a chosen offset: a TIMESYNC
round trip inside one frame measures the offset exactly, so mapped times are exact.
Expected values come from geometry (a pure yaw rotation, the nose-down pitch needed to
accelerate forward), from the clocks' offset, and from the
MAVLink/PX4/ArduPilot documentation (param2 = 6, custom_mode 20, GUID_OPTIONS bit 3, 21196,
AUTO.LAND = main 4 / sub 6, ArduCopter LAND = 9).
"""
import dataclasses
import os
import select
import struct
import threading
import time

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

from ibvs_common.core.frames import GRAVITY, quat_multiply  # noqa: E402
from ibvs_control.mavlink.bridge import (  # noqa: E402
    BridgeConfig, MavlinkBridge, SetpointSource)
from ibvs_control.mavlink.hover import EstimatorConfig  # noqa: E402
from ibvs_control.mavlink.link import LinkConfig  # noqa: E402
from ibvs_control.mavlink.sequencer import EngageState, SequencerConfig  # noqa: E402
from ibvs_common.core.modes import Mode  # noqa: E402
from ibvs_common.core.mavlink_connection import free_udp_port  # noqa: E402

MASS = 1.676
PX4_OFFBOARD = 6 << 16
PX4_POSCTL = 3 << 16
PX4_AUTO_LAND = (4 << 16) | (6 << 24)
AP_GUIDED_NOGPS, AP_GUIDED, AP_LAND = 20, 4, 9
KEY = bytes(range(32))
MS = 1_000_000                                  # ns
OFFSET = 1_700_000_000_123_456_789              # ns, ROS (system time) - autopilot boot time
FRAME_NS = 20 * MS
TICK_S = 0.002                                  # s of the test clock per spin() step
FORCE_MAGIC = 21196
HOVER_F = np.array([0.0, 0.0, MASS * GRAVITY])     # level: the setpoint is a pure yaw


class FrozenClock:
    """The test's steady clock (s): it moves only when the test advances it."""

    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t

    def advance(self, dt):
        self.t += dt


class FrameClock:
    """An autopilot boot clock in whole 20 ms frames (ns) of ``clock``, 1 s at creation."""

    def __init__(self, clock, start_ns=1_000 * MS):
        self.clock = clock
        self.start_ns = start_ns
        self.t0 = clock()

    def __call__(self):
        elapsed_ns = round((self.clock() - self.t0) * 1e9)
        return self.start_ns + elapsed_ns // FRAME_NS * FRAME_NS


def rotmat(q):
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class FakeAutopilot:
    """A minimal PX4- or ArduPilot-like autopilot speaking MAVLink 2 on udpin.

    It listens on a port the kernel picks (``udpin:127.0.0.1:0``): ``udp_port``. No other
    process can take that port between a check and the bind, as with a port chosen first.
    No thread: :meth:`step` runs one pass of its loop at the time of ``clock``.
    """

    def __init__(self, clock, kind='px4', armed=True, params=None, key=None, yaw_ned=0.0,
                 boot_clock=None, timesync_on=True, timesync_requests=False, landed=False,
                 armable=True, specific_force=(0.0, 0.0, -GRAVITY), thrust=0.5):
        self.kind = kind
        self.clock = clock
        self.boot_clock = boot_clock if boot_clock is not None else FrameClock(clock)
        self.timesync_on = timesync_on              # answer TIMESYNC requests
        self.timesync_requests = timesync_requests  # send our own, as PX4 does
        self.timesync_seen = []    # requests (tc1 == 0) received: msg
        self.timesync_answers = []  # (boot ns at receipt, msg) answers to our requests
        self.attitude_ms = []      # time_boot_ms of every ATTITUDE_QUATERNION sent
        self.conn = mavutil.mavlink_connection('udpin:127.0.0.1:0', source_system=1,
                                               source_component=1)
        self.udp_port = self.conn.port.getsockname()[1]
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.armed = armed
        self.landed = landed                # EXTENDED_SYS_STATE; plain disarm accepted then
        self.armable = armable              # SYS_STATUS pre-arm bit; arming refused otherwise
        self.specific_force = np.array(specific_force, dtype=float)  # IMU, FRD, m/s^2
        self.thrust = thrust                # ATTITUDE_TARGET (the thrust applied)
        self.refuse_arm = 0                 # refuse this many arm commands even if armable
        self.custom_mode = PX4_POSCTL if kind == 'px4' else 0
        self.params = params or {}
        self.yaw_ned = yaw_ned
        self.heartbeats_on = True
        self.setpoints = []        # (t_rx, msg)
        self.commands = []         # (t_rx, msg)
        self.intervals = []        # (t_rx, msg id, interval us) of SET_MESSAGE_INTERVAL
        self.sources = set()       # (host, port) the bridge sent from
        self.rc = None             # RC_CHANNELS at 10 Hz: list of 18 channels (us), or None
        self.signed = []           # _signed flag of every message received
        self._next = {'hb': 0.0, 'att': 0.0, 'ts': 0.0, 'status': 0.0, 'rc': 0.0}

    def close(self):
        self.conn.close()

    def boot_ms(self):
        return self.boot_clock() // MS

    def statustext(self, text, severity=2):
        self.conn.mav.statustext_send(severity, text.encode())

    def step(self):
        """One pass at the clock's time: what is due is sent, what came in is handled."""
        now = self.clock()
        nxt = self._next
        kind = {'px4': mavutil.mavlink.MAV_AUTOPILOT_PX4,
                'ardupilot': mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA}[self.kind]
        alive = self.heartbeats_on and self.conn.clients
        if now >= nxt['hb']:
            nxt['hb'] = now + 0.1
            if alive:
                base = 1 | (128 if self.armed else 0)
                self.conn.mav.heartbeat_send(2, kind, base, self.custom_mode, 4)
        if now >= nxt['att'] and alive:
            nxt['att'] = now + 0.02
            h = self.yaw_ned / 2.0
            ms = self.boot_ms()
            self.attitude_ms.append(ms)
            self.conn.mav.attitude_quaternion_send(ms, np.cos(h), 0.0, 0.0, np.sin(h),
                                                   0.1, 0.2, 0.3)
            self.conn.mav.attitude_target_send(ms, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                               float(self.thrust))
            f = self.specific_force
            if self.kind == 'px4':
                self.conn.mav.highres_imu_send(ms * 1000, *map(float, f), 0.0, 0.0, 0.0, 0.0,
                                               0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0x3F)
            else:
                mg = np.round(f / GRAVITY * 1000.0).astype(int)
                self.conn.mav.scaled_imu_send(ms, *map(int, mg), 0, 0, 0, 0, 0, 0)
        if now >= nxt['status'] and alive:
            nxt['status'] = now + 0.1
            self.conn.mav.extended_sys_state_send(0, 1 if self.landed else 2)
            self.conn.mav.sys_status_send(0, 0, (1 << 28) if self.armable else 0, 0, 0,
                                          -1, -1, 0, 0, 0, 0, 0, 0)
        if self.rc is not None and now >= nxt['rc'] and alive:
            nxt['rc'] = now + 0.1
            used = [us for us in self.rc if us not in (0, 0xFFFF)]
            self.conn.mav.rc_channels_send(self.boot_ms(), len(used), *self.rc, 255)
        if self.timesync_requests and now >= nxt['ts'] and self.conn.clients:
            nxt['ts'] = now + 0.2
            self.conn.mav.timesync_send(0, self.boot_clock())
        self.receive()

    def receive(self):
        """Handle every datagram that came in (stamped with the clock's time)."""
        now = self.clock()
        while True:
            msg = self.conn.recv_msg()
            if msg is None:
                return
            self._handle(msg, now)

    def _handle(self, msg, now):
        kind = msg.get_type()
        if kind == 'BAD_DATA':
            return
        self.sources |= set(self.conn.clients)
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
                value, kind = float(self.params[name]), 9                  # REAL32
                if isinstance(self.params[name], int) and self.kind == 'px4':
                    # PX4: an INT32 parameter's bytes in the float field (bytewise encoding)
                    value = struct.unpack('<f', struct.pack('<i', self.params[name]))[0]
                    kind = 6
                self.conn.mav.param_value_send(name.encode(), value, kind, len(self.params), 0)
        elif kind == 'COMMAND_LONG':
            self.commands.append((now, msg))
            self.conn.mav.command_ack_send(msg.command, self._command(msg, now))

    def _command(self, msg, now):
        m = mavutil.mavlink
        if msg.command == m.MAV_CMD_DO_SET_MODE:
            if self.kind == 'px4':
                main, sub = int(msg.param2), int(msg.param3)
                if main == 6:
                    self.custom_mode = PX4_OFFBOARD
                elif (main, sub) == (4, 6):
                    self.custom_mode = PX4_AUTO_LAND
                elif main == 3:
                    self.custom_mode = PX4_POSCTL
            else:
                self.custom_mode = int(msg.param2)
            return 0  # PX4 also ACKs the packed 6 << 16 and ignores it
        if msg.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 == 1.0:
                if not self.armable or self.refuse_arm > 0:
                    self.refuse_arm -= 1
                    self.statustext('Arming denied: not ready')
                    return 1                # TEMPORARILY_REJECTED, as PX4's commander
                self.armed = True
                return 0
            if not self.landed and int(msg.param2) != FORCE_MAGIC:
                self.statustext('Disarming denied: not landed')
                return 1
            self.armed = False
            return 0
        if msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            self.intervals.append((now, int(msg.param1), msg.param2))
            if self.kind == 'ardupilot' and int(msg.param1) == 105:
                self.statustext('No ap_message for mavlink id (105)', 6)
                return 2                    # DENIED, as ArduPilot for HIGHRES_IMU
            return 0
        return 0

    def set_mode_commands(self):
        return [(t, m) for t, m in self.commands
                if m.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE]

    def arm_commands(self):
        return [(t, m) for t, m in self.commands
                if m.command == mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
                and m.param1 == 1.0]

    def disarm_commands(self):
        return [(t, m) for t, m in self.commands
                if m.command == mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
                and m.param1 == 0.0]


class PeerThread:
    """Runs a FakeAutopilot on the real clock in a thread, for a ROS node's real timers."""

    def __init__(self, peer):
        self.peer = peer
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            self.peer.step()
            select.select([self.peer.conn.port], [], [], 0.001)   # wake on a datagram

    def close(self):
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.peer.close()


def make_bridge(port, autopilot='auto', source='config', hover=0.5, key=None,
                hold_last_s=5.0, clock=None, ros_clock=None, estimator=False, arm=False,
                heartbeat_clock=None, **kw):
    """A bridge on udpout to ``port``; ``ros_clock()`` (ns) is what spin() passes to poll()."""
    link = LinkConfig(url=f'udpout:127.0.0.1:{port}', heartbeat_timeout_s=0.5,
                      reconnect_period_s=0.3, signing_key=key)
    seq_kw = {k: kw.pop(k) for k in list(kw) if k in SequencerConfig.__dataclass_fields__}
    seq = SequencerConfig(**{'prestream_s': 1.0, 'command_retry_s': 0.3, 'max_attempts': 5,
                             'disarm_force_after_s': 0.3, 'arm_backoff_max_s': 1.2, **seq_kw})
    cfg = BridgeConfig(link=link, mass=MASS, max_thrust_factor=2.0,
                       configured_hover_thrust=hover, autopilot=autopilot,
                       hover_thrust_source=source, param_timeout_s=1.0, param_retry_s=0.2,
                       hold_last_s=hold_last_s, sequencer=seq, arm_on_start=arm,
                       estimator=EstimatorConfig(enabled=estimator), **kw)
    bridge = MavlinkBridge(cfg, heartbeat_clock=heartbeat_clock) if clock is None \
        else MavlinkBridge(cfg, clock, heartbeat_clock)
    bridge.test_ros_clock = ros_clock
    return bridge


def seq(bridge):
    """The bridge's engage sequencer (None before the autopilot is known)."""
    return bridge.engagement.sequencer


def ros_now(bridge):
    """The bridge's ROS time for poll() (None: the bridge was made without a ROS clock)."""
    clock = getattr(bridge, 'test_ros_clock', None)
    return None if clock is None else clock()


def spin(bridge, seconds, until=None, force_hz=50.0, force_fn=None):
    """Step the peer, then tick the bridge like the node's timers, every 2 ms of the clock.

    Stops early when until() is true. ``force_fn(now)``: called at ``force_hz``, e.g. to feed
    forces like the controller.
    """
    clock = bridge.clock
    t_end = clock() + seconds
    next_force = next_hb = 0.0
    samples = []
    while clock() < t_end:
        now = clock()
        bridge.test_peer.step()
        if force_fn is not None and now >= next_force:
            next_force = now + 1.0 / force_hz
            force_fn(now)
        if now >= next_hb:
            next_hb = now + 0.2
            bridge.heartbeat()
        ros = ros_now(bridge)
        samples += bridge.poll(ros)
        bridge.stream(ros)
        if until is not None and until():
            return True, samples
        clock.advance(TICK_S)
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
        """Peer + bridge on one test clock (``bridge_kw['clock']`` or a new one).

        The bridge's ROS clock = the peer's boot clock + ros_offset_ns.
        """
        bridge_kw = dict(bridge_kw or {})
        clock = bridge_kw.setdefault('clock', FrozenClock())
        peer_kw = dict(peer_kw or {})
        boot = peer_kw.setdefault('boot_clock', FrameClock(clock))
        peer = FakeAutopilot(clock, **peer_kw)
        if ros_clock is None:
            def ros_clock():
                return boot() + ros_offset_ns
        bridge = make_bridge(peer.udp_port, ros_clock=ros_clock, **bridge_kw)
        bridge.test_peer = peer
        made.append((peer, bridge))
        return peer, bridge
    yield factory
    for peer, bridge in made:
        bridge.close()
        peer.close()


def wait_link(bridge):
    """Spin until the link is up and the clocks are synced."""
    ok, _ = spin(bridge, 3.0, until=lambda: bridge.link.link_up
                 and seq(bridge) is not None and bridge.time_sync.synced)
    assert ok, f'link never came up or never synced: {bridge.time_sync.status()}'


def last_setpoint(peer):
    assert peer.setpoints, 'no SET_ATTITUDE_TARGET received'
    return peer.setpoints[-1][1]


def same_rotation(q_a, q_b, atol=1e-6):
    return np.allclose(rotmat(q_a), rotmat(q_b), atol=atol)


def level_q(yaw_ned):
    """SET_ATTITUDE_TARGET q of a level attitude with NED yaw (rotation about NED z)."""
    return [np.cos(yaw_ned / 2.0), 0.0, 0.0, np.sin(yaw_ned / 2.0)]


def sent_for(peer, ms):
    return [m for _, m in list(peer.setpoints) if m.time_boot_ms == ms]


def wait_peer(peer, until, timeout_s=1.0):
    """Let the peer take what the bridge sent, without ticking the bridge or the test clock.

    Loopback datagrams are queued when sendto returns; one still on its way is waited for on
    the socket, at most ``timeout_s`` (real time) in all.
    """
    deadline = time.monotonic() + timeout_s
    peer.receive()
    while not until() and time.monotonic() < deadline:
        select.select([peer.conn.port], [], [], max(0.0, deadline - time.monotonic()))
        peer.receive()
    return until()


def feeder(bridge, force=HOVER_F, yaw=0.0):
    """force_fn for spin(): heading then force with the ROS time as the stamp (a controller)."""
    def feed(_now):
        stamp = ros_now(bridge)
        bridge.on_heading(stamp, heading_msg_quat(yaw))
        bridge.on_force(stamp, force)
    return feed


def engage(bridge, peer, mode=Mode.WINDOW, arm=False):
    """IDLE, then ``mode`` with forces flowing, until ENGAGED (arming on request if ``arm``)."""
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    if arm:
        bridge.request_arm()
    bridge.on_supervisor_mode(mode)
    ok, _ = spin(bridge, 5.0, until=lambda: seq(bridge).state == EngageState.ENGAGED,
                 force_fn=feeder(bridge))
    assert ok, f'{seq(bridge).state}: {seq(bridge).last_reason}'


# --- setpoint content ----------------------------------------------------------------------------

def test_setpoint_up_with_yaw_90_is_a_pure_yaw_rotation(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    assert bridge.on_heading(1_234_000_000, heading_msg_quat(np.pi / 2)) == ''
    # Heading of NED yaw 90 deg (east) is the ENU identity: checked independently.
    assert np.allclose(heading_msg_quat(np.pi / 2), [1, 0, 0, 0])
    assert bridge.on_force(1_234_000_000, HOVER_F) == ''
    ok, _ = spin(bridge, 1.0, until=lambda: sent_for(peer, 1234))
    assert ok
    m = sent_for(peer, 1234)[0]
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
    bridge.on_force(3_000_000_000, 1.5 * HOVER_F)
    spin(bridge, 0.2)
    assert last_setpoint(peer).thrust == pytest.approx(0.6, abs=1e-6)

    peer2, bridge2 = peer_bridge(peer_kw={'params': {'MPC_THR_HOVER': 0.35}},
                                 bridge_kw={'source': 'autopilot'})
    ok, _ = spin(bridge2, 3.0, until=lambda: bridge2.hover.seed.value is not None)
    assert ok and bridge2.hover.seed.value == pytest.approx(0.35, abs=1e-6)
    assert 'MPC_THR_HOVER' in bridge2.status().hover_thrust_source
    bridge2.on_heading(3_000_000_000, heading_msg_quat(0.0))
    bridge2.on_force(3_000_000_000, HOVER_F)
    spin(bridge2, 0.2)
    assert last_setpoint(peer2).thrust == pytest.approx(0.35, abs=1e-6)


@pytest.mark.parametrize('boost', [1, 0])
def test_ardupilot_angle_boost_means_the_vertical_component_is_sent(peer_bridge, boost):
    # ATC_ANGLE_BOOST = 1: ArduPilot multiplies the thrust by 1/cos(tilt) itself; the bridge
    # then sends F_z / (m g) * hover, so that the vehicle gets |F| once, not |F| / cos(tilt).
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.4, 'ATC_ANGLE_BOOST': boost}},
        bridge_kw={'source': 'autopilot'})
    ok, _ = spin(bridge, 3.0, until=lambda: bridge.params.angle_boost is not None
                 and seq(bridge).state == EngageState.STANDBY)
    assert ok
    tilt = np.radians(20.0)
    F = MASS * GRAVITY * np.array([np.tan(tilt), 0.0, 1.0])    # F_z = m g: level flight
    thrust, _ = None, None
    bridge.on_heading(3_000_000_000, heading_msg_quat(0.0))
    bridge.on_force(3_000_000_000, F)
    thrust = bridge.setpoints.current.thrust
    expected = 0.4 if boost else 0.4 / np.cos(tilt)
    assert thrust == pytest.approx(expected, rel=1e-6)
    assert bridge.setpoints.shaper.tilt_boost_by_autopilot == bool(boost)


def test_setpoints_leave_at_the_force_rate_and_repeats_only_fill_gaps(peer_bridge):
    # Each force at once (50 Hz here, one per camera frame); a repeat only when nothing left
    # for 1 / stream_rate_hz (30 Hz): the force rate with the controller, 30 Hz without.
    peer, bridge = peer_bridge()
    wait_link(bridge)
    spin(bridge, 0.3, force_fn=feeder(bridge))
    forces = []
    feed = feeder(bridge)

    def counted(now):
        forces.append(now)
        feed(now)
    n0, t0 = len(peer.setpoints), bridge.clock()
    spin(bridge, 2.0, force_fn=counted, force_hz=50.0)
    peer.receive()
    dt = bridge.clock() - t0
    with_forces, force_rate = (len(peer.setpoints) - n0) / dt, len(forces) / dt
    n0, t0 = len(peer.setpoints), bridge.clock()
    spin(bridge, 2.0)
    peer.receive()
    repeats = (len(peer.setpoints) - n0) / (bridge.clock() - t0)
    print(f'\nsetpoint rate: {with_forces:.1f} Hz with forces at {force_rate:.1f} Hz, '
          f'{repeats:.1f} Hz without')
    assert force_rate * 0.97 <= with_forces <= force_rate * 1.1
    assert 26.0 <= repeats <= 31.5


def test_the_step_slows_to_the_idle_rate_only_while_quiet(peer_bridge):
    # The node's step (poll, supervision, repeat) runs on a 30 Hz timer; while nothing is to
    # be engaged (standby, supervisor IDLE, clocks synced) it acts at idle_tick_rate_hz (10),
    # which is then the keepalive stream's rate (PX4 wants > 2 Hz before OFFBOARD).
    peer, bridge = peer_bridge()
    wait_link(bridge)
    spin(bridge, 0.3)
    assert seq(bridge).state == EngageState.STANDBY and bridge.quiet
    clock = bridge.clock
    n0, due, t0 = len(peer.setpoints), 0, clock()
    while clock() - t0 < 1.0:                      # the node's 30 Hz timer
        peer.step()
        if bridge.tick_due():
            due += 1
            bridge.poll(ros_now(bridge))
            bridge.stream(ros_now(bridge))
        clock.advance(1.0 / 30.0)
    peer.receive()
    assert 8 <= due <= 11
    assert 8 <= len(peer.setpoints) - n0 <= 11
    bridge.on_supervisor_mode(Mode.WINDOW)          # engaging: every step again
    assert not bridge.quiet and all(bridge.tick_due() for _ in range(5))


def test_an_idle_step_rate_of_2_hz_or_less_is_refused():
    link = LinkConfig(url='udpin:127.0.0.1:9')
    with pytest.raises(ValueError, match='idle_tick_rate_hz'):
        BridgeConfig(link=link, mass=MASS, max_thrust_factor=2.0,
                     configured_hover_thrust=0.5, idle_tick_rate_hz=2.0)


@pytest.mark.parametrize('field,value', [('quiet_telemetry_rate_hz', -1.0),
                                         ('quiet_telemetry_rate_hz', float('nan')),
                                         ('quiet_telemetry_delay_s', float('inf'))])
def test_a_bad_telemetry_rate_at_rest_is_refused(field, value):
    link = LinkConfig(url='udpin:127.0.0.1:9')
    with pytest.raises(ValueError, match=field):
        BridgeConfig(link=link, mass=MASS, max_thrust_factor=2.0,
                     configured_hover_thrust=0.5, **{field: value})


# --- engage and arm -----------------------------------------------------------------------------

def test_px4_offboard_after_streaming_and_arms_only_when_asked(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'armed': False, 'landed': True})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    spin(bridge, 1.3, force_fn=feeder(bridge))
    assert peer.set_mode_commands() == []          # IDLE: stream, do not switch
    assert seq(bridge).state == EngageState.STANDBY
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.WAIT_ARM,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    t_mode, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 6.0)      # custom mode enabled, OFFBOARD main mode
    assert t_mode - peer.setpoints[0][0] > 0.98    # > 1 s of stream first
    spin(bridge, 1.5, force_fn=feeder(bridge))
    assert peer.arm_commands() == [] and not peer.armed        # never arms by itself
    assert seq(bridge).state == EngageState.WAIT_ARM
    ok, text = bridge.request_arm()
    assert ok and 'arm' in text
    t_req = bridge.clock()
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.ENGAGED,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    [(t_arm, arm)] = peer.arm_commands()           # exactly one ARM
    assert arm.param1 == 1.0 and t_arm >= t_req and peer.armed
    assert not seq(bridge).arm_requested      # used up


def test_arming_waits_until_armable_retries_with_backoff_and_logs_the_reasons(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'armed': False, 'landed': True, 'armable': False})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.request_arm()
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.ARMING,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason        # PX4: OFFBOARD though not armable yet
    spin(bridge, 1.0, force_fn=feeder(bridge))
    assert peer.arm_commands() == []               # not armable: nothing sent
    assert bridge.status().armable is False
    peer.refuse_arm = 3                            # armable, but refused three times
    peer.armable = True
    ok, _ = spin(bridge, 8.0, until=lambda: seq(bridge).state == EngageState.ENGAGED,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    times = [t for t, _ in peer.arm_commands()]
    assert len(times) == 4
    gaps = np.diff(times)                          # 0.3, 0.6, 1.2 s (retry 0.3 s, doubling)
    assert gaps[0] == pytest.approx(0.3, abs=0.1) and gaps[1] == pytest.approx(0.6, abs=0.1)
    assert gaps[2] == pytest.approx(1.2, abs=0.1)
    reasons = [t for level, t in bridge.pop_events() if level.startswith('reason')]
    assert any('Arming denied: not ready' in r for r in reasons)


def test_px4_switch_requested_immediately_still_waits_for_stream(peer_bridge):
    peer, bridge = peer_bridge()
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 4.0, until=lambda: seq(bridge) is not None
                 and seq(bridge).state == EngageState.ENGAGED, force_fn=feeder(bridge))
    assert ok
    t_mode, _ = peer.set_mode_commands()[0]
    assert t_mode - peer.setpoints[0][0] > 0.98
    assert peer.arm_commands() == []               # already armed: no arm command


def test_no_engagement_without_an_idle_report_first(peer_bridge):
    # A bridge (re)started while the supervisor is already flying never takes the vehicle.
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.WINDOW)
    spin(bridge, 1.5, force_fn=feeder(bridge))
    assert peer.set_mode_commands() == []
    assert seq(bridge).state == EngageState.STANDBY


def test_ardupilot_guided_nogps_with_guid_options_bit3(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.3, 'ATC_ANGLE_BOOST': 1}, 'armed': False,
        'landed': True}, bridge_kw={'source': 'autopilot', 'arm': True})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    spin(bridge, 1.5, force_fn=feeder(bridge))
    assert peer.setpoints == []                    # ArduPilot: nothing before the switch
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 4.0, until=lambda: seq(bridge).state == EngageState.ENGAGED,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    t_mode, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 20.0)
    assert peer.setpoints[0][0] >= t_mode - 0.01
    assert peer.custom_mode == 20 and peer.armed
    assert bridge.hover.seed.value == pytest.approx(0.3)


@pytest.mark.parametrize('guid_options', [0, 7, None])
def test_ardupilot_refuses_without_guid_options_bit3(peer_bridge, guid_options):
    params = {'MOT_THST_HOVER': 0.3, 'ATC_ANGLE_BOOST': 1}
    if guid_options is not None:
        params['GUID_OPTIONS'] = guid_options
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': params, 'armed': False})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 2.5, until=lambda: seq(bridge).state == EngageState.REFUSED)
    assert ok
    assert 'GUID_OPTIONS' in seq(bridge).last_reason
    spin(bridge, 0.3)
    assert peer.set_mode_commands() == [] and peer.arm_commands() == []
    assert peer.setpoints == []
    assert bridge.request_arm()[0] is False


def test_mode_change_to_window_sends_do_set_mode_at_once(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    spin(bridge, 1.3, force_fn=feeder(bridge))     # > prestream_s (1.0 s) of stream
    assert seq(bridge).state == EngageState.STANDBY and peer.set_mode_commands() == []
    bridge.on_supervisor_mode(Mode.WINDOW)         # no poll between this and the next force
    assert seq(bridge).state == EngageState.SET_MODE
    stamp = ros_now(bridge) + 7 * MS
    bridge.on_heading(stamp, heading_msg_quat(0.0))
    bridge.on_force(stamp, HOVER_F)
    ms = bridge.setpoints.stamp_to_boot_ms(stamp)
    assert wait_peer(peer, lambda: peer.set_mode_commands() and sent_for(peer, ms))
    t_mode, m = peer.set_mode_commands()[0]
    assert (m.param1, m.param2) == (1.0, 6.0)
    t_sp = min(t for t, sp in list(peer.setpoints) if sp.time_boot_ms == ms)
    assert t_mode <= t_sp                          # the command left before the setpoint


# --- hand back ----------------------------------------------------------------------------------

def test_silent_controller_px4_stops_streaming_after_hold_last(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'hold_last_s': 0.25})
    engage(bridge, peer)
    t_last = bridge.clock()
    ok, _ = spin(bridge, 2.0, until=lambda: seq(bridge).state == EngageState.HELD)
    t_held = bridge.clock()
    assert ok, seq(bridge).last_reason
    assert 'offboard-loss failsafe' in seq(bridge).last_reason
    assert 0.2 <= t_held - t_last <= 0.45          # hold_last_s of vehicle (ROS) time
    n = len(peer.setpoints)
    spin(bridge, 1.0)
    assert len(peer.setpoints) <= n + 1            # nothing more (one may be on its way)
    assert max(t for t, _ in peer.setpoints) <= t_held + 0.05
    assert [m for _, m in peer.setpoints if m.thrust != pytest.approx(0.5)] == []  # no hover
    #                                                of our own: the last force held, then none
    assert len(peer.set_mode_commands()) == 1      # nothing commanded: PX4's failsafe acts


def test_forces_of_old_images_are_not_flown_and_hand_the_vehicle_back(peer_bridge):
    """A graph 0.3 s behind (older than max_force_age_s): refused, then handed back.

    The forces keep coming, so the controller is not silent; they answer images older than
    max_force_age_s (0.25 s), so none is flown, none counts as valid, and after hold_last_s
    the bridge hands PX4 its offboard-loss failsafe. One 0.1 s behind is flown.
    """
    peer, bridge = peer_bridge(bridge_kw={'hold_last_s': 0.25})
    engage(bridge, peer)
    tilted = MASS * np.array([-2.0, 0.0, GRAVITY])

    def behind(lag_s):
        def feed(_now):
            stamp = ros_now(bridge) - int(lag_s * 1e9)
            bridge.on_heading(stamp, heading_msg_quat(0.0))
            bridge.on_force(stamp, tilted)
        return feed
    spin(bridge, 0.1, force_fn=behind(0.1))
    assert bridge.status().stale_setpoints == 0
    flown = last_setpoint(peer)
    assert flown.thrust > 0.5                      # the tilted force, 0.1 s old: flown
    ok, _ = spin(bridge, 2.0, until=lambda: seq(bridge).state == EngageState.HELD,
                 force_fn=behind(0.3))
    assert ok, seq(bridge).last_reason
    assert 'offboard-loss failsafe' in seq(bridge).last_reason
    st = bridge.status()
    assert st.stale_setpoints > 5 and st.rejected_setpoints == st.stale_setpoints
    assert 'ms old' in bridge.setpoints.shaper.last_error


def test_silent_controller_ardupilot_commands_land(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.3, 'ATC_ANGLE_BOOST': 1}},
        bridge_kw={'source': 'autopilot', 'hold_last_s': 0.25})
    engage(bridge, peer)
    ok, _ = spin(bridge, 2.0, until=lambda: peer.custom_mode == AP_LAND)
    assert ok, seq(bridge).last_reason
    _, m = peer.set_mode_commands()[-1]
    assert (m.param1, m.param2) == (1.0, 9.0)      # ArduCopter LAND
    ok, _ = spin(bridge, 1.0, until=lambda: not bridge.status().streaming)
    assert ok and seq(bridge).state == EngageState.LANDING
    n = len(peer.setpoints)
    spin(bridge, 0.5)
    assert len(peer.setpoints) <= n + 1
    peer.landed = True                             # it lands: disarm (ArduPilot would itself)
    ok, _ = spin(bridge, 2.0, until=lambda: seq(bridge).state == EngageState.DONE)
    assert ok and not peer.armed
    assert all(int(m.param2) != FORCE_MAGIC for _, m in peer.disarm_commands())


@pytest.mark.parametrize('kind', ['px4', 'ardupilot'])
def test_failsafe_is_the_autopilots_land_mode(peer_bridge, kind):
    params = {'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0} \
        if kind == 'ardupilot' else {}
    peer, bridge = peer_bridge(peer_kw={'kind': kind, 'params': params, 'yaw_ned': -1.0},
                               bridge_kw={'source': 'autopilot' if params else 'config'})
    engage(bridge, peer)
    n = len(peer.setpoints)
    bridge.on_supervisor_mode(Mode.FAILSAFE)
    land = PX4_AUTO_LAND if kind == 'px4' else AP_LAND
    ok, _ = spin(bridge, 2.0, until=lambda: peer.custom_mode == land)
    assert ok
    _, m = peer.set_mode_commands()[-1]
    expected = (1.0, 4.0, 6.0) if kind == 'px4' else (1.0, 9.0, 0.0)
    assert (m.param1, m.param2, m.param3) == expected
    ok, _ = spin(bridge, 1.0, until=lambda: not bridge.status().streaming)
    assert ok
    # until the land mode showed: level at the current yaw, hover thrust (no descent of ours)
    for _, sp in peer.setpoints[n + 1:]:
        assert same_rotation(sp.q, level_q(-1.0)) and sp.thrust == pytest.approx(0.5)
    n = len(peer.setpoints)
    spin(bridge, 0.5)
    assert len(peer.setpoints) <= n + 1


@pytest.mark.parametrize('kind', ['px4', 'ardupilot'])
def test_a_mode_taken_by_the_pilot_stops_the_stream_at_once_for_good(peer_bridge, kind):
    params = {'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0} \
        if kind == 'ardupilot' else {}
    peer, bridge = peer_bridge(peer_kw={'kind': kind, 'params': params},
                               bridge_kw={'source': 'autopilot' if params else 'config'})
    engage(bridge, peer)
    taken = PX4_POSCTL if kind == 'px4' else AP_GUIDED    # GUIDED obeys attitude targets too
    peer.custom_mode = taken
    ok, _ = spin(bridge, 1.0, until=lambda: seq(bridge).state == EngageState.HELD,
                 force_fn=feeder(bridge))
    assert ok
    t_held = bridge.clock()
    n_modes = len(peer.set_mode_commands())
    spin(bridge, 1.5, force_fn=feeder(bridge))      # the controller goes on: nothing flies
    assert max(t for t, _ in peer.setpoints) <= t_held + 0.05
    assert len(peer.set_mode_commands()) == n_modes and peer.custom_mode == taken
    # only a new start (supervisor IDLE, then flying again) engages again
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.ENGAGED,
                 force_fn=feeder(bridge))
    assert ok


def test_link_loss_hands_back_and_never_reengages_by_itself(peer_bridge):
    peer, bridge = peer_bridge()
    engage(bridge, peer)
    n_modes = len(peer.set_mode_commands())
    # the bridge's sending port (peer.sources can also hold strays: another test's bridge
    # still sending to a port number reused here, seen once in CI with 17 sources)
    own_port = bridge.link._conn.port.getsockname()[1]
    assert own_port in {port for _, port in peer.sources}
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up, force_fn=feeder(bridge))
    t_lost = bridge.clock()
    assert ok and seq(bridge).state == EngageState.NO_LINK
    spin(bridge, 0.7, force_fn=feeder(bridge))
    assert max(t for t, _ in peer.setpoints) <= t_lost + 0.05     # nothing while lost
    assert bridge.link.counters.link_losses == 1
    assert bridge.link.counters.reopens == 0       # the udpout socket is kept ...
    assert bridge.link._conn.port.getsockname()[1] == own_port   # ... one source address
    peer.custom_mode = PX4_POSCTL                  # the autopilot's failsafe took over
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 2.0, until=lambda: seq(bridge).state == EngageState.HELD,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    spin(bridge, 1.0, force_fn=feeder(bridge))
    assert len(peer.set_mode_commands()) == n_modes
    assert bridge.link.counters.reconnects == 1
    assert bridge.link._conn.port.getsockname()[1] == own_port


def test_heartbeats_are_timed_on_the_heartbeat_clock_when_one_is_given(peer_bridge):
    """Under simulated time the node times HEARTBEATs on the ROS clock (a firmware in lockstep
    sends them at 1 Hz of its own time): while that clock stands still the link stays up
    however long the steady clock runs; once it passes heartbeat_timeout_s the link is lost."""
    sim = FrozenClock()
    peer, bridge = peer_bridge(bridge_kw={'heartbeat_clock': sim})
    wait_link(bridge)
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up)   # 4 x the timeout
    assert not ok and bridge.link.link_up and bridge.link.heartbeat_age() == 0.0
    sim.advance(0.6)                              # heartbeat_timeout_s 0.5 of the sim clock
    ok, _ = spin(bridge, 0.1, until=lambda: not bridge.link.link_up)
    assert ok and bridge.link.counters.link_losses == 1


def test_link_back_still_offboard_applies_the_input_loss_action(peer_bridge):
    # ArduPilot keeps GUIDED_NOGPS after GUID_TIMEOUT (it only levels the vehicle and holds
    # the altitude): back from a link loss, the bridge commands LAND.
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0}},
        bridge_kw={'source': 'autopilot'})
    engage(bridge, peer)
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up)
    assert ok
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 3.0, until=lambda: peer.custom_mode == AP_LAND)
    assert ok, seq(bridge).last_reason


def test_link_lost_in_the_shutdown_ends_disarmed(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'shutdown_ramp_s': 0.6})
    engage(bridge, peer, mode=Mode.LANDING)
    bridge.on_supervisor_mode(Mode.SHUTDOWN)
    peer.heartbeats_on = False                     # lost during the ramp
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up, force_fn=feeder(bridge))
    assert ok
    peer.landed = True                             # meanwhile on the ground, still armed
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.DONE)
    assert ok, seq(bridge).last_reason
    assert not peer.armed and int(peer.disarm_commands()[-1][1].param2) == 0


def test_shutdown_ramps_thrust_then_forces_disarm_only_under_the_touchdown_rule(peer_bridge):
    # The peer refuses a plain disarm (its land detector says "in the air"); the IMU says the
    # vehicle rests on the ground (specific force g at zero thrust): forced, not at once.
    peer, bridge = peer_bridge(bridge_kw={'shutdown_ramp_s': 0.6})
    engage(bridge, peer, mode=Mode.LANDING)
    bridge.on_supervisor_mode(Mode.SHUTDOWN)
    t_sd = bridge.clock()
    ok, _ = spin(bridge, 5.0, until=lambda: seq(bridge).state == EngageState.DONE,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    assert not peer.armed
    ramp = [(t, m.thrust) for t, m in peer.setpoints if t >= t_sd]
    thrusts = np.array([th for _, th in ramp])
    assert thrusts[0] == pytest.approx(0.5, abs=0.05)
    assert np.all(np.diff(thrusts) <= 1e-6)        # monotonic ramp down
    t_zero = min(t for t, th in ramp if th == 0.0)
    assert 0.5 <= t_zero - t_sd <= 0.9             # ramp of 0.6 s
    disarms = peer.disarm_commands()
    assert disarms[0][0] >= t_zero - 0.05          # disarm only after the ramp
    assert [int(m.param2) for _, m in disarms[:-1]] == [0] * (len(disarms) - 1)
    assert int(disarms[-1][1].param2) == FORCE_MAGIC
    # forced >= disarm_force_after_s (0.3 s) after the first refusal, never with a plain one
    assert disarms[-1][0] - disarms[0][0] >= 0.3 - 0.02
    assert np.min(np.diff([t for t, _ in disarms])) >= 0.25
    assert seq(bridge).disarm_forced


def test_shutdown_in_the_air_is_never_forced_and_lands(peer_bridge):
    # At low thrust the IMU reads almost no specific force: falling, not on the ground.
    peer, bridge = peer_bridge(bridge_kw={'shutdown_ramp_s': 0.4})
    engage(bridge, peer, mode=Mode.LANDING)
    bridge.on_supervisor_mode(Mode.SHUTDOWN)
    peer.specific_force = np.array([0.0, 0.0, -0.1 * GRAVITY])
    ok, _ = spin(bridge, 3.0, until=lambda: peer.custom_mode == PX4_AUTO_LAND,
                 force_fn=feeder(bridge))
    assert ok, seq(bridge).last_reason
    assert all(int(m.param2) != FORCE_MAGIC for _, m in peer.disarm_commands())
    assert peer.armed and seq(bridge).state == EngageState.LANDING


def test_landed_state_gives_a_plain_disarm(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'shutdown_ramp_s': 0.3})
    engage(bridge, peer, mode=Mode.LANDING)
    peer.landed = True
    bridge.on_supervisor_mode(Mode.SHUTDOWN)
    ok, _ = spin(bridge, 3.0, until=lambda: seq(bridge).state == EngageState.DONE,
                 force_fn=feeder(bridge))
    assert ok
    assert [int(m.param2) for _, m in peer.disarm_commands()] == [0]


# --- link, streams, reasons ---------------------------------------------------------------------

@pytest.mark.parametrize('kind', ['px4', 'ardupilot'])
def test_streams_requested_at_their_rates_and_again_after_a_link_loss(peer_bridge, kind):
    params = {'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0} \
        if kind == 'ardupilot' else {}
    peer, bridge = peer_bridge(peer_kw={'kind': kind, 'params': params},
                               bridge_kw={'source': 'autopilot' if params else 'config'})
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.rates.streams is not None
                 and bridge.rates.streams.complete)
    assert ok
    asked = {i: us for _, i, us in peer.intervals}
    imu = 105 if kind == 'px4' else 26
    expected = {31: 1e4, imu: 1e4, 83: 2e4, 245: 2e5, 1: 2e5}
    if kind == 'ardupilot':
        expected[0] = 2e5                          # HEARTBEAT at 5 Hz: takeovers seen fast
    assert asked == pytest.approx(expected)
    assert 105 not in asked or kind == 'px4'       # never HIGHRES_IMU from ArduPilot
    n = len(peer.intervals)
    spin(bridge, 0.5)
    assert len(peer.intervals) == n                # once each, not repeated
    peer.heartbeats_on = False
    spin(bridge, 1.0, until=lambda: not bridge.link.link_up)
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 4.0, until=lambda: len(peer.intervals) >= 2 * n)
    assert ok, 'asked again after the link came back'


def test_ardupilot_imu_from_scaled_imu_in_milli_g(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={
        'kind': 'ardupilot', 'specific_force': (0.5, -0.25, -GRAVITY),
        'params': {'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0}},
        bridge_kw={'source': 'autopilot'})
    wait_link(bridge)
    _, samples = spin(bridge, 0.3)
    acc = samples[-1].linear_acceleration_flu      # FRD -> FLU, milli-g rounded
    assert np.allclose(acc, [0.5, 0.25, GRAVITY], atol=GRAVITY / 1000)


def test_internal_error_0x100000_and_statustext_reported(peer_bridge):
    peer, bridge = peer_bridge()
    wait_link(bridge)
    bridge.pop_events()
    peer.statustext('PreArm: Internal errors 0x100000 l:57 flow_of_ctrl')
    ok, _ = spin(bridge, 1.0, until=lambda: bridge.status().autopilot_internal_errors)
    assert ok
    events = bridge.pop_events()
    assert any(level == 'error' and '#26865' in text for level, text in events)
    assert any(level.startswith('reason') and 'flow_of_ctrl' in text for level, text in events)
    assert bridge.status().autopilot_internal_errors == 0x100000


def test_hover_thrust_estimated_from_the_vehicles_response(peer_bridge):
    # True hover thrust 0.4, seed 0.5 (MPC_THR_HOVER): the vehicle hovers at thrust 0.4, its
    # IMU reads g; the estimate converges to 0.4 and the setpoints use it.
    peer, bridge = peer_bridge(peer_kw={'params': {'MPC_THR_HOVER': 0.5}, 'thrust': 0.4},
                               bridge_kw={'source': 'autopilot', 'estimator': True})
    wait_link(bridge)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.hover.estimator.accepted >= 50
                 and abs(bridge.hover.now() - 0.4) < 0.005)
    est = bridge.hover.estimator
    assert ok, (bridge.hover.now(), est.accepted, est.rejected)
    stamp = ros_now(bridge)
    bridge.on_heading(stamp, heading_msg_quat(0.0))
    bridge.on_force(stamp, HOVER_F)
    assert bridge.setpoints.current.thrust == pytest.approx(0.4, abs=0.006)
    st = bridge.status()
    assert st.hover_thrust_seed == pytest.approx(0.5) and 'estimate' in st.hover_thrust_source
    # on the ground (landed) nothing is learnt
    peer.landed = True
    spin(bridge, 0.3)
    n = bridge.hover.estimator.accepted
    spin(bridge, 0.3)
    assert bridge.hover.estimator.accepted == n


# --- signing ------------------------------------------------------------------------------------

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
        assert b.engagement.sequencer is None


# --- clock sync and IMU stamps ----------------------------------------------------------------

def test_imu_held_until_synced_then_stamped_boot_time_plus_offset(peer_bridge):
    # The autopilot does not answer TIMESYNC yet: its attitude is received, never published.
    peer, bridge = peer_bridge(peer_kw={'yaw_ned': np.pi / 2, 'timesync_on': False},
                               ros_offset_ns=OFFSET)
    ok, samples = spin(bridge, 2.0, until=lambda: bridge.link.link_up
                       and bridge.telemetry.imu_dropped_unsynced >= 10)
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


def _asked(peer, msg_id, since=0):
    """The intervals (us) asked for ``msg_id`` in SET_MESSAGE_INTERVAL ``since`` onwards."""
    return [us for _, i, us in peer.intervals[since:] if i == msg_id]


def test_telemetry_slows_at_rest_and_is_full_again_before_anything_engages(peer_bridge):
    # Disarmed on the pad, supervisor IDLE: after the delay the attitude, IMU and thrust
    # streams are asked at 10 Hz (1e5 us); the status streams keep their 5 Hz. A supervisor
    # mode asks the full rates again before its first engagement command leaves.
    peer, bridge = peer_bridge(peer_kw={'armed': False, 'landed': True},
                               bridge_kw={'quiet_telemetry_delay_s': 0.3})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    ok, _ = spin(bridge, 4.0, until=lambda: _asked(peer, 83)[-1:] == [1e5]
                 and bridge.rates.streams.complete)
    assert ok, peer.intervals
    assert _asked(peer, 31) == [1e4, 1e5] and _asked(peer, 105) == [1e4, 1e5]
    assert _asked(peer, 83) == [2e4, 1e5] and _asked(peer, 245) == [2e5]
    assert bridge.status().telemetry_slowed
    n, commands = len(peer.intervals), len(peer.commands)
    bridge.on_supervisor_mode(Mode.WINDOW)
    assert not bridge.status().telemetry_slowed
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.rates.streams.complete
                 and peer.set_mode_commands(), force_fn=feeder(bridge))
    assert ok, seq(bridge).state
    assert _asked(peer, 31, n) == [1e4] and _asked(peer, 105, n) == [1e4] \
        and _asked(peer, 83, n) == [2e4]
    first_full = min(t for t, i, _ in peer.intervals[n:] if i == 31)
    engage_cmds = [t for t, m in peer.commands[commands:]
                   if m.command != mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert first_full <= min(engage_cmds)


@pytest.mark.parametrize('how', ['arm request', 'pilot arms', 'frames'])
def test_telemetry_full_again_on_an_arm_request_or_an_armed_vehicle(peer_bridge, how):
    peer, bridge = peer_bridge(peer_kw={'armed': False, 'landed': True},
                               bridge_kw={'quiet_telemetry_delay_s': 0.3})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.status().telemetry_slowed
                 and bridge.rates.streams.complete)
    assert ok
    n = len(peer.intervals)
    if how == 'arm request':
        assert bridge.request_arm()[0]
    elif how == 'pilot arms':
        peer.armed = True                       # armed by its pilot: seen at the HEARTBEAT
    else:                                       # cameras on: the supervisor evaluates frames
        assert bridge.on_supervisor_status(1_000_000_000, int(Mode.IDLE)) == ''
        assert not bridge.status().telemetry_slowed      # asked in that call
    feed = (lambda now: bridge.on_supervisor_status(int(now * 1e9), int(Mode.IDLE))) \
        if how == 'frames' else None
    ok, _ = spin(bridge, 2.0, until=lambda: _asked(peer, 31, n) == [1e4]
                 and bridge.rates.streams.complete, force_fn=feed)
    assert ok, peer.intervals[n:]
    assert not bridge.status().telemetry_slowed
    spin(bridge, 0.8, force_fn=feed)            # longer than the delay: stays full
    assert _asked(peer, 31, n) == [1e4] and not bridge.status().telemetry_slowed
    if how == 'frames':                         # the frames stop: at rest again after it
        ok, _ = spin(bridge, 3.0, until=lambda: _asked(peer, 31, n)[-1] == 1e5)
        assert ok and bridge.status().telemetry_slowed


def test_telemetry_never_slows_when_off_or_armed(peer_bridge):
    for peer_kw, bridge_kw in (({'armed': False, 'landed': True},
                                {'quiet_telemetry_rate_hz': 0.0}), ({'armed': True}, {})):
        peer, bridge = peer_bridge(peer_kw=peer_kw, bridge_kw={
            'quiet_telemetry_delay_s': 0.2, **bridge_kw})
        wait_link(bridge)
        bridge.on_supervisor_mode(Mode.IDLE)
        spin(bridge, 1.0)
        assert _asked(peer, 31) == [1e4] and not bridge.status().telemetry_slowed


def test_autopilot_reboot_holds_the_imu_until_synced_again(peer_bridge):
    clock = FrozenClock()
    frames = FrameClock(clock, start_ns=100_000 * MS)     # booted 100 s ago
    boot_epoch = [0]                                # ns of `frames` at the last boot

    def boot():
        return frames() - boot_epoch[0]
    peer, bridge = peer_bridge(peer_kw={'boot_clock': boot}, bridge_kw={'clock': clock},
                               ros_clock=lambda: frames() + OFFSET)
    wait_link(bridge)
    assert bridge.time_sync.offset_ns == OFFSET
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.rates.streams.complete)
    assert ok
    requested = len(peer.intervals)
    assert requested > 0
    # Reboot: the boot clock starts again at 1 s; our ROS clock runs on.
    boot_epoch[0] = frames() - 1_000 * MS
    spin(bridge, 0.1)
    assert bridge.time_sync.resets == 1 and bridge.time_sync.reboots == 1
    ok, samples = spin(bridge, 2.0, until=lambda: bridge.time_sync.synced)
    assert ok
    new_offset = OFFSET + boot_epoch[0]
    assert bridge.time_sync.offset_ns == new_offset
    _, samples = spin(bridge, 0.2)
    sent_ns = {ms * MS for ms in peer.attitude_ms}
    assert samples and all(s.stamp_ns - new_offset in sent_ns for s in samples)
    assert len(peer.intervals) > requested         # an autopilot forgets its streams


def test_a_time_jump_resyncs_but_is_no_reboot(peer_bridge):
    # The companion's system clock is stepped by 3 s (chrony's makestep) while the autopilot
    # runs on: the clock sync re-initialises from the streak of outliers, and nothing
    # per-boot is redone (streams asked again, landed state and ground contact forgotten).
    clock = FrozenClock()
    frames = FrameClock(clock, start_ns=100_000 * MS)
    step = [0]
    peer, bridge = peer_bridge(peer_kw={'boot_clock': frames}, bridge_kw={'clock': clock},
                               ros_clock=lambda: frames() + OFFSET + step[0])
    wait_link(bridge)
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.rates.streams.complete)
    assert ok
    requested = len(peer.intervals)
    assert requested > 0
    step[0] = 3_000 * MS
    ok, _ = spin(bridge, 2.0, until=lambda: bridge.time_sync.resets == 1
                 and bridge.time_sync.synced)
    assert ok
    assert bridge.time_sync.reboots == 0
    assert bridge.time_sync.offset_ns == OFFSET + 3_000 * MS
    spin(bridge, 0.3)
    assert len(peer.intervals) == requested


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
                       and bridge.telemetry.imu_dropped_unsynced > 20)
    spin(bridge, 0.3)
    assert bridge.link.link_up
    assert peer.timesync_seen == [] and peer.timesync_answers == []
    assert samples == [] and bridge.telemetry.imu_dropped_unsynced > 0
    assert bridge.status().counters['timesync_answered'] == 0


def test_setpoint_time_boot_ms_is_the_force_stamp_mapped_at_each_send(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'timesync_on': False}, ros_offset_ns=OFFSET)
    ok, _ = spin(bridge, 2.0, until=lambda: bridge.link.link_up and seq(bridge))
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
    assert wait_peer(peer, lambda: sent_for(peer, 1255))
    assert sent_for(peer, 1254) == []


def test_diagnostics_report_the_clock_sync(peer_bridge):
    peer, bridge = peer_bridge(ros_offset_ns=OFFSET)
    wait_link(bridge)
    ts = bridge.status().time_sync
    assert ts.synced and ts.offset_ns == OFFSET and ts.accepted >= 5
    assert ts.last_rtt_ns == 0                    # within one frame of the FrameClock


# --- heading / force pairing by stamp ---------------------------------------------------------

S0, S1, S2 = 1_000_000_000, 1_020_000_000, 1_040_000_000      # 20 ms frames: 1000, 1020, 1040
# (older than max_force_age_s on the peer's boot clock by the time they are sent: the tests
# that send them switch the age check off; test_forces_of_old_images_... tests it)


def test_heading_before_force_sent_at_once_with_the_heading_of_the_same_stamp(peer_bridge):
    peer, bridge = peer_bridge(bridge_kw={'clock': FrozenClock(), 'max_force_age_s': 0.0})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.1))
    bridge.on_heading(S1, heading_msg_quat(0.2))   # a newer heading is already there ...
    bridge.on_force(S0, HOVER_F)
    assert wait_peer(peer, lambda: sent_for(peer, 1000))  # ... at once, no timer ...
    assert same_rotation(sent_for(peer, 1000)[0].q, level_q(0.1))   # ... with its own stamp's
    bridge.on_force(S1, HOVER_F)
    assert wait_peer(peer, lambda: sent_for(peer, 1020))
    assert same_rotation(sent_for(peer, 1020)[0].q, level_q(0.2))
    assert bridge.status().counters['headings_missing'] == 0


def test_force_without_its_heading_flies_at_once_with_the_latest_and_is_counted(peer_bridge):
    clock = FrozenClock()
    peer, bridge = peer_bridge(bridge_kw={'clock': clock, 'max_force_age_s': 0.0})
    wait_link(bridge)
    bridge.on_heading(S0, heading_msg_quat(0.3))
    bridge.on_force(S0, HOVER_F)
    bridge.on_force(S1, HOVER_F)                   # its heading is not there: no waiting
    assert wait_peer(peer, lambda: sent_for(peer, 1020))
    assert same_rotation(sent_for(peer, 1020)[0].q, level_q(0.3))   # the latest heading
    assert bridge.status().counters['headings_missing'] == 1
    assert 'without the heading' in bridge.pop_heading_warning()
    assert bridge.pop_heading_warning() == ''      # reported once
    # the late heading of S1 never changes what was sent for S1; it is the latest for S2
    assert bridge.on_heading(S1, heading_msg_quat(0.5)) == ''
    for _ in range(5):
        clock.advance(0.04)
        bridge.stream()
    assert wait_peer(peer, lambda: len(sent_for(peer, 1020)) >= 6)
    first = sent_for(peer, 1020)[0]
    for m in sent_for(peer, 1020):                 # every repeat is what was sent
        assert np.allclose(m.q, first.q, atol=0.0) and m.thrust == first.thrust
    assert bridge.status().counters['late_headings'] == 1
    bridge.on_force(S2, HOVER_F)
    assert wait_peer(peer, lambda: sent_for(peer, 1040))
    assert same_rotation(sent_for(peer, 1040)[0].q, level_q(0.5))


def test_stream_held_sends_nothing_then_fallback_carries_no_newer_time(peer_bridge):
    # The node holds the stream until imu/data has its readers; a fallback setpoint (level
    # hover before any force) carries time_boot_ms 0, never the autopilot's current time,
    # which a lockstep sim would take for the answer to its newest frame.
    peer, bridge = peer_bridge()
    bridge.setpoints.enabled = False
    wait_link(bridge)
    spin(bridge, 0.3)
    assert peer.setpoints == []
    bridge.setpoints.enabled = True
    ok, _ = spin(bridge, 1.0, until=lambda: len(peer.setpoints) >= 3)
    assert ok
    assert {m.time_boot_ms for _, m in peer.setpoints} == {0}


def test_content_follows_the_status_of_the_force_stamp_not_the_latest_mode(peer_bridge):
    # ibvs/mode SHUTDOWN may land before the force of the last LANDING frame: that force is
    # still flown as LANDING (its own status); the SHUTDOWN frame's force starts the ramp.
    peer, bridge = peer_bridge(bridge_kw={'max_force_age_s': 0.0})   # fixed stamps: no age
    wait_link(bridge)
    assert bridge.on_supervisor_status(1_000_000_000, int(Mode.LANDING)) == ''
    assert bridge.on_supervisor_status(1_020_000_000, int(Mode.SHUTDOWN)) == ''
    assert bridge.on_supervisor_status(1_040_000_000, 99) != ''      # refused
    bridge.on_supervisor_mode(int(Mode.SHUTDOWN))
    bridge.on_force(1_000_000_000, 1.2 * HOVER_F)
    assert bridge.setpoints.content_mode() == Mode.LANDING
    assert bridge.setpoints.source == SetpointSource.IBVS
    bridge.on_force(1_020_000_000, 1.2 * HOVER_F)
    assert bridge.setpoints.content_mode() == Mode.SHUTDOWN
    assert bridge.setpoints.source == SetpointSource.SHUTDOWN_RAMP
    # a force without a status of its own: the latest ibvs/mode
    bridge.on_force(1_060_000_000, HOVER_F)
    assert bridge.setpoints.content_mode() == Mode.SHUTDOWN


def test_bad_force_is_never_sent_held_then_level_hover_outside_an_engagement(peer_bridge):
    peer, bridge = peer_bridge(peer_kw={'yaw_ned': 0.5}, bridge_kw={'hold_last_s': 0.3})
    wait_link(bridge)
    stamp = ros_now(bridge)
    bridge.on_heading(stamp, heading_msg_quat(0.0))
    F = MASS * np.array([-1.0, 0.0, GRAVITY])
    assert bridge.on_force(stamp, F) == ''
    spin(bridge, 0.1)
    good_q = np.array(last_setpoint(peer).q)
    for bad in (np.array([np.nan, 0.0, 9.0]), np.array([0.0, 0.0, 1e4]),
                np.array([0.0, 0.0, -5.0])):
        assert bridge.on_force(stamp + FRAME_NS, bad) != ''
    spin(bridge, 0.1)
    assert bridge.setpoints.source == SetpointSource.HOLD_LAST
    assert same_rotation(last_setpoint(peer).q, good_q)
    assert last_setpoint(peer).time_boot_ms == bridge.setpoints.stamp_to_boot_ms(stamp + FRAME_NS)
    spin(bridge, 0.4)
    assert bridge.setpoints.source == SetpointSource.LEVEL_HOVER     # standby: not engaged
    m = last_setpoint(peer)
    assert same_rotation(m.q, [np.cos(0.25), 0.0, 0.0, np.sin(0.25)])   # level, yaw 0.5
    assert m.thrust == pytest.approx(0.5)
    for _, m in peer.setpoints:
        assert np.all(np.isfinite(m.q)) and np.isfinite(m.thrust)
    assert bridge.on_heading(stamp, np.array([np.nan, 0, 0, 1.0])) != ''
    assert bridge.on_heading(stamp, np.array([2.0, 0, 0, 0])) != ''


@pytest.mark.parametrize('params, expected, says', [
    ({'FS_GCS_ENABLE': 5, 'SYSID_MYGCS': 1}, True, 'dead-bridge failsafe: FS_GCS_ENABLE = 5'),
    ({'FS_GCS_ENABLE': 0, 'SYSID_MYGCS': 1}, False, 'no dead-bridge failsafe (FS_GCS_ENABLE = 0)'),
    ({'FS_GCS_ENABLE': 5, 'SYSID_MYGCS': 255}, False, "SYSID_MYGCS = 255 is not this bridge's"),
    ({}, None, None)])
def test_ardupilot_dead_bridge_failsafe_is_read_and_reported(peer_bridge, params, expected,
                                                             says):
    """FS_GCS_ENABLE / SYSID_MYGCS are read and reported, never required to fly."""
    peer, bridge = peer_bridge(peer_kw={'kind': 'ardupilot', 'params': {
        'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.3, 'ATC_ANGLE_BOOST': 1, **params}})
    wait_link(bridge)
    spin(bridge, 1.5, until=lambda: bridge.params.dead_bridge_failsafe is not None)
    assert bridge.params.dead_bridge_failsafe is expected
    assert bridge.status().dead_bridge_failsafe is expected
    status = bridge.status()         # the values as read, and our system id, for /diagnostics
    assert status.dead_bridge_params == {k: float(v) for k, v in params.items()}
    assert status.source_system == 1
    events = [text for _, text in bridge.pop_events()]
    if says:
        assert sum(says in t for t in events) == 1, events
    assert seq(bridge).state == EngageState.STANDBY       # it never blocks preflight


def test_param_value_decodes_px4_bytewise_integers_and_keeps_casts():
    from ibvs_control.mavlink.params import param_value
    as_float = struct.unpack('<f', struct.pack('<i', 4))[0]        # PX4's INT32 4 on the wire
    assert as_float != 4.0 and as_float > 0.0                     # a denormal, not 4.0
    assert param_value(as_float, 6, bytewise=True) == 4.0
    minus_one = struct.unpack('<f', struct.pack('<i', -1))[0]     # a NaN pattern
    assert param_value(minus_one, 6, bytewise=True) == -1.0
    assert param_value(0.49, 9, bytewise=True) == 0.49             # REAL32: as sent
    assert param_value(5.0, 2, bytewise=False) == 5.0              # ArduPilot: cast


@pytest.mark.parametrize('params, expected, says', [
    ({'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 4}, True,
     'dead-bridge failsafe: COM_OBL_RC_ACT = 4 (Land mode), COM_OF_LOSS_T = 1 s'),
    ({'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 0}, False,
     'Position mode needs a position estimate'),
    ({'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 7}, False, 'Disarm stops the motors in the air'),
    ({'COM_OF_LOSS_T': 5.0, 'COM_OBL_RC_ACT': 4}, True,
     'COM_OF_LOSS_T = 5 s: the vehicle flies the last setpoint'),
    ({}, None, None)])
def test_px4_offboard_loss_failsafe_is_read_and_reported(peer_bridge, params, expected, says):
    """COM_OF_LOSS_T / COM_OBL_RC_ACT (INT32, bytewise) are read and reported, never required."""
    px4_params = {'MPC_THR_HOVER': 0.5, **params}
    peer, bridge = peer_bridge(peer_kw={'kind': 'px4', 'params': px4_params})
    wait_link(bridge)
    spin(bridge, 1.5, until=lambda: bridge.params.dead_bridge_failsafe is not None)
    assert bridge.params.dead_bridge_failsafe is expected
    assert bridge.status().dead_bridge_failsafe is expected
    # the values as read, for /diagnostics (the preflight gates on them)
    assert bridge.status().dead_bridge_params == {k: float(v) for k, v in params.items()}
    events = [text for _, text in bridge.pop_events()]
    if says:
        assert sum(says in t for t in events) == 1, events
    else:
        assert not [t for t in events if 'offboard loss' in t or 'dead-bridge' in t], events
    assert seq(bridge).state == EngageState.STANDBY       # it never blocks preflight


# --- MavlinkReader: input handled as it arrives, no poll timer -------------------------------

def _reader_link():
    from ibvs_control.mavlink.link import MavlinkLink
    link = MavlinkLink(LinkConfig(url='udpin:127.0.0.1:0', source_system=1))
    peer = mavutil.mavlink_connection(f'udpout:127.0.0.1:{link.local_port}', source_system=1,
                                      source_component=1)
    return link, peer


def _send_heartbeat(peer):
    peer.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR,
                            mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)


def _wait_until(predicate, timeout_s=2.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not predicate():
        time.sleep(0.002)
    return predicate()


def test_reader_wakes_on_input_within_milliseconds_and_holds_the_lock():
    from ibvs_control.mavlink.link import MavlinkReader
    link, peer = _reader_link()
    lock = threading.Lock()
    handled = []                              # (receipt delay s, whether the lock was held)

    def on_readable():
        handled.append((time.monotonic() - sent[-1], lock.locked()))
        link.poll()                           # drain, as the bridge's receive step does

    reader = MavlinkReader(link, lock, on_readable, wait_s=0.5)
    sent = []
    try:
        reader.start()
        time.sleep(0.2)
        assert handled == []                  # no input: no call (no polling)
        for _ in range(5):
            sent.append(time.monotonic())
            _send_heartbeat(peer)
            assert _wait_until(lambda: len(handled) == len(sent))
        delays = [d for d, _ in handled]
        # woken by the socket, not by the 0.5 s wait: well under one camera period
        assert max(delays) < 0.02, delays
        assert all(held for _, held in handled)
        assert link.counters.received == 5 and reader.wakeups == 5
    finally:
        reader.stop()
        link.close()
        peer.close()
    assert not reader._thread.is_alive()


def test_reader_follows_a_reopened_link_and_reports_errors_without_dying():
    from ibvs_control.mavlink.link import MavlinkReader
    link, peer = _reader_link()
    lock = threading.Lock()
    errors, calls = [], []

    def on_readable():
        calls.append(1)
        link.poll()
        if len(calls) == 1:
            raise RuntimeError('boom')

    reader = MavlinkReader(link, lock, on_readable, wait_s=0.05, on_error=errors.append)
    try:
        reader.start()
        _send_heartbeat(peer)
        assert _wait_until(lambda: errors == ['RuntimeError: boom'])
        port = link.local_port
        link.close()                          # closed under the reader: it waits, no error
        assert port > 0 and link.local_port is None
        time.sleep(0.2)
        link.config = dataclasses.replace(link.config, url=f'udpin:127.0.0.1:{port}')
        link.open()                           # the same port again
        _send_heartbeat(peer)
        assert _wait_until(lambda: len(calls) >= 2)
        assert reader.errors == 1 and reader._thread.is_alive()
    finally:
        reader.stop()
        link.close()
        peer.close()


def test_reader_refuses_a_nonpositive_wait():
    from ibvs_control.mavlink.link import MavlinkReader
    link, peer = _reader_link()
    try:
        with pytest.raises(ValueError, match='wait_s'):
            MavlinkReader(link, threading.Lock(), lambda: None, wait_s=0.0)
    finally:
        link.close()
        peer.close()


def test_reader_poll_supervises_only_after_messages_other_than_high_rate_telemetry():
    """poll(supervise=False) (the node's reader thread, every datagram): the supervision
    step (sequencer, requests) runs only when something else than the ~270/s attitude, IMU
    and thrust streams came in; poll() (the stream tick) runs it always."""
    m = mavutil.mavlink
    bridge = make_bridge(free_udp_port())
    try:
        steps = []
        bridge._run_sequencer = steps.append
        attitude = m.MAVLink_attitude_quaternion_message(10, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                                         [0.0] * 4)
        imu = m.MAVLink_highres_imu_message(10_000, 0.0, 0.0, -GRAVITY, *[0.0] * 10, 0)
        state = m.MAVLink_extended_sys_state_message(0, m.MAV_LANDED_STATE_IN_AIR)
        for batch, supervise, stepped in (([attitude, imu], False, False),
                                          ([attitude], True, True),
                                          ([attitude, state], False, True),
                                          ([state], False, True)):
            bridge.link.poll = lambda batch=batch: list(batch)
            steps.clear()
            bridge.poll(1, supervise)
            assert bool(steps) == stepped, ([x.get_type() for x in batch], supervise)
        assert bridge.telemetry.landed_state == m.MAV_LANDED_STATE_IN_AIR   # handled all
    finally:
        bridge.close()


# --- MavlinkLink: connection errors and a second UDP peer are reported -----------------------

def test_a_port_that_cannot_be_opened_is_reported_once_per_loss_with_its_reason():
    from ibvs_control.mavlink.link import MavlinkLink
    clock = FrozenClock()
    link = MavlinkLink(LinkConfig(url='/dev/ibvs-no-such-serial-port,921600',
                                  reconnect_period_s=1.0), clock=clock)
    try:
        events = link.pop_events()
        assert len(events) == 1 and events[0][0] == 'error', events
        assert 'cannot open /dev/ibvs-no-such-serial-port' in events[0][1]
        assert 'cannot open' in link.last_error
        for _ in range(3):                      # retried every reconnect period, said once
            clock.t += 1.5
            link.poll()
        assert link.counters.reopens >= 2 and link.pop_events() == []
        assert 'cannot open' in link.last_error
    finally:
        link.close()


def test_a_second_udp_sender_is_warned_about_once_and_counted():
    """pymavlink's udpin answers every address it heard: a second sender gets our messages."""
    link, autopilot = _reader_link()
    port = link.local_port
    tool = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=255,
                                      source_component=190)
    try:
        _send_heartbeat(autopilot)
        assert _wait_until(lambda: link.poll() or link.counters.received >= 1)
        assert link.pop_events() == [] and link.counters.peers == 1
        for _ in range(3):                      # a GCS tool on the companion port
            tool.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                    mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert _wait_until(lambda: link.poll() is not None and link.counters.foreign >= 3)
        _send_heartbeat(autopilot)
        assert _wait_until(lambda: link.poll() or link.counters.received >= 2)
        events = link.pop_events()
        assert len(events) == 1 and events[0][0] == 'warn', events
        tool_port = tool.port.getsockname()[1]
        assert f'second address 127.0.0.1:{tool_port}' in events[0][1]
        assert link.counters.peers == 2 and link.target_system == 1
        # all silent, then the autopilot again from a new port (ArduPilot restarted: it sends
        # from an ephemeral port): only noted. Silent for 1.1 s of pymavlink's clock (wall
        # time): every sender's last-heard time set back by that much
        alive = link._conn.clients_last_alive
        for address in alive:
            alive[address] -= 1.1
        restarted = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=1,
                                               source_component=1)
        _send_heartbeat(restarted)
        assert _wait_until(lambda: link.poll() or link.counters.received >= 3)
        events = link.pop_events()
        assert [lv for lv, _ in events] == ['info'] and 'restarted' in events[0][1], events
        assert link.counters.peers == 3
        restarted.close()
    finally:
        link.close()
        autopilot.close()
        tool.close()


def test_the_bridge_logs_the_links_errors_and_reports_them_on_diagnostics():
    link = LinkConfig(url='/dev/ibvs-no-such-serial-port,921600')
    bridge = MavlinkBridge(BridgeConfig(link=link, mass=MASS, max_thrust_factor=2.0,
                                        configured_hover_thrust=0.5), clock=FrozenClock())
    try:
        events = bridge.pop_events()
        assert [lv for lv, text in events if 'cannot open' in text] == ['error'], events
        st = bridge.status()
        assert not st.link_up and 'cannot open' in st.link_error
        assert st.counters['peers'] == 0
    finally:
        bridge.close()


# --- the ROS clock read only when needed (reader thread) -----------------------------------

def test_reader_poll_reads_the_ros_clock_only_for_messages_that_need_it():
    """poll(ros_clock=...): high-rate telemetry alone reads no clock; TIMESYNC reads it first."""
    enc = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    bridge = make_bridge(free_udp_port())
    reads = []

    def ros_clock():
        reads.append(len(reads))
        return 5_000_000_000 + len(reads)

    def feed(*messages):
        bridge.link.poll = lambda: list(messages)

    attitude = enc.attitude_quaternion_encode(10, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    imu = enc.highres_imu_encode(10_000, 0.0, 0.0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    thrust = enc.attitude_target_encode(10, 7, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
    try:
        feed(attitude, imu, thrust)
        bridge.poll(supervise=False, ros_clock=ros_clock)
        assert reads == []                          # nothing here needed the ROS time
        # a TIMESYNC request of the autopilot: our answer's tc1 is the ROS time, read for it
        request = enc.timesync_encode(0, 123_000)
        feed(attitude, request)
        bridge.poll(supervise=False, ros_clock=ros_clock)
        assert reads == [0] and bridge.ros.ns == 5_000_000_001
        # the periodic poll supervises: it reads the clock once even with telemetry alone
        feed(attitude)
        bridge.poll(supervise=True, ros_clock=ros_clock)
        assert reads == [0, 1] and bridge.ros.ns == 5_000_000_002
        # ros_ns given (no ros_clock): taken as before
        feed(attitude)
        bridge.poll(7_000_000_000, supervise=False)
        assert bridge.ros.ns == 7_000_000_000 and len(reads) == 2
    finally:
        bridge.close()


# --- the pilot's mission switch (RC_CHANNELS) ---------------------------------------------------

def rc_with(channel, us, count=8):
    """18 RC channels: ``count`` used at 1500 us, ``channel`` (1-based) at ``us``."""
    rc = [1500] * count + [0xFFFF] * (18 - count)
    rc[channel - 1] = us
    return rc


@pytest.mark.parametrize('kind', ['px4', 'ardupilot'])
def test_pilot_switch_read_from_rc_channels_asked_for_and_kept_at_rest(peer_bridge, kind):
    from ibvs_control.core.pilot_input import PilotInput
    from ibvs_control.mavlink.pilot_switch import PilotSwitchConfig
    params = {'GUID_OPTIONS': 8, 'MOT_THST_HOVER': 0.5, 'ATC_ANGLE_BOOST': 0} \
        if kind == 'ardupilot' else {}
    peer, bridge = peer_bridge(
        peer_kw={'kind': kind, 'params': params, 'armed': False},
        bridge_kw={'source': 'autopilot' if params else 'config',
                   'pilot_switch': PilotSwitchConfig(channel=7),
                   'quiet_telemetry_delay_s': 0.3})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    assert bridge.pilot_input() == PilotInput.UNKNOWN          # no RC_CHANNELS yet
    ok, _ = spin(bridge, 4.0, until=lambda: bridge.rates.slowed)
    assert ok, 'telemetry never slowed at rest'
    asked = {i: us for _, i, us in peer.intervals}
    assert asked[65] == pytest.approx(1e5)          # RC_CHANNELS at 10 Hz, not slowed at rest
    peer.rc = rc_with(7, 1100)
    ok, _ = spin(bridge, 0.5, until=lambda: bridge.pilot_input() == PilotInput.OFF)
    assert ok
    peer.rc = rc_with(7, 1500)                       # the hysteresis band: unchanged
    spin(bridge, 0.3)
    assert bridge.pilot_input() == PilotInput.OFF
    peer.rc = rc_with(7, 1900)
    ok, _ = spin(bridge, 0.5, until=lambda: bridge.pilot_input() == PilotInput.ON)
    assert ok and bridge.status().pilot_input == 'ON'
    peer.rc = None                                   # RC_CHANNELS stop: UNKNOWN, not OFF
    ok, _ = spin(bridge, 2.0, until=lambda: bridge.pilot_input() == PilotInput.UNKNOWN)
    assert ok


def test_pilot_takeover_in_flight_latches_off_until_the_switch_is_off(peer_bridge):
    from ibvs_control.core.pilot_input import PilotInput
    from ibvs_control.mavlink.pilot_switch import PilotSwitchConfig
    peer, bridge = peer_bridge(bridge_kw={'pilot_switch': PilotSwitchConfig(channel=7)})
    peer.rc = rc_with(7, 1900)
    engage(bridge, peer)
    assert bridge.pilot_input() == PilotInput.ON
    peer.custom_mode = PX4_POSCTL                    # the pilot takes the vehicle
    ok, _ = spin(bridge, 1.0, until=lambda: seq(bridge).state == EngageState.HELD,
                 force_fn=feeder(bridge))
    assert ok
    spin(bridge, 0.5)
    assert bridge.pilot_input() == PilotInput.OFF    # switch still ON: OFF, latched
    peer.rc = rc_with(7, 1100)
    spin(bridge, 0.3)
    peer.rc = rc_with(7, 1900)
    ok, _ = spin(bridge, 0.5, until=lambda: bridge.pilot_input() == PilotInput.ON)
    assert ok                                        # the switch cycled: it reads again


def test_without_a_switch_a_link_loss_in_flight_is_off_until_the_next_standby(peer_bridge):
    from ibvs_control.core.pilot_input import PilotInput
    peer, bridge = peer_bridge()
    engage(bridge, peer)
    assert bridge.pilot_input() == PilotInput.UNKNOWN
    assert 65 not in {i for _, i, _ in peer.intervals}     # no switch: no RC_CHANNELS asked
    peer.heartbeats_on = False
    ok, _ = spin(bridge, 2.0, until=lambda: not bridge.link.link_up, force_fn=feeder(bridge))
    assert ok and bridge.pilot_input() == PilotInput.OFF
    peer.custom_mode = PX4_POSCTL
    peer.heartbeats_on = True
    ok, _ = spin(bridge, 2.0, until=lambda: seq(bridge).state == EngageState.HELD)
    assert ok and bridge.pilot_input() == PilotInput.OFF
    bridge.on_supervisor_mode(Mode.IDLE)             # a new mission may start
    ok, _ = spin(bridge, 1.0, until=lambda: seq(bridge).state == EngageState.STANDBY)
    assert ok and bridge.pilot_input() == PilotInput.UNKNOWN


def test_a_supervisor_that_stops_flying_before_engagement_is_no_release(peer_bridge):
    """SET_MODE -> HELD because the supervisor left its flying modes (an abort before PX4 took
    OFFBOARD, measured in lockstep): the mission ended on the graph's side, ibvs/pilot_input
    stays as it was (no latched OFF)."""
    from ibvs_control.core.pilot_input import PilotInput
    peer, bridge = peer_bridge(bridge_kw={'prestream_s': 5.0})
    wait_link(bridge)
    bridge.on_supervisor_mode(Mode.IDLE)
    bridge.on_supervisor_mode(Mode.WINDOW)
    ok, _ = spin(bridge, 1.0, until=lambda: seq(bridge).state == EngageState.SET_MODE,
                 force_fn=feeder(bridge))
    assert ok
    bridge.on_supervisor_mode(Mode.FAILSAFE)
    ok, _ = spin(bridge, 1.0, until=lambda: seq(bridge).state == EngageState.HELD)
    assert ok and bridge.pilot_input() == PilotInput.UNKNOWN
