"""Scenario monitor: the in-process node of ``run_scenario`` that watches one run.

It fills a ``report.RunLog`` ({I}, sim time) from the ground truth, modes (from
``ibvs/supervisor_status``: each change at the stamp of the frame where the supervisor made it,
not when the monitor heard it), events, force setpoint, flows and features, and carries the
preflight ``GraphHealth`` checks (the supervisor starts by itself: graph option
``auto_start_at_s``). All frame conversions go
through ``ibvs_common.core.frames``.
"""
from __future__ import annotations

from collections import deque
import json
import time
from typing import TYPE_CHECKING

from geometry_msgs.msg import Vector3Stamped
from ibvs_bringup.preflight import BEST_EFFORT, GraphHealth, LATCHED
from ibvs_harness.report import FEATURE_VECTORS, named_vector, RunLog
from diagnostic_msgs.msg import DiagnosticArray
from ibvs_common.core import frames
from ibvs_common.node_common import COMMAND_QOS, mode_from_status, NS_PER_S
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, String, UInt8

if TYPE_CHECKING:
    from rclpy.executors import Executor

FLOW_TOPICS = {'flow_front': 'front_camera/translational_flow',
               'flow_down': 'down_camera/translational_flow'}
# the MAVLink bridge's /diagnostics values kept once per message (1 Hz) for summary.json
BRIDGE_KEYS = ('engage_state', 'setpoint_source', 'hover_thrust', 'hover_estimate_std',
               'clock_synced', 'clock_offset_ms', 'clock_skew_ppm', 'timesync_accepted',
               'timesync_rejected_rtt', 'timesync_rejected_outliers', 'timesync_resets',
               'setpoint_rate_hz')
BRIDGE_HISTORY_LEN = 120


