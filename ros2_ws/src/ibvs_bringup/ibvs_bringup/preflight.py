"""Preflight: wait until the graph is healthy, print a checklist, exit 0 (ready) or 1.

Checks: camera_info valid on both cameras, imu/data flowing, MAVLink link up in /diagnostics
(a status of the bridge with 'mavlink' in its name at level OK), the bridge's clock synced with
the autopilot (TIMESYNC, ``clock_synced`` in its diagnostics, with the offset), image and IMU
stamps on one clock (both cameras' and the IMU's latest stamps each within
``STAMP_AGREEMENT_S`` of this node's ROS clock at their receipt, and of each other's such
offsets: a camera driver or an IMU mapping on another clock fails here, whatever the streams'
rates, e.g. the 10 Hz imu/data of a vehicle at rest), ibvs/mode present, window detected
(4 corners on window/corners), and the perception keeping up with the front camera
(``KeepUp``: of the last ``KEEP_UP_FRAMES`` front camera frames, at least
``KEEP_UP_MIN_ANSWERED`` answered on window/corners, median ``KEEP_UP_MAX_DELAY_S`` at most
after the frame arrived, on the ROS clock: a computer that cannot keep up with 50 Hz, or a
detector that is not running, fails here), and each camera's timing (``CameraTiming``: its
frame rate from the stamps within ``RATE_TOLERANCE`` of vehicle.yaml's ``rate_hz``, and its
delivery latency, stamp to arrival, median at most ``MAX_DELIVERY_S``: a driver that stamps
at the end of the transfer, or a latency the frame deadlines cannot cover, fails here).
``GraphHealth`` can also be attached to another node
(``run_scenario`` does) so that the same checks gate a scripted run.
"""
from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass
import sys
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PolygonStamped
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Imu
from std_msgs.msg import UInt8

from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.config import load_vehicle
from ibvs_common.core.stamps import NS_PER_S, s_to_ns, stamp_to_ns

IMU_MIN_MESSAGES = 10
IMU_MAX_AGE_S = 1.0
STAMP_AGREEMENT_S = 0.1       # s, latest image and IMU stamps vs each other and the ROS clock
KEEP_UP_FRAMES = 50           # front camera frames the keep-up check looks at (1 s at 50 Hz)
KEEP_UP_MIN_FRAMES = 25       # fewer judged frames than this: not judged yet
KEEP_UP_MIN_ANSWERED = 0.95   # fraction of them whose window/corners arrived
KEEP_UP_MAX_DELAY_S = 0.020   # s (ROS clock), median frame arrival -> window/corners arrival:
#                               one frame period, the detector keeps up with 50 Hz
KEEP_UP_GRACE_S = 0.25        # s (ROS clock), frames that arrived less than this ago are not
#                               judged yet (the bridge's max_force_age_s: later is no use)
CAMERA_TIMING_FRAMES = 50     # frames each camera's timing is judged on
RATE_TOLERANCE = 0.1          # measured frame rate within 10 % of vehicle.yaml's rate_hz
MAX_DELIVERY_S = 0.1          # s, median stamp -> arrival (a USB / MIPI camera: 20-40 ms)
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@dataclass(frozen=True)
class Check:
    """One line of the checklist."""

    name: str
    ok: bool
    detail: str


def camera_info_problem(msg: CameraInfo) -> str | None:
    """Return what is wrong with a CameraInfo, or None if usable."""
    if msg.width <= 0 or msg.height <= 0:
        return f'image size {msg.width}x{msg.height}'
    k = list(msg.k)
    if len(k) != 9 or k[0] <= 0 or k[4] <= 0 or not (0 < k[2] < msg.width) \
            or not (0 < k[5] < msg.height):
        return f'bad K {k}'
    if msg.distortion_model not in ('plumb_bob', 'equidistant', 'rational_polynomial', ''):
        return f'unknown distortion model {msg.distortion_model!r}'
    return None


def armed_state(msg: DiagnosticArray) -> bool | None:
    """Return the vehicle's armed flag reported by the bridge ('armed' key), None if absent."""
    for s in msg.status:
        if 'mavlink' in s.name.lower():
            for kv in s.values:
                if kv.key.lower() == 'armed':
                    return kv.value.strip().lower() in ('true', '1', 'yes')
    return None


def diag_value(msg: DiagnosticArray, key: str) -> str | None:
    """Return the value of ``key`` in the bridge's MAVLink status of a DiagnosticArray."""
    for s in msg.status:
        if 'mavlink' in s.name.lower():
            for kv in s.values:
                if kv.key == key:
                    return kv.value
    return None


