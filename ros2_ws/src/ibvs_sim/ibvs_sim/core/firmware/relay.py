"""The wire between the companion computer and a real firmware, inside the lockstep sim.

:class:`CompanionRelay` stands where :class:`~ibvs_sim.core.autopilot.Autopilot` stands when
the sim emulates the autopilot: the bridge talks MAVLink to the sim's endpoint
(``mavlink_url``, e.g. ``udpin:127.0.0.1:14560``) and the relay passes every datagram on,
unchanged (signed ones too), to the firmware's companion port (:class:`CompanionPort`: PX4
listens on 14580 + instance and sends to 14540 + instance; ArduPilot's SERIAL1 sends to
14540 + instance from a port of its own, which the relay answers), and the firmware's back.
It reads what the lockstep needs on the way: the ``time_boot_ms`` of the bridge's
SET_ATTITUDE_TARGET (the frame it answers), the newest attitude the firmware sent (the IMU
sample that must reach the graph before a frame's images), and whether the firmware flies
the graph's setpoints (PX4 in OFFBOARD, ArduCopter in GUIDED_NOGPS). The firmware's clock
runs ``boot_offset_ms`` ahead of sim time (for a firmware that answers TIMESYNC in lockstep,
measured from the answers the bridge gets: :meth:`CompanionRelay.pass_timesync`); the relay
reports sim time. ``new_setpoints`` holds (sim ms, wall s) of each new setpoint for the sim's
answer latency. Never blocks. ROS-free.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import os
import socket
import time
from typing import Any, Callable

import numpy as np

from ibvs_common.core.mavlink_connection import udp_server_address

os.environ.setdefault('MAVLINK20', '1')
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402  (after MAVLINK20)

PX4_COMPANION_SEND_BASE = 14540   # PX4 sends the companion stream to 127.0.0.1:(14540 + i)
PX4_COMPANION_LISTEN_BASE = 14580  # ... and listens on 14580 + i
PX4_MAIN_MODE_OFFBOARD = 6
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
ARDUCOPTER_MODE_GUIDED_NOGPS = 20     # the custom_mode the bridge flies ArduCopter in
MAX_DATAGRAM = 65535
ATTITUDE_MESSAGE = 'ATTITUDE_QUATERNION'     # what the bridge turns into imu/data
#: ms: the bridge maps stamps between ROS time and the firmware's clock through its TIMESYNC
#: estimate. The relay makes its round trips exact (:meth:`CompanionRelay.poll`), but PX4's
#: clock is its last HIL_SENSOR's, up to one 4 ms sensor step before the sim's: a setpoint
#: this close to a frame answers it (frames are 20-33 ms apart: never the previous one's)
STAMP_TOLERANCE_MS = 8
#: ms: an imu/data sample this close to the newest attitude sent reaches it. The bridge's
#: offset is off by PX4's sensor step either way (measured -4 and +4 ms): a tighter hold
#: waited for a stamp that never came (5 s stalls, then a lost link; a failed CI run). The
#: price: an image may go before the IMU sample of its own instant (about 5 of 600 frames;
#: the graph answers those with a gyro-propagated attitude and counts them)
IMU_TOLERANCE_MS = STAMP_TOLERANCE_MS
#: s (wall): the wait for PX4's answer to a TIMESYNC request passed on (it answers from its
#: receiving thread at once; measured < 1 ms)
TIMESYNC_ANSWER_WAIT_S = 0.05
#: a firmware answering TIMESYNC in lockstep: the relay's clock offset is the median of this
#: many of the last answers, as the bridge's (time_sync.py)
OFFSET_SAMPLES = 5


@dataclass(frozen=True)
class CompanionPort:
    """A firmware's companion link as the relay meets it.

    ``listen_port``: where the relay receives the firmware's datagrams; ``send_port``: where
    the firmware listens (None: it answers the address the firmware sends from, as
    ArduPilot's SERIAL1 wants); ``autopilot``: its HEARTBEAT's MAV_AUTOPILOT; ``flying``:
    whether a HEARTBEAT's ``custom_mode`` is the mode that flies the bridge's setpoints;
    ``timesync_in_lockstep``: the firmware answers TIMESYNC only when its clock steps
    (ArduPilot's main loop waits for the physics), not at once (PX4's receiver thread).
    """

    name: str
    listen_port: int
    send_port: int | None
    autopilot: int
    flying: Callable[[int], bool]
    timesync_in_lockstep: bool = False

    @staticmethod
    def px4(instance: int) -> 'CompanionPort':
        """Return PX4 SITL's companion link of ``instance`` (OFFBOARD flies setpoints)."""
        return CompanionPort('PX4', PX4_COMPANION_SEND_BASE + int(instance),
                             PX4_COMPANION_LISTEN_BASE + int(instance), MAV_AUTOPILOT_PX4,
                             lambda mode: (int(mode) >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD)

    @staticmethod
    def ardupilot(instance: int) -> 'CompanionPort':
        """Return ArduPilot SITL's SERIAL1 of ``instance`` (GUIDED_NOGPS flies setpoints)."""
        return CompanionPort('ArduPilot', PX4_COMPANION_SEND_BASE + int(instance), None,
                             MAV_AUTOPILOT_ARDUPILOTMEGA,
                             lambda mode: int(mode) == ARDUCOPTER_MODE_GUIDED_NOGPS,
                             timesync_in_lockstep=True)


class CompanionRelay:
    """Bridge <-> firmware datagrams, and the lockstep's view of them (see module doc).

    ``bridge_url``: the sim's endpoint (``udpin:HOST:PORT``); ``instance``: the PX4 instance
    (its :meth:`CompanionPort.px4`) unless ``port`` names the firmware's link.
    """

    def __init__(self, bridge_url: str, instance: int, boot_offset_ms: int,
                 wall_clock: Callable[[], float] = time.monotonic,
                 port: CompanionPort | None = None) -> None:
        address = udp_server_address(bridge_url)
        if address is None:
            raise ValueError(f'the relay needs a udpin: endpoint for the bridge, got '
                             f'{bridge_url!r}')
        self.boot_offset_ms = int(boot_offset_ms)
        self.wall_clock = wall_clock
        self.graph_flies: Callable[[], bool] = lambda: True
        self._bridge = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._bridge.bind(address)
        self._bridge.setblocking(False)
        self.port = port or CompanionPort.px4(instance)
        self._firmware = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._firmware.bind(('127.0.0.1', self.port.listen_port))
        self._firmware.setblocking(False)
        self._firmware_to = (None if self.port.send_port is None
                             else ('127.0.0.1', self.port.send_port))
        self._bridge_peer = None
        self._from_bridge = mavlink.MAVLink(None)
        self._from_firmware = mavlink.MAVLink(None)
        self.last_setpoint_sim_ms: int | None = None           # sim time, ms
        self.newest_attitude_ms: int | None = None             # sim time, ms
        self.new_setpoints: deque = deque()                  # (sim ms, wall s)
        self.flying_mode = False       # the firmware's mode flies the bridge's setpoints
        self.armed: bool | None = None  # the firmware's HEARTBEAT (None: none seen yet)
        self._held: list = []          # the firmware's datagrams held to the next poll
        self.forwarded = {'to_firmware': 0, 'to_bridge': 0, 'unparsed': 0}
        self.timesync_unanswered = 0
        self._sim_ms: float | None = None      # sim time of the poll passing bridge datagrams
        self._timesync_sent: dict = {}          # ts1 of a request passed on -> sim ms then
        self.offset_samples_ms: deque = deque(maxlen=OFFSET_SAMPLES)
        self._timesync_asked = self._timesync_answered = False

    @property
    def local_port(self) -> int:
        """Return the UDP port the bridge's side listens on."""
        return self._bridge.getsockname()[1]

    @property
    def last_setpoint_time_boot_ms(self) -> int | None:
        """Return the newest frame (sim ms) the bridge's setpoints answer (see the tolerance)."""
        if self.last_setpoint_sim_ms is None:
            return None
        return self.last_setpoint_sim_ms + STAMP_TOLERANCE_MS

    @property
    def last_attitude_ms(self) -> int | None:
        """Return the sim ms imu/data must reach before a frame's images (see the tolerance)."""
        if self.newest_attitude_ms is None:
            return None
        return self.newest_attitude_ms - IMU_TOLERANCE_MS

    @property
    def awaits_setpoints(self) -> bool:
        """Whether the graph's setpoints fly the vehicle: PX4 in OFFBOARD, a flying mode.

        Before the mission PX4 flies its own hold, and its telemetry (heartbeat included)
        runs on sim time: waiting for setpoints then would wait for a bridge that has not
        yet heard the firmware. After the landing (SHUTDOWN) PX4 stays in OFFBOARD until its
        land detector lets the bridge disarm it, and no frame is answered any more.
        ``graph_flies`` (set by the sim: the supervisor's latest mode is WINDOW, CROSSING or
        LANDING) says which. Otherwise the lockstep waits for the graph's products only, as
        with the emulated autopilot once it flies a mode of its own.
        """
        return self.flying_mode and self.graph_flies()

    def poll(self, state: Any = None, receive: bool = True, telemetry: bool = True) -> None:
        """Pass on every datagram waiting on either side (the arguments: the autopilot's API).

        The firmware's datagrams go on even without ``receive`` (the firmware made them at
        its time, before the delivery the sim is at); the bridge's only with ``receive``, as
        the emulated autopilot reads them.
        """
        held, self._held = self._held, []
        for data, peer in held:
            self._on_firmware(data, peer)
        self._pump(self._firmware, self._on_firmware)
        if receive:
            self._timesync_asked = False
            self._sim_ms = None if state is None else 1e3 * float(state.t)
            self._pump(self._bridge, self._on_bridge)
            if self._timesync_asked and not self.port.timesync_in_lockstep:
                self._await_timesync_answer()

    def pass_timesync(self) -> None:
        """Between deliveries, at each physics step: pass on a TIMESYNC answer at once.

        A firmware that answers TIMESYNC only as its clock steps (ArduPilot) answers while
        the sim steps to the next delivery. Passed on then, the bridge reads it before the
        next /clock, so its round trip is within the step it took (the bridge's offset is
        off by that step, 2 ms, less than the stamp tolerance); passed on at the delivery it
        would be a frame period long, above the bridge's ``max_rtt_s``. The firmware's other
        datagrams are held for the next :meth:`poll`, in order: they are telemetry of times
        the graph's clock has not reached.

        The answer also sets the relay's ``boot_offset_ms``: its ``tc1`` less the sim time
        the request was passed on at, the median of the last :data:`OFFSET_SAMPLES`. That is
        the bridge's estimate from the same answers (it asked and heard at that /clock), so
        both map the firmware's times alike. ArduPilot's own stamp of a request lags the JSON
        clock by a few ms (5-7 ms measured); an offset assumed from the JSON clock put the
        bridge's setpoints 7 ms before their frames, at the edge of :data:`STAMP_TOLERANCE_MS`.
        """
        def take(data: bytes, peer) -> None:
            self._note_peer(peer)
            answers = [m for m in self._parse(mavlink.MAVLink(None), data)
                       if m.get_type() == 'TIMESYNC' and m.tc1 != 0]
            if not answers:
                self._held.append((data, peer))
                return
            self._forward_to_bridge(data)
            for m in answers:
                self._offset_sample(m)
        self._pump(self._firmware, take)

    def _offset_sample(self, answer: Any) -> None:
        """Take the firmware's clock offset (ms) from an answer to a request passed on."""
        sent_ms = self._timesync_sent.pop(int(answer.ts1), None)
        if sent_ms is None:
            return
        self.offset_samples_ms.append(int(answer.tc1) / 1e6 - sent_ms)
        self.boot_offset_ms = int(round(float(np.median(self.offset_samples_ms))))

    def _await_timesync_answer(self) -> None:
        """Pass on the firmware's answer to a TIMESYNC request before the sim steps on.

        The firmware stamps its answer with its clock when it reads the request; the bridge
        stamps the round trip with ROS time (/clock, the delivery's). Answered now, while the
        sim stands at the delivery, both read the same instant and the bridge's offset is
        exact; answered while the sim steps to the next delivery, it would be off by up to a
        frame period, more than the lockstep's stamp matching allows.
        """
        self._firmware.settimeout(TIMESYNC_ANSWER_WAIT_S)
        self._timesync_answered = False
        try:
            while not self._timesync_answered:
                try:
                    data, peer = self._firmware.recvfrom(MAX_DATAGRAM)
                except (socket.timeout, OSError):
                    self.timesync_unanswered += 1
                    return
                self._on_firmware(data, peer)
        finally:
            self._firmware.setblocking(False)

    def discard_firmware(self) -> None:
        """Drop what the firmware sent so far (its pre-roll, before the sim's clock ran)."""
        self._pump(self._firmware, lambda data, peer: self._note_peer(peer))

    def _note_peer(self, peer) -> None:
        """Learn where a firmware that sends from a port of its own listens (ArduPilot)."""
        if self.port.send_port is None:
            self._firmware_to = peer

    def _pump(self, sock: socket.socket, handle) -> None:
        while True:
            try:
                data, peer = sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            handle(data, peer)

    def _on_bridge(self, data: bytes, peer) -> None:
        self._bridge_peer = peer
        if self._firmware_to is not None:
            self._firmware.sendto(data, self._firmware_to)
            self.forwarded['to_firmware'] += 1
        for m in self._parse(self._from_bridge, data):
            if m.get_type() == 'TIMESYNC' and m.tc1 == 0:
                self._timesync_asked = True
                if self.port.timesync_in_lockstep and self._sim_ms is not None:
                    self._timesync_sent[int(m.ts1)] = self._sim_ms
                    while len(self._timesync_sent) > 4 * OFFSET_SAMPLES:   # never answered
                        self._timesync_sent.pop(next(iter(self._timesync_sent)))
            if m.get_type() == 'SET_ATTITUDE_TARGET':
                t_ms = int(m.time_boot_ms) - self.boot_offset_ms
                if self.last_setpoint_sim_ms is None or t_ms > self.last_setpoint_sim_ms:
                    self.new_setpoints.append((t_ms, self.wall_clock()))
                self.last_setpoint_sim_ms = max(t_ms, self.last_setpoint_sim_ms or t_ms)

    def _forward_to_bridge(self, data: bytes) -> None:
        if self._bridge_peer is not None:
            self._bridge.sendto(data, self._bridge_peer)
            self.forwarded['to_bridge'] += 1

    def _on_firmware(self, data: bytes, peer) -> None:
        self._note_peer(peer)
        self._forward_to_bridge(data)
        for m in self._parse(self._from_firmware, data):
            kind = m.get_type()
            if kind == 'TIMESYNC' and m.tc1 != 0:
                self._timesync_answered = True
            if kind == 'HEARTBEAT' and m.autopilot == self.port.autopilot:
                self.flying_mode = self.port.flying(int(m.custom_mode))
                self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == ATTITUDE_MESSAGE:
                t_ms = int(m.time_boot_ms) - self.boot_offset_ms
                self.newest_attitude_ms = max(t_ms, self.newest_attitude_ms or t_ms)

    def _parse(self, parser: Any, data: bytes) -> list:
        try:
            return parser.parse_buffer(data) or []
        except mavlink.MAVError:
            self.forwarded['unparsed'] += 1
            return []

    def imu_fault_at(self, t: float) -> str:
        """Return '' : no injected IMU faults on a real firmware (its telemetry is its own)."""
        return ''

    def estimate_error(self, t: float) -> np.ndarray:
        """Return the identity: the firmware's own estimator flies, none is injected."""
        return np.eye(3)

    def close(self) -> None:
        """Close both sockets (idempotent)."""
        for s in (self._bridge, self._firmware):
            try:
                s.close()
            except OSError:
                pass
