"""Preflight: wait until the graph is ready to fly, print a checklist and a go/no-go line.

Exit status 0 on go, 1 on no-go; the verdict is also published, latched, on ``ibvs/preflight``
(the supervisor refuses ``ibvs/start`` while it is no-go: its ``require_preflight_go``).

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
The preflight command adds the autopilot's set-up (``autopilot_setup``): its failsafe when
the bridge stops (``failsafe_setup``: PX4 ``COM_OBL_RC_ACT`` = 4, Land mode, and
``COM_OF_LOSS_T`` at most ``PX4_OFFBOARD_LOSS_T_MAX_S``; ArduPilot ``FS_GCS_ENABLE`` on and
``SYSID_MYGCS`` = the bridge's system id, as the bridge reads them, docs/mavlink.md
"Autopilot set-up") and whether the vehicle is armed or armable (``armability``: the
autopilot's pre-arm checks, reported by the bridge). With ``--check-pad`` (a bench with the
down camera over the pad) it also checks that the pad is in view (``PadInView``: the pad
detector's own code, on the down camera's images, a few a second); at the start of the
mission the pad is past the wall, out of the down camera's view, so by default that check is
listed as skipped. ``GraphHealth`` can also be attached to another node (``run_scenario``
does) so that the graph's checks gate a scripted run; the autopilot's set-up and the pad are
then listed as skipped.
"""
from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass
import math
import sys
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PolygonStamped
import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_msgs.msg import UInt8

from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_common.core.stamps import NS_PER_S, s_to_ns, stamp_to_ns
from ibvs_common.node_common import IMAGE_QOS, PREFLIGHT_TOPIC, preflight_verdict_msg
from ibvs_common.throttled_log import ThrottledLog
from ibvs_control.mavlink.params import (
    ARDUPILOT_TIMEOUT_MAX_S, GCS_FAILSAFE_PARAM, MY_GCS_PARAM, OFFBOARD_LOSS_ACT_PARAM,
    OFFBOARD_LOSS_T_PARAM, PX4_OFFBOARD_LOSS_ACTIONS, PX4_OFFBOARD_LOSS_LAND,
    PX4_OFFBOARD_LOSS_T_MAX_S, PX4_OFFBOARD_LOSS_WHY)

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
PAD_TRY_PERIOD_S = 0.2        # s (steady), one down image in this long is searched for the pad
PAD_TRIES = 10                # the last down images tried that the pad check looks at
PAD_MIN_SEEN = 0.8            # fraction of them with a complete marker group
VERDICT_ACK_S = 2.0           # s (wall), the verdict's wait for its subscribers' ack at the end
THROTTLE_S = 5.0
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@dataclass(frozen=True)
class Check:
    """One line of the checklist."""

    name: str
    ok: bool
    detail: str
    skipped: bool = False       # not checked here (``detail`` says why): neither go nor no-go


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
    median delivery with ``MAX_DELIVERY_S``; frames missing between the stamps are said, not
    judged (a free-running sim drops late frames by design; the supervisor's frame counts and
    stride on /diagnostics judge them in flight).
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
        expected = int(round((stamps[-1] - stamps[0]) / period)) + 1
        missing = expected - len(stamps)    # frames the camera did not deliver (said, not judged)
        detail = (f'{measured:.1f} Hz (vehicle.yaml {rate_hz:g} Hz), delivered '
                  f'{median / 1e6:.1f} ms after the stamp (p95 {p95 / 1e6:.1f} ms)'
                  + (f', {missing} of the last {expected} frames missing' if missing > 0 else ''))
        # a stamp a little ahead of the receiver's clock (a simulator's /clock, which arrives
        # after its images) is within the clocks' agreement, checked by stamps_agree
        ok = abs(measured - rate_hz) <= tolerance * rate_hz \
            and -s_to_ns(STAMP_AGREEMENT_S) <= median <= s_to_ns(max_delivery_s)
        return ok, detail


def bridge_values(msg: DiagnosticArray) -> dict | None:
    """Return the key -> value pairs of the bridge's MAVLink status (None if it has none)."""
    for s in msg.status:
        if 'mavlink' in s.name.lower():
            return {kv.key: kv.value for kv in s.values}
    return None