def stamps_agree(stamps: dict, tolerance_s: float = STAMP_AGREEMENT_S) -> tuple[bool, str]:
    """Whether the latest stamps are on the ROS clock: name -> (stamp ns, ROS ns at receipt).

    Each stream's stamp minus the ROS time of its receipt (its delay, negative for a stamp in
    the receiver's future) within ``tolerance_s``, and those offsets within ``tolerance_s`` of
    each other. Comparing each stamp with its own receipt, not with the time of the check, is
    what makes the check independent of the streams' rates (None: no message yet).
    """
    missing = [n for n, v in stamps.items() if v is None]
    if missing:
        return False, 'no stamp yet from ' + ', '.join(missing)
    tol = s_to_ns(tolerance_s)
    offsets = {n: stamp - receipt for n, (stamp, receipt) in stamps.items()}
    detail = ', '.join(f'{n} {dt / NS_PER_S * 1e3:+.0f} ms' for n, dt in offsets.items()) \
        + ' vs ROS time at receipt'
    values = list(offsets.values()) + [0]
    return max(values) - min(values) <= tol, detail


class KeepUp:
    """Does a product answer its camera's frames, and how long after they arrived? ROS-free.

    ``note_frame`` takes each frame's stamp and when it arrived (camera_info: a driver
    publishes it with every image, same stamp), ``note_answer`` the stamp of each product and
    when it arrived; times in ns on one clock (the ROS clock: system time onboard). The delay is
    counted from the frame's arrival, not from its stamp: a camera's own latency (exposure,
    transfer, a simulator's rendering) is not the graph's, and the stamps' clock is checked
    apart (``stamps_agree``). Frames younger than ``grace_s`` are not judged.
    """

    def __init__(self, frames: int = KEEP_UP_FRAMES, grace_s: float = KEEP_UP_GRACE_S) -> None:
        self._frames: collections.deque = collections.deque(maxlen=frames)   # (stamp, arrival)
        self._answers: dict[int, int] = {}            # product stamp -> its arrival (ns)
        self._grace_ns = s_to_ns(grace_s)
        self._backsteps = BackstepWatch()

    def note_frame(self, stamp_ns: int, received_ns: int) -> None:
        """Take one frame; a stamp not newer than the newest one is ignored.

        A clock step back (``clock_step.BackstepWatch``) starts the frames and answers again.
        """
        if self._backsteps.observe(stamp_ns):         # the clock stepped back: start again
            self._frames.clear()
            self._answers.clear()
        if not self._frames or stamp_ns > self._frames[-1][0]:
            self._frames.append((stamp_ns, received_ns))
        oldest = self._frames[0][0]
        for stamp in [t for t in self._answers if t < oldest]:
            del self._answers[stamp]

    def note_answer(self, stamp_ns: int, received_ns: int) -> None:
        """Take one product of the frame stamped ``stamp_ns``, arrived at ``received_ns``."""
        self._answers.setdefault(stamp_ns, received_ns)

    def check(self, now_ns: int, min_frames: int = KEEP_UP_MIN_FRAMES,
              min_answered: float = KEEP_UP_MIN_ANSWERED,
              max_delay_s: float = KEEP_UP_MAX_DELAY_S) -> tuple[bool, str]:
        """Return (ok, detail) over the frames that arrived at least ``grace_s`` ago."""
        judged = [(t, rx) for t, rx in self._frames if rx <= now_ns - self._grace_ns]
        if len(judged) < min_frames:
            return False, f'{len(judged)} frames to judge yet (needs {min_frames})'
        delays = sorted(self._answers[t] - rx for t, rx in judged if t in self._answers)
        detail = f'{len(delays)} / {len(judged)} frames answered'
        if not delays:
            return False, detail
        median_s = delays[len(delays) // 2] / NS_PER_S
        detail += f', median {median_s * 1e3:.1f} ms after the frame arrived'
        return len(delays) / len(judged) >= min_answered and median_s <= max_delay_s, detail


class CameraTiming:
    """A camera's frame rate (from its stamps) and delivery latency (stamp to arrival). ROS-free.

    ``note`` takes each frame's stamp and its arrival (ns, ROS clock); ``check`` compares the
    median stamp interval with the rate the graph was configured for (vehicle.yaml), and the
    median delivery with ``MAX_DELIVERY_S``.
    """

    def __init__(self, frames: int = CAMERA_TIMING_FRAMES) -> None:
        self._frames: collections.deque = collections.deque(maxlen=frames)

    def note(self, stamp_ns: int, received_ns: int) -> None:
        """Take one frame (a stamp not newer than the last one starts again)."""
        if self._frames and stamp_ns <= self._frames[-1][0]:
            self._frames.clear()
        self._frames.append((int(stamp_ns), int(received_ns)))

    def check(self, rate_hz: float, min_frames: int = KEEP_UP_MIN_FRAMES,
              tolerance: float = RATE_TOLERANCE,
              max_delivery_s: float = MAX_DELIVERY_S) -> tuple[bool, str]:
        """Return (ok, detail): the measured rate and delivery latency against the limits."""
        if len(self._frames) < min_frames:
            return False, f'{len(self._frames)} frames yet (needs {min_frames})'
        stamps = [s for s, _ in self._frames]
        period = sorted(b - a for a, b in zip(stamps, stamps[1:]))[len(stamps) // 2 - 1]
        measured = NS_PER_S / period
        delivery = sorted(rx - s for s, rx in self._frames)
        median, p95 = delivery[len(delivery) // 2], delivery[int(0.95 * (len(delivery) - 1))]
        detail = (f'{measured:.1f} Hz (vehicle.yaml {rate_hz:g} Hz), delivered '
                  f'{median / 1e6:.1f} ms after the stamp (p95 {p95 / 1e6:.1f} ms)')
        # a stamp a little ahead of the receiver's clock (a simulator's /clock, which arrives
        # after its images) is within the clocks' agreement, checked by stamps_agree
        ok = abs(measured - rate_hz) <= tolerance * rate_hz \
            and -s_to_ns(STAMP_AGREEMENT_S) <= median <= s_to_ns(max_delivery_s)
        return ok, detail


def link_up(msg: DiagnosticArray) -> bool | None:
    """Return the MAVLink link state reported in a DiagnosticArray (None if not reported)."""
    states = [s.level == DiagnosticStatus.OK for s in msg.status if 'mavlink' in s.name.lower()]
    return all(states) if states else None


class GraphHealth:
    """Subscriptions that watch the graph's vital signs on a given node."""

    def __init__(self, node: Node, clock: Callable[[], float] = time.monotonic,
                 rates_hz: dict | None = None) -> None:
        self.clock = clock
        self.node = node
        self.rates_hz = rates_hz or {cam: c.rate_hz for cam, c in load_vehicle().cameras.items()}
        self.camera_timing = {cam: CameraTiming() for cam in ('front', 'down')}
        self.stamps: dict = {'front camera': None, 'down camera': None, 'imu': None}
        self.clock_synced: str | None = None
        self.clock_offset_ms: str | None = None
        self.camera_info: dict = {'front': None, 'down': None}
        self.imu_count = 0
        self.imu_last = None
        self.link: bool | None = None
        self.armed: bool | None = None
        self.mode: int | None = None
        self.window_corners = 0
        self.front_keep_up = KeepUp()
        # read by the checklist only (stop_preflight_only drops them once it has passed)
        self._preflight_only = [
            node.create_subscription(CameraInfo, f'{cam}_camera/camera_info',
                                     lambda m, c=cam: self._on_info(c, m), BEST_EFFORT)
            for cam in self.camera_info]
        self._preflight_only += [
            node.create_subscription(Imu, 'imu/data', self._on_imu, BEST_EFFORT),
            node.create_subscription(PolygonStamped, 'window/corners', self._on_window,
                                     BEST_EFFORT)]
        self.subs = self._preflight_only + [
            node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag,
                                     BEST_EFFORT),
            node.create_subscription(UInt8, 'ibvs/mode', self._on_mode, LATCHED)]

    def stop_preflight_only(self) -> None:
        """Drop the subscriptions only the checklist reads (camera_info, imu/data, window).

        After the preflight a run reads only the link's state (``armed``) and the mode: the
        camera_info, IMU and window streams (250 messages/s at 50 Hz frames) would cost the
        watching process a share of the CPU the graph runs on. The checklist then reports
        their last state.
        """
        for sub in self._preflight_only:
            self.node.destroy_subscription(sub)
        self.subs = [sub for sub in self.subs if sub not in self._preflight_only]
        self._preflight_only = []

    def _on_info(self, cam: str, msg: CameraInfo) -> None:
        self.camera_info[cam] = camera_info_problem(msg) or 'ok'
        stamp, now = stamp_to_ns(msg.header.stamp), self._ros_ns()
        self.stamps[f'{cam} camera'] = (stamp, now)
        self.camera_timing[cam].note(stamp, now)
        if cam == 'front':
            self.front_keep_up.note_frame(stamp, now)

    def _on_imu(self, msg: Imu) -> None:
        self.imu_count += 1
        self.imu_last = self.clock()
        self.stamps['imu'] = (stamp_to_ns(msg.header.stamp), self._ros_ns())

    def _ros_ns(self) -> int:
        """Return the watching node's ROS clock now (ns): receipts, keep-up, stamp agreement."""
        return self.node.get_clock().now().nanoseconds

    def _on_diag(self, msg: DiagnosticArray) -> None:
        synced = diag_value(msg, 'clock_synced')
        if synced is not None:
            self.clock_synced = synced
            self.clock_offset_ms = diag_value(msg, 'clock_offset_ms')
        state, armed = link_up(msg), armed_state(msg)
        if state is not None:
            self.link = state
        if armed is not None:
            self.armed = armed

    def _on_mode(self, msg: UInt8) -> None:
        self.mode = int(msg.data)

    def _on_window(self, msg: PolygonStamped) -> None:
        self.window_corners = len(msg.polygon.points)
        self.front_keep_up.note_answer(stamp_to_ns(msg.header.stamp), self._ros_ns())

    def checklist(self) -> list[Check]:
        """Return the current checklist."""
        checks = [Check(f'{cam} camera_info valid', state == 'ok', state or 'not received')
                  for cam, state in self.camera_info.items()]
        age = None if self.imu_last is None else self.clock() - self.imu_last
        imu_ok = self.imu_count >= IMU_MIN_MESSAGES and age is not None and age < IMU_MAX_AGE_S
        checks.append(Check('imu/data flowing', imu_ok,
                            f'{self.imu_count} messages' + (f', last {age:.2f} s ago'
                                                            if age is not None else '')))
        checks.append(Check('MAVLink link up (/diagnostics)', bool(self.link),
                            {None: 'not reported', True: 'OK', False: 'DOWN'}[self.link]))
        checks.append(Check('clock synced with the autopilot (TIMESYNC)',
                            self.clock_synced == 'yes',
                            'not reported' if self.clock_synced is None else
                            f'{self.clock_synced}, offset {self.clock_offset_ms} ms'))
        agree, detail = stamps_agree(self.stamps)
        checks.append(Check('image and IMU stamps on one clock', agree, detail))
        for cam, timing in self.camera_timing.items():
            ok, detail = timing.check(self.rates_hz[cam])
            checks.append(Check(f'{cam} camera rate and delivery latency', ok, detail))
        checks.append(Check('ibvs/mode present', self.mode is not None,
                            'not received' if self.mode is None else f'mode {self.mode}'))
        checks.append(Check('window detected', self.window_corners == 4,
                            f'{self.window_corners} corners'))
        keeps_up, detail = self.front_keep_up.check(self._ros_ns())
        checks.append(Check('perception keeps up (window/corners per front frame)', keeps_up,
                            detail))
        return checks

    def healthy(self) -> bool:
        """Return True if every check passes."""
        return all(c.ok for c in self.checklist())


def format_checklist(checks: list[Check]) -> str:
    """Return the checklist as text, one '[ OK ]' / '[FAIL]' line per check."""
    return '\n'.join(f'  [{" OK " if c.ok else "FAIL"}] {c.name}: {c.detail}' for c in checks)


def wait_healthy(node: Node, health: GraphHealth, timeout_s: float,
                 spin_once: Callable[[float], None] | None = None) -> bool:
    """Spin ``node`` until ``health`` is healthy or ``timeout_s`` (wall) passed."""
    spin = spin_once or (lambda t: rclpy.spin_once(node, timeout_sec=t))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if health.healthy():
            return True
        spin(0.05)
    return health.healthy()


def main(argv: list | None = None) -> int:
    """Wait for a healthy graph (``--timeout`` s), print the checklist, return 0 or 1."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--timeout', type=float, default=60.0, help='seconds (wall)')
    args, ros_args = parser.parse_known_args(argv)
    rclpy.init(args=ros_args)
    node = None
    ok = False
    try:
        node = rclpy.create_node('preflight')
        health = GraphHealth(node)
        ok = wait_healthy(node, health, args.timeout)
        print(('PREFLIGHT OK' if ok else f'PREFLIGHT FAILED after {args.timeout:.0f} s') +
              '\n' + format_checklist(health.checklist()), flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