def stamp_s(msg: Odometry | Vector3Stamped | JointState) -> float:
    """Return a header stamp in seconds."""
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _number(text: str):
    """Return a diagnostic value as int or float when it is one, else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=float)


def odom_to_I(msg: Odometry) -> tuple:
    """Return (xi_I, v_I, euler (roll, pitch, yaw of R_IB), omega_FRD) of a ground-truth odom.

    Pose in ``map``; twist in the child frame ``base_link`` (nav_msgs/Odometry convention).
    """
    q = msg.pose.pose.orientation
    R_map_base = frames.rot_from_quat(frames.quat_xyzw_to_wxyz(np.array([q.x, q.y, q.z, q.w])))
    xi = frames.vec_map_to_I(_vec(msg.pose.pose.position))
    v_map = R_map_base @ _vec(msg.twist.twist.linear)
    euler = frames.euler_zyx_from_rot(frames.R_IB_from_rot_map_base(R_map_base))
    omega = frames.vec_flu_to_frd(_vec(msg.twist.twist.angular))
    return xi, frames.vec_map_to_I(v_map), np.asarray(euler), omega


class ScenarioMonitor(Node):
    """Subscribe to what a run reports; log it in {I}; expose the health checks."""

    def __init__(self, use_sim_time: bool = True, **kwargs) -> None:
        super().__init__('scenario_monitor', parameter_overrides=[
            Parameter('use_sim_time', value=use_sim_time)], **kwargs)
        # s on the ROS clock, subtracted from every time logged (px4-sih: the system time of
        # ibvs/start, see reset_log); 0 with the sim (its clock starts at 0)
        self.time_origin_s = 0.0
        self.log = RunLog()
        self.touchdown = None
        self.collision = None
        self.disarmed = False
        # steady clock (s) when the first ground truth (frame 0's) arrived: the start of the
        # sim's run for its real-time factor (summary.json timing.wall_s, sim_over_wall)
        self.first_truth_wall: float | None = None
        self.health = GraphHealth(self)
        self.create_subscription(Odometry, 'sim/ground_truth/odom', self._on_odom, BEST_EFFORT)
        self.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', self._on_status,
                                 COMMAND_QOS)
        self.create_subscription(String, 'sim/events', self._on_event, LATCHED)
        self.create_subscription(Vector3Stamped, 'ibvs/force_setpoint',
                                 lambda m: self._on_map_vector('force', m), BEST_EFFORT)
        for name, topic in FLOW_TOPICS.items():
            self.create_subscription(Vector3Stamped, topic,
                                     lambda m, n=name: self._on_map_vector(n, m), BEST_EFFORT)
        self.create_subscription(JointState, 'ibvs/features', self._on_features, BEST_EFFORT)
        self.sim_stats: dict = {}
        self.create_subscription(DiagnosticArray, 'sim/stats', self._on_sim_stats, LATCHED)
        self.bridge_history: deque = deque(maxlen=BRIDGE_HISTORY_LEN)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        # the pilot's side (--pilot-switch): what the bridge reads, and the sim's radio
        self.pilot_inputs: list = []
        self.create_subscription(UInt8, 'ibvs/pilot_input',
                                 lambda m: self.pilot_inputs.append(int(m.data)), LATCHED)
        self.pilot_switch = self.create_publisher(Bool, 'sim/pilot_switch', COMMAND_QOS)

    def now_s(self) -> float:
        """Return the node's (sim) time in seconds, from ``time_origin_s``."""
        return self.get_clock().now().nanoseconds * 1e-9 - self.time_origin_s

    def reset_log(self, origin_s: float) -> None:
        """Start a new log whose times count from ``origin_s`` (s, ROS clock); drop events."""
        self.time_origin_s = float(origin_s)
        self.log = RunLog()
        self.touchdown = self.collision = None

    def _on_odom(self, msg: Odometry) -> None:
        if self.first_truth_wall is None:
            self.first_truth_wall = time.monotonic()
        self.log.add_truth(stamp_s(msg) - self.time_origin_s, *odom_to_I(msg))

    def _on_status(self, msg: DiagnosticArray) -> None:
        """Record a mode change at the stamp of the frame where the supervisor made it."""
        stamp_ns, mode, err = mode_from_status(msg)
        if err or mode is None:
            return
        if self.log.add_mode(stamp_ns / NS_PER_S - self.time_origin_s, mode):
            self.get_logger().info(f'mode {mode} at t = {stamp_ns / NS_PER_S:.2f} s')

    def _on_sim_stats(self, msg: DiagnosticArray) -> None:
        """Keep the sim's latest timing figures (frames dropped, image -> setpoint latency)."""
        for status in msg.status:
            self.sim_stats = {kv.key: _number(kv.value) for kv in status.values}

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Keep the bridge's state, hover thrust and clock sync once per message (sim time)."""
        for status in msg.status:
            if not status.name.endswith(': MAVLink link'):
                continue
            values = {kv.key: _number(kv.value) for kv in status.values}
            row = {'t': round(self.now_s(), 3),
                   **{k: values[k] for k in BRIDGE_KEYS if k in values}}
            self.bridge_history.append(row)

    def _on_event(self, msg: String) -> None:
        try:
            event = json.loads(msg.data)
        except ValueError:
            self.get_logger().error(f'sim/events: not JSON: {msg.data[:80]!r}')
            return
        if self.time_origin_s and isinstance(event, dict) and 't' in event:
            try:
                event['t'] = float(event['t']) - self.time_origin_s
            except (TypeError, ValueError):
                pass
        self.log.events.append(event)
        if event.get('type') == 'touchdown' and self.touchdown is None:
            self.touchdown = event
        elif event.get('type') == 'collision' and self.collision is None:
            self.collision = event

    def _on_map_vector(self, name: str, msg: Vector3Stamped) -> None:
        self.log.add_vector(name, stamp_s(msg) - self.time_origin_s,
                            frames.vec_map_to_I(_vec(msg.vector)))

    def _on_features(self, msg: JointState) -> None:
        for name in FEATURE_VECTORS:
            v = named_vector(list(msg.name), list(msg.position), name)
            if v is not None:
                self.log.add_vector(name, stamp_s(msg) - self.time_origin_s, v)


DRAIN_SPINS = 20      # spins without waiting: what arrived while the graph was being stopped


def close_monitor(monitor: ScenarioMonitor | None, executor: Executor | None = None
                  ) -> tuple[RunLog, dict, list]:
    """Take what arrived while the graph stopped, destroy the monitor; return its products.

    Returns (run log, the sim's timing stats, the bridge's diagnostics history); empty ones
    when the monitor was never created. ``executor``: the one the monitor spins on (shut
    down here; None: rclpy's global one). Call after the graph is stopped, before
    ``rclpy.try_shutdown``.
    """
    import rclpy
    if monitor is None:
        if executor is not None:
            executor.shutdown()
        return RunLog(), {}, []
    if rclpy.ok():
        for _ in range(DRAIN_SPINS):
            if executor is None:
                rclpy.spin_once(monitor, timeout_sec=0.0)
            else:
                executor.spin_once(timeout_sec=0.0)
    products = monitor.log, dict(monitor.sim_stats), list(monitor.bridge_history)
    if executor is not None:
        executor.shutdown()
    monitor.destroy_node()
    return products