def _number(text: str | None) -> float | None:
    """Return a finite number from a diagnostics value, None if absent or not one."""
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def failsafe_setup(values: dict | None) -> tuple[bool, str]:
    """Whether the autopilot lands the vehicle when the bridge stops: (ok, detail).

    ``values``: the bridge's MAVLink status (``bridge_values``), which carries the failsafe
    parameters as the bridge read them. PX4: ``COM_OBL_RC_ACT`` = 4 (Land mode; the other
    actions need a position estimate or a pilot, or stop the motors) and ``COM_OF_LOSS_T`` at
    most ``PX4_OFFBOARD_LOSS_T_MAX_S`` (the vehicle flies the last setpoint that long).
    ArduPilot: ``FS_GCS_ENABLE`` not 0 and ``SYSID_MYGCS`` = the bridge's ``source_system``
    (its GCS failsafe then acts on the loss of our HEARTBEAT), and where reported
    ``GUID_TIMEOUT`` and ``FS_GCS_TIMEOUT`` at most ``ARDUPILOT_TIMEOUT_MAX_S`` (how long the
    vehicle flies the last target, then coasts, before LAND). docs/mavlink.md "Autopilot
    set-up". Not read yet, or another autopilot: not ok.
    """
    if values is None:
        return False, 'not reported (no MAVLink status of the bridge on /diagnostics)'
    autopilot = values.get('autopilot', 'unknown')
    if autopilot == 'px4':
        action = _number(values.get(OFFBOARD_LOSS_ACT_PARAM))
        timeout = _number(values.get(OFFBOARD_LOSS_T_PARAM))
        if action is None or timeout is None:
            return False, f'PX4 {OFFBOARD_LOSS_ACT_PARAM} / {OFFBOARD_LOSS_T_PARAM} not read yet'
        act = int(action)
        what = PX4_OFFBOARD_LOSS_ACTIONS.get(act, 'unknown action')
        said = (f'PX4 {OFFBOARD_LOSS_ACT_PARAM} = {act} ({what}), {OFFBOARD_LOSS_T_PARAM} = '
                f'{timeout:g} s')
        if act != PX4_OFFBOARD_LOSS_LAND:
            why = PX4_OFFBOARD_LOSS_WHY.get(act, 'is not an action of PX4 v1.16')
            return False, (f'{said}: {what} {why}; set {OFFBOARD_LOSS_ACT_PARAM} = '
                           f'{PX4_OFFBOARD_LOSS_LAND} (Land mode)')
        if timeout > PX4_OFFBOARD_LOSS_T_MAX_S:
            return False, (f'{said}: the vehicle would fly the last setpoint {timeout:g} s '
                           f'after ours stop; set {OFFBOARD_LOSS_T_PARAM} <= '
                           f'{PX4_OFFBOARD_LOSS_T_MAX_S:g} s')
        return True, f'{said}: PX4 lands when our setpoints stop'
    if autopilot == 'ardupilot':
        enabled = _number(values.get(GCS_FAILSAFE_PARAM))
        gcs = _number(values.get(MY_GCS_PARAM))
        ours = _number(values.get('source_system'))
        if enabled is None or gcs is None:
            return False, f'ArduPilot {GCS_FAILSAFE_PARAM} / {MY_GCS_PARAM} not read yet'
        if ours is None:
            return False, "the bridge's source_system is not reported"
        said = f'ArduPilot {GCS_FAILSAFE_PARAM} = {int(enabled)}, {MY_GCS_PARAM} = {int(gcs)}'
        if int(enabled) == 0:
            return False, (f'{said}: no GCS failsafe, a dead bridge leaves the vehicle '
                           f'hovering armed; set {GCS_FAILSAFE_PARAM} = 5 (land)')
        if int(gcs) != int(ours):
            return False, (f"{said}: not this bridge's system id {int(ours)}; set "
                           f'{MY_GCS_PARAM} = {int(ours)}')
        timing = {n: _number(values.get(n)) for n in ARDUPILOT_TIMEOUT_MAX_S}
        said += ''.join(f', {n} = {v:g} s' for n, v in timing.items() if v is not None)
        long = [f'{n} <= {ARDUPILOT_TIMEOUT_MAX_S[n]:g} s' for n, v in timing.items()
                if v is not None and v > ARDUPILOT_TIMEOUT_MAX_S[n]]
        if long:
            return False, (f'{said}: a dead bridge leaves the vehicle flying the last target, '
                           f'then coasting, that long; set {" and ".join(long)}')
        return True, f'{said} (this bridge): ArduPilot acts when our HEARTBEAT stops'
    return False, f'autopilot {autopilot}: its failsafe parameters are not known'


