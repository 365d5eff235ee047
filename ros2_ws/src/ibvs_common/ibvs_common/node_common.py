"""Message <-> numpy helpers and QoS profiles shared by the nodes of every IBVS package.

Only conversions of message fields (frames.py does the frame conversions, no maths),
:class:`DeadlineTimer`, the one-shot ROS-clock timer of the timing layer's frame deadlines, and
:class:`LateImuReport`, the nodes' warning about IMU samples that came after their image.
"""
from __future__ import annotations

import math
from typing import Iterable, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Header

from ibvs_common.core.stamps import NS_PER_S, stamp_to_ns

if TYPE_CHECKING:
    from builtin_interfaces.msg import Time
    from ibvs_common.core.attitude_buffer import AttitudeBuffer
    from ibvs_common.throttled_log import ThrottledLog
    from geometry_msgs.msg import PolygonStamped, Quaternion, Vector3

MIN_TIMER_NS = 100_000          # a deadline already due fires on the next spin

# ibvs/mode: latched state (the last mode reaches late joiners).
MODE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      history=HistoryPolicy.KEEP_LAST)
# Detections, flows, IMU: best effort (accepts any publisher), a few kept.
SENSOR_QOS = qos_profile_sensor_data
# Camera images: best effort, 4 kept. A node that falls behind skips the queued images a newer
# one has superseded (ibvs_perception.core.latest_only, at a cost of microseconds each) and
# computes the newest, so the queue bounds nothing but memory: deep enough that a grid frame
# of a frame stride of 2 survives 60 ms of a busy executor behind the off-grid one after it
# (with 2 kept, a grid frame was overwritten by two off-grid ones while the node computed
# another camera's frame: grid frames missed about as often as computed at a slow hour).
# Not 1: frame 0 of the lockstep sim is answered by the bridge's pre-force stream
# (time_boot_ms 0), so frame 1 can follow at once, and a detector busy with frame 0 lost one
# of the two (two 5 s harness time-outs at start-up in one run of six).
IMAGE_QOS = QoSProfile(depth=4, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
# Publishers of setpoints, statuses and features, imu/data, commands: reliable, 10 kept for
# every reader (recorders, tools); the flight-path nodes subscribe with FRAME_QOS below.
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)
# One message per camera frame between the flight-path nodes (supervisor status, force and
# heading setpoints: FRAME_QOS; the perception products as subscribed by the supervisor and
# controller: PRODUCT_QOS, best effort as sensor data): keep last 2. A node
# that falls behind takes the newest frame and at most one queued behind it, never a backlog:
# with depth 5 / 10 a saturated computer queued 150-190 ms at the supervisor and 0.84-0.96 s
# at the bridge (docs/journal/performance.md). Not 1, for the reason given at IMAGE_QOS:
# in lockstep a consumer may still hold frame k's message when frame k+1's arrives. (Images
# keep 4: a node skips the superseded ones itself.)
FRAME_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
PRODUCT_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)


def ns_to_stamp(ns: int, stamp: Time) -> None:
    """Write integer nanoseconds into a builtin_interfaces/Time (in place)."""
    stamp.sec, stamp.nanosec = divmod(int(ns), NS_PER_S)


def imu_attitude(msg: Imu) -> tuple[int, tuple, np.ndarray]:
    """sensor_msgs/Imu -> (stamp ns, q_map_base (w, x, y, z), Omega_B FRD in rad/s), checked.

    For :meth:`AttitudeBuffer.add_map_base`, which turns the quaternion into R_IB only when a
    query reads the sample. Raises ValueError for NaN/Inf or a quaternion that is not unit
    within 10 %.
    """
    o, av = msg.orientation, msg.angular_velocity
    q = (o.w, o.x, o.y, o.z)
    if not math.isfinite(o.w + o.x + o.y + o.z + av.x + av.y + av.z):
        raise ValueError('IMU message holds NaN or Inf')
    norm = math.sqrt(o.w * o.w + o.x * o.x + o.y * o.y + o.z * o.z)
    if abs(norm - 1.0) > 0.1:
        raise ValueError(f'IMU orientation is not a unit quaternion (|q| = {norm:.3f})')
    # base_link FLU -> body FRD: y and z change sign (frames.R_FRD_FLU)
    return stamp_to_ns(msg.header.stamp), q, np.array((av.x, -av.y, -av.z))


class DeadlineTimer:
    """One-shot timer on the node's ROS clock for the earliest pending frame deadline.

    :meth:`arm` (re)schedules it for a deadline (ROS time, ns); an earlier deadline replaces
    a later one, a later one is ignored while armed. When the ROS clock reaches the deadline
    the callback runs once. Under ``use_sim_time`` it fires on /clock: in lockstep, where the
    clock stands still while the graph computes, it cannot fire before an input that is
    coming. Nodes also check deadlines on every arrival; this covers inputs that stop.
    """

    def __init__(self, node: Node, callback) -> None:
        self._node = node
        self._callback = callback
        self._timer = None
        self.deadline_ns: int | None = None

    def arm(self, deadline_ns: int | None) -> None:
        """Fire at ``deadline_ns`` (None: nothing pending, cancel)."""
        if deadline_ns is None:
            self._cancel()
            return
        if self._timer is not None and self.deadline_ns <= deadline_ns:
            return
        self._cancel()
        now_ns = self._node.get_clock().now().nanoseconds
        period_s = max(int(deadline_ns) - now_ns, MIN_TIMER_NS) / NS_PER_S
        self.deadline_ns = int(deadline_ns)
        self._timer = self._node.create_timer(period_s, self._fire)

    def _cancel(self) -> None:
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
        self._timer, self.deadline_ns = None, None

    def _fire(self) -> None:
        self._cancel()
        self._callback()


class LateImuReport:
    """Warn (throttled) when imu/data samples reach a node after an image that needed them.

    Such an image was answered with an attitude propagated beyond the newest sample (never
    held back: docs/design.md, "Time"), and the sample of its moment came afterwards
    (:attr:`AttitudeBuffer.late_samples`). Onboard: the IMU path is slower than the camera's.
    In a lockstep sim: the run's attitudes depended on delivery order, so it need not repeat
    another bit for bit (tests/integration/test_bringup_whole_graph.py reads these lines).
    """

    TEXT = 'came after an image that needed it'     # what the tests look for

    def __init__(self, log: ThrottledLog, period_s: float, prefix: str = '') -> None:
        self._log, self._period_s, self._prefix = log, float(period_s), prefix
        self._reported = 0

    def check(self, buffer: AttitudeBuffer) -> None:
        """Warn if ``buffer`` counted late samples since the last warning that went out."""
        n = buffer.late_samples
        if n == self._reported or buffer.last_late is None:
            return
        sample_s, image_s = buffer.last_late
        if self._log.warning(
                f'{self._prefix}imu/data sample of t = {sample_s:.3f} s {self.TEXT} (image of '
                f't = {image_s:.3f} s, answered with a propagated attitude: the IMU is later '
                f'than the camera); {n} late sample(s) in all', self._period_s,
                key='late_imu'):
            self._reported = n


def polygon_points(msg: PolygonStamped) -> np.ndarray:
    """geometry_msgs/PolygonStamped -> (N, 3) array."""
    return np.array([[p.x, p.y, p.z] for p in msg.polygon.points], dtype=float).reshape(-1, 3)


def vector3(v: Vector3) -> np.ndarray:
    """geometry_msgs/Vector3 -> (3,) array."""
    return np.array([v.x, v.y, v.z], dtype=float)


def quat_wxyz(q: Quaternion) -> np.ndarray:
    """geometry_msgs/Quaternion (x, y, z, w fields) -> (w, x, y, z) array."""
    return np.array([q.w, q.x, q.y, q.z], dtype=float)


def set_quat(q_msg: Quaternion, q_wxyz: np.ndarray) -> None:
    """Write a (w, x, y, z) quaternion into a geometry_msgs/Quaternion (in place)."""
    q_msg.w, q_msg.x, q_msg.y, q_msg.z = (float(x) for x in q_wxyz)


def set_vector3(v_msg: Vector3, v: np.ndarray) -> None:
    """Write a 3-vector into a geometry_msgs/Vector3 (in place)."""
    v_msg.x, v_msg.y, v_msg.z = (float(x) for x in v)


# pad/groups (sensor_msgs/JointState): the stamp and frame of its pad/landmarks (the image's)
# and the names of the groups whose landmarks pad/landmarks carries, in the same order; the
# value arrays are empty. Stamped, so that a subscriber pairs the two by stamp: two topics are
# not ordered with respect to each other (an executor that fell behind takes the next
# landmarks before the last groups).
def pad_groups_msg(stamp: Time, frame_id: str, groups: Iterable[str],
                   weights: Iterable[float] = ()) -> JointState:
    """Build the ``pad/groups`` message of one image (``stamp``: builtin_interfaces/Time).

    ``name``: the groups in the order of the landmarks; ``position``: each group's weight in
    the pad feature (the pad detector's group_weight), or empty.
    """
    msg = JointState(name=[str(g) for g in groups], position=[float(w) for w in weights])
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    return msg


def pad_group_names(msg: JointState) -> tuple[str, ...]:
    """Group names of a ``pad/groups`` message, in the order of the landmarks."""
    return tuple(str(g) for g in msg.name)