def armability(values: dict | None) -> tuple[bool, str]:
    """Whether the vehicle is armed, or armable (its pre-arm checks pass): (ok, detail)."""
    if values is None:
        return False, 'not reported (no MAVLink status of the bridge on /diagnostics)'
    if values.get('armed') == 'True':
        return True, 'armed'
    armable = values.get('armable')
    if armable == 'True':
        return True, "disarmed, armable (the autopilot's pre-arm checks pass)"
    if armable == 'False':
        reason = values.get('last_autopilot_reason', '')
        return False, ("disarmed and NOT armable: the autopilot's pre-arm checks fail"
                       + (f' (its last message: {reason})' if reason else '')
                       + "; PX4's follow its current mode: Altitude or Stabilized indoors")
    return False, 'armability not reported yet (SYS_STATUS)'


class PadInView:
    """Is the pad in view of the down camera: complete groups in the last images tried. ROS-free.

    ``note`` takes the groups found in one image (the pad detector's ``group_names``: empty
    when none is complete), ``note_error`` an image that could not be searched.
    """

    def __init__(self, tries: int = PAD_TRIES) -> None:
        self._tries: collections.deque = collections.deque(maxlen=tries)
        self.last_error = ''

    def note(self, groups: tuple) -> None:
        """Take the complete groups found in one image."""
        self._tries.append(tuple(groups))

    def note_error(self, why: str) -> None:
        """Take an image that could not be searched (``why``: the reason)."""
        self.last_error = why
        self._tries.append(())

    def check(self, min_tries: int = PAD_TRIES,
              min_seen: float = PAD_MIN_SEEN) -> tuple[bool, str]:
        """Return (ok, detail): a complete group in at least ``min_seen`` of the tries."""
        error = f'; last error: {self.last_error}' if self.last_error else ''
        if len(self._tries) < min_tries:
            return False, f'{len(self._tries)} down images tried yet (needs {min_tries}){error}'
        seen = [t for t in self._tries if t]
        groups = sorted({g for t in seen for g in t})
        detail = (f'complete groups in {len(seen)} of the last {len(self._tries)} down images'
                  + (f' ({", ".join(groups)})' if groups else '') + error)
        return len(seen) >= min_seen * len(self._tries), detail


def link_up(msg: DiagnosticArray) -> bool | None:
    """Return the MAVLink link state reported in a DiagnosticArray (None if not reported)."""
    states = [s.level == DiagnosticStatus.OK for s in msg.status if 'mavlink' in s.name.lower()]
    return all(states) if states else None


class GraphHealth:
    """Subscriptions that watch the graph's vital signs on a given node.

    ``autopilot_setup``: also check the autopilot's failsafe parameters and armability (the
    preflight command; a scripted run, whose harness plays the pilot, leaves them out).
    ``check_pad``: also search the down camera's images for the pad (a bench; the pad is not
    in view at a mission's start); ``pad_layout_file``: its layout ('' = installed).
    """

    def __init__(self, node: Node, clock: Callable[[], float] = time.monotonic,
                 rates_hz: dict | None = None, autopilot_setup: bool = False,
                 check_pad: bool = False, pad_layout_file: str = '') -> None:
        self.clock = clock
        self.node = node
        self.autopilot_setup = autopilot_setup
        self.check_pad = check_pad
        self.bridge: dict | None = None     # the bridge's latest MAVLink status values
        self.pad = PadInView()
        self._down_info: CameraInfo | None = None
        self._pad_detector = None
        self._pad_tried = -math.inf
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
        if check_pad:
            from ibvs_perception.core.pad import PadDetector, PadDetectorConfig
            self._pad_detector = PadDetector(load_pad_layout(pad_layout_file or None),
                                             PadDetectorConfig())
            self._log = ThrottledLog(node.get_logger())
            self._preflight_only.append(node.create_subscription(
                Image, 'down_camera/image_raw', self._on_down_image, IMAGE_QOS))
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
        if cam == 'down':
            self._down_info = msg
        stamp, now = stamp_to_ns(msg.header.stamp), self._ros_ns()
        self.stamps[f'{cam} camera'] = (stamp, now)
        self.camera_timing[cam].note(stamp, now)
        if cam == 'front':
            self.front_keep_up.note_frame(stamp, now)

    def _on_down_image(self, msg: Image) -> None:
        """Search one down image for the pad, at most every ``PAD_TRY_PERIOD_S``."""
        from ibvs_perception.messages import camera_from_info, mono8_from_image
        now = self.clock()
        if now - self._pad_tried < PAD_TRY_PERIOD_S:
            return
        self._pad_tried = now
        try:
            camera = camera_from_info(self._down_info, msg)
            detection = self._pad_detector.process(mono8_from_image(msg), camera,
                                                   stamp_to_ns(msg.header.stamp) / NS_PER_S)
        except ValueError as exc:
            self._log.error(f'preflight: down image not searched for the pad: {exc}',
                            THROTTLE_S)
            self.pad.note_error(str(exc))
            return
        self.pad.note(detection.group_names)

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
        values = bridge_values(msg)
        if values is not None:
            self.bridge = values
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
        pad = 'pad in view of the down camera'
        if self.check_pad:
            checks.append(Check(pad, *self.pad.check()))
        else:
            checks.append(Check(pad, False, 'not checked: out of view at the start (the pad is '
                                'past the wall); --check-pad on a bench', skipped=True))
        setup = (('autopilot failsafe when the bridge stops', failsafe_setup),
                 ('armed or armable', armability))
        for name, judge in setup:
            if self.autopilot_setup:
                checks.append(Check(name, *judge(self.bridge)))
            else:
                checks.append(Check(name, False, "not checked here (the preflight command "
                                    'checks it)', skipped=True))
        return checks

    def healthy(self) -> bool:
        """Return True if every check passes (or is skipped)."""
        return go(self.checklist())