def pad_group_weights(msg: JointState) -> tuple[float, ...] | None:
    """Group weights of a ``pad/groups`` message, or None (equal weights then).

    None when it has none (an older bag) or bad ones (not one finite value >= 0 per group, or
    all 0).
    """
    w = [float(x) for x in msg.position]
    if len(w) != len(msg.name) or not w or not all(math.isfinite(x) and x >= 0.0 for x in w) \
            or not any(x > 0.0 for x in w):
        return None
    return tuple(w)


# ibvs/supervisor_status (diagnostic_msgs/DiagnosticArray): one per frame the supervisor
# evaluated, stamped with the frame's stamp; status[0] names the node, its message is the mode
# name and its values carry the mode number under STATUS_MODE_KEY (the controller flies that
# mode for that frame) and, for a frame of a camera, the camera under STATUS_CAMERA_KEY
# ('front' or 'down'; absent when the status is of a time, not of a frame).
STATUS_NAME = 'mode_supervisor'
STATUS_MODE_KEY = 'mode'
STATUS_CAMERA_KEY = 'camera'
# '<product>_from_ns' (e.g. 'flow_front_from_ns'): the frame took that product from the earlier
# frame of this stamp (ns), not its own (the rate governor sheds the flows); absent: its own.
STATUS_HELD_SUFFIX = '_from_ns'


def held_key(product: str) -> str:
    """Return the supervisor status key of a product held from an earlier frame."""
    return f'{product}{STATUS_HELD_SUFFIX}'


def held_from_status(msg: DiagnosticArray) -> tuple[dict, str]:
    """Return ({product name: source stamp ns} of an ibvs/supervisor_status, '' or an error)."""
    out = {}
    for status in msg.status:
        if status.name != STATUS_NAME:
            continue
        for kv in status.values:
            if kv.key.endswith(STATUS_HELD_SUFFIX):
                value = kv.value.lstrip('-')
                if not value.isdigit():
                    return {}, f'{kv.key} value {kv.value!r} is not an integer'
                out[kv.key[:-len(STATUS_HELD_SUFFIX)]] = int(kv.value)
    return out, ''


def supervisor_status_msg(stamp_ns: int, mode: int, mode_name: str, level: bytes,
                          values: dict, camera: str | None = None) -> DiagnosticArray:
    """Build the ibvs/supervisor_status message of one evaluated frame (level: OK, WARN...).

    ``camera``: the camera whose frame was evaluated (None: a status of a time).
    """
    head = [KeyValue(key=STATUS_MODE_KEY, value=str(int(mode)))]
    if camera is not None:
        head.append(KeyValue(key=STATUS_CAMERA_KEY, value=str(camera)))
    status = DiagnosticStatus(level=level, name=STATUS_NAME, message=mode_name,
                              values=head
                              + [KeyValue(key=k, value=str(v)) for k, v in values.items()])
    msg = DiagnosticArray(status=[status])
    ns_to_stamp(stamp_ns, msg.header.stamp)
    return msg


# ibvs/frame_grid (diagnostic_msgs/DiagnosticArray, latched): which frames of each camera the
# graph computes (ibvs_common.core.frame_grid): per camera, every ``stride``-th frame counted
# from the frame stamped ``ref_ns``, and the frames its translational flow is computed on
# (``flow_stride``, ``flow_ref_ns``: the same grid, or a sparser one while the rate governor
# sheds the flows; absent: the same grid). Published by the supervisor on every change and
# once a second; every perception node computes only the frames on its camera's grid (the
# optical-flow nodes: on its flow grid).
FRAME_GRID_NAME = 'frame_grid'


def frame_grid_msg(grids: dict, stamp_ns: int) -> DiagnosticArray:
    """Build ibvs/frame_grid from camera name -> (stride, ref_ns[, flow_stride, flow_ref_ns])."""
    values = []
    for camera, grid in sorted(grids.items()):
        stride, ref_ns = grid[:2]
        flow_stride, flow_ref_ns = grid[2:4] if len(grid) >= 4 else (stride, ref_ns)
        values += [KeyValue(key=f'{camera}_stride', value=str(int(stride))),
                   KeyValue(key=f'{camera}_ref_ns', value=str(int(ref_ns))),
                   KeyValue(key=f'{camera}_flow_stride', value=str(int(flow_stride))),
                   KeyValue(key=f'{camera}_flow_ref_ns', value=str(int(flow_ref_ns)))]
    msg = DiagnosticArray(status=[DiagnosticStatus(level=DiagnosticStatus.OK,
                                                   name=FRAME_GRID_NAME, values=values)])
    ns_to_stamp(stamp_ns, msg.header.stamp)
    return msg