def go(checks: list[Check]) -> bool:
    """Return True if every check passes or is skipped: the go."""
    return all(c.ok or c.skipped for c in checks)


def _state(c: Check) -> str:
    return 'SKIP' if c.skipped else 'OK' if c.ok else 'FAIL'


def summary_line(checks: list[Check]) -> str:
    """Return the one go / no-go line: 'PREFLIGHT GO: ...' or 'PREFLIGHT NO-GO: ...'."""
    judged = [c for c in checks if not c.skipped]
    skipped = [c.name for c in checks if c.skipped]
    failed = [c.name for c in judged if not c.ok]
    if failed:
        return (f'PREFLIGHT NO-GO: {len(failed)} of {len(judged)} checks failed: '
                + '; '.join(failed))
    return (f'PREFLIGHT GO: {len(judged)} checks passed'
            + (f', {len(skipped)} skipped ({"; ".join(skipped)})' if skipped else ''))


def verdict_msg(checks: list[Check], stamp_ns: int) -> DiagnosticArray:
    """Return the ibvs/preflight message of a checklist (go, the summary line, each check)."""
    return preflight_verdict_msg(go(checks), summary_line(checks),
                                 [(c.name, f'{_state(c)}: {c.detail}') for c in checks],
                                 stamp_ns)


def format_checklist(checks: list[Check]) -> str:
    """Return the checklist as text, one '[ OK ]' / '[FAIL]' line per check."""
    return '\n'.join(f'  [{_state(c).center(4)}] {c.name}: {c.detail}' for c in checks)


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
    """Wait for a go (``--timeout`` s); print the checklist and the go/no-go line; 0 or 1.

    The verdict is published, latched, on ``ibvs/preflight`` (the supervisor reads it).
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--timeout', type=float, default=60.0,
                        help='seconds (wall) to wait for a go, then no-go')
    parser.add_argument('--check-pad', action='store_true',
                        help='also check that the down camera sees the pad (a bench: at the '
                             "mission's start the pad is past the wall, out of view)")
    parser.add_argument('--pad-layout', default='',
                        help="pad layout YAML for --check-pad ('' = the installed one)")
    args, ros_args = parser.parse_known_args(argv)
    rclpy.init(args=ros_args)
    node = None
    ok = False
    try:
        node = rclpy.create_node('preflight')
        verdict = node.create_publisher(DiagnosticArray, PREFLIGHT_TOPIC, LATCHED)
        health = GraphHealth(node, autopilot_setup=True, check_pad=args.check_pad,
                             pad_layout_file=args.pad_layout)
        wait_healthy(node, health, args.timeout)
        checks = health.checklist()
        ok = go(checks)
        print(format_checklist(checks) + '\n' + summary_line(checks)
              + ('' if ok else f' (after {args.timeout:.0f} s)'), flush=True)
        # a subscriber (the supervisor) not yet matched would miss a verdict published now,
        # and the latched copy ends with this process: wait for one first (bounded)
        deadline = time.monotonic() + VERDICT_ACK_S
        while verdict.get_subscription_count() == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        verdict.publish(verdict_msg(checks, node.get_clock().now().nanoseconds))
        verdict.wait_for_all_acked(Duration(seconds=VERDICT_ACK_S))   # the supervisor has it
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