def grid_from_msg(msg: DiagnosticArray, camera: str,
                  flow: bool = False) -> tuple[int, int] | None:
    """Return (stride, ref_ns) of ``camera`` in an ibvs/frame_grid message, else None.

    ``flow``: the camera's flow grid instead (its frame grid when the message has none).
    """
    for status in msg.status:
        if status.name != FRAME_GRID_NAME:
            continue
        values = {kv.key: kv.value for kv in status.values}
        grid = _grid_values(values, camera, '')
        if grid is not None and flow and f'{camera}_flow_stride' in values:
            return _grid_values(values, camera, 'flow_')
        return grid
    return None


def _grid_values(values: dict, camera: str, prefix: str) -> tuple[int, int] | None:
    stride = values.get(f'{camera}_{prefix}stride', '')
    ref = values.get(f'{camera}_{prefix}ref_ns', '')
    if stride.isdigit() and int(stride) >= 1 and ref.lstrip('-').isdigit():
        return int(stride), int(ref)
    return None


#: a perception node skipped a grid image for a newer one (latest only): std_msgs/Header, the
#: image's stamp, frame_id the camera's name ('front', 'down'), one per image and node
SUPERSEDED_TOPIC = 'ibvs/frames_superseded'


def superseded_msg(camera: str, stamp_ns: int) -> Header:
    """Build ibvs/frames_superseded: ``camera``'s grid image of ``stamp_ns`` was skipped."""
    msg = Header(frame_id=str(camera))
    ns_to_stamp(stamp_ns, msg.stamp)
    return msg


def superseded_from_msg(msg: Header) -> tuple[str, int]:
    """Return (camera name, image stamp ns) of an ibvs/frames_superseded message."""
    return msg.frame_id, stamp_to_ns(msg.stamp)


def mode_from_status(msg: DiagnosticArray) -> tuple[int, int | None, str]:
    """ibvs/supervisor_status -> (stamp ns, mode number or None, '' or why it is refused)."""
    stamp_ns = stamp_to_ns(msg.header.stamp)
    for status in msg.status:
        if status.name != STATUS_NAME:
            continue
        for kv in status.values:
            if kv.key == STATUS_MODE_KEY:
                try:
                    return stamp_ns, int(kv.value), ''
                except ValueError:
                    return stamp_ns, None, f'mode value {kv.value!r} is not an integer'
    return stamp_ns, None, f'no {STATUS_NAME!r} status with a {STATUS_MODE_KEY!r} value'


def camera_from_status(msg: DiagnosticArray) -> str | None:
    """Return the camera of the frame an ibvs/supervisor_status evaluated, or None."""
    for status in msg.status:
        if status.name == STATUS_NAME:
            for kv in status.values:
                if kv.key == STATUS_CAMERA_KEY:
                    return kv.value
    return None


# ibvs/preflight (diagnostic_msgs/DiagnosticArray, latched): the preflight's verdict. One
# status named PREFLIGHT_NAME: level OK = go, ERROR = no-go; message = the summary line; one
# value per check (its name -> 'OK: ...', 'FAIL: ...' or 'SKIP: ...'). Published by the
# preflight (ibvs_bringup.preflight) when it ends; the supervisor refuses ibvs/start while
# the latest one is no-go (its require_preflight_go).
PREFLIGHT_TOPIC = 'ibvs/preflight'
PREFLIGHT_NAME = 'preflight'


def preflight_verdict_msg(go: bool, summary: str, checks: Iterable[tuple[str, str]],
                          stamp_ns: int) -> DiagnosticArray:
    """Build the ibvs/preflight message: go or no-go, the summary line, (check, state) pairs."""
    status = DiagnosticStatus(
        level=DiagnosticStatus.OK if go else DiagnosticStatus.ERROR, name=PREFLIGHT_NAME,
        message=summary, values=[KeyValue(key=k, value=v) for k, v in checks])
    msg = DiagnosticArray(status=[status])
    ns_to_stamp(stamp_ns, msg.header.stamp)
    return msg


def preflight_verdict(msg: DiagnosticArray) -> tuple[bool | None, str]:
    """ibvs/preflight -> (True: go | False: no-go, its summary) or (None, why it is unreadable)."""
    for status in msg.status:
        if status.name != PREFLIGHT_NAME:
            continue
        if status.level == DiagnosticStatus.OK:
            return True, status.message
        if status.level == DiagnosticStatus.ERROR:
            return False, status.message
        return None, f'level {status.level!r} is neither OK (go) nor ERROR (no-go)'
    return None, f'no {PREFLIGHT_NAME!r} status'
