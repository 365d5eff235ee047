"""mavlink_bridge: ibvs/force_setpoint + ibvs/heading_setpoint -> SET_ATTITUDE_TARGET; IMU back.

Thin ROS wrapper of :class:`ibvs_control.mavlink.bridge.MavlinkBridge`: its parameters are
:class:`~ibvs_control.mavlink.config.MavlinkBridgeNodeConfig`; a reader thread
(``MavlinkReader``) handles MAVLink input as it arrives, under the lock every callback holds;
the stream, heartbeat and diagnostics timers run on the steady clock. The pilot's mission
switch (RC_CHANNELS) is published on ``ibvs/pilot_input`` (latched, on change;
:mod:`ibvs_control.core.pilot_input`). Topics, services and threading: docs/mavlink.md and
docs/interfaces.md.
"""
from __future__ import annotations

import threading
from typing import Callable

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import QuaternionStamped, Vector3Stamped
from sensor_msgs.msg import Imu
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from ibvs_common.core.frames import vec_map_to_I
from ibvs_common.intra_process import IntraProcessTopic
from ibvs_common.node_common import (
    COMMAND_QOS, FRAME_QOS, MODE_QOS, mode_from_status, ns_to_stamp, quat_wxyz, set_quat,
    set_vector3, stamp_to_ns, vector3)
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import message_kind, ThrottledLog
from ibvs_control.core.pilot_input import PilotInput
from ibvs_control.mavlink.bridge import BridgeStatus, MavlinkBridge
from ibvs_control.mavlink.config import MavlinkBridgeNodeConfig
from ibvs_control.mavlink.link import MavlinkReader, SigningError
from ibvs_control.mavlink.telemetry import ImuSample

UNKNOWN_COVARIANCE = np.array([-1.0] + [0.0] * 8)   # sensor_msgs/Imu: [0] = -1 "not provided"
LOG_THROTTLE_S = 2.0
READER_WAIT_S = 0.1     # s (steady clock), the reader looks at a reopened link this often


class MavlinkBridgeNode(Node):
    """ROS side of the MAVLink bridge."""

    def __init__(self, node_name: str = 'mavlink_bridge',
                 imu_local: IntraProcessTopic | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        cfg = declare_config(self, MavlinkBridgeNodeConfig)   # ValueError: bad type or range
        self._config = cfg.bridge_config()
        self._frame_id = cfg.frame_id
        # float64 arrays: a message takes them as they are (a list is checked and copied)
        self._cov = {k: np.array(getattr(cfg, k), dtype=np.float64) for k in (
            'orientation_covariance', 'angular_velocity_covariance',
            'linear_acceleration_covariance')}
        self._bridge = MavlinkBridge(self._config, heartbeat_clock=self._heartbeat_clock())
        self._lock = threading.Lock()           # the core: reader thread vs. executor
        self._min_imu_subscribers = cfg.min_imu_subscribers
        self._bridge.setpoints.enabled = self._min_imu_subscribers == 0

        self._imu_pub = self.create_publisher(Imu, 'imu/data', COMMAND_QOS)
        self._imu_local = imu_local             # the composed container's co-located nodes
        self.imu_dds_skipped = 0                # samples not published through DDS (no reader)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._pilot_pub = self.create_publisher(UInt8, 'ibvs/pilot_input', MODE_QOS)
        self._pilot_published: PilotInput | None = None
        # The heading subscription first: with both ready, the executor takes it first, so a
        # force finds the heading of its own stamp (the controller publishes the heading first).
        self.create_subscription(QuaternionStamped, 'ibvs/heading_setpoint', self._on_heading,
                                 FRAME_QOS)
        self.create_subscription(Vector3Stamped, 'ibvs/force_setpoint', self._on_force,
                                 FRAME_QOS)
        self.create_subscription(UInt8, 'ibvs/mode', self._on_mode, MODE_QOS)
        self.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', self._on_status,
                                 FRAME_QOS)
        self.create_service(Trigger, 'ibvs/arm', self._on_arm)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / self._config.stream_rate_hz, self._on_stream_tick, clock=steady)
        self.create_timer(1.0 / cfg.heartbeat_rate_hz, self._on_heartbeat_tick, clock=steady)
        self.create_timer(1.0 / cfg.diagnostics_rate_hz, self._on_diagnostics, clock=steady)
        self._reader = MavlinkReader(self._bridge.link, self._lock, self._on_readable,
                                     READER_WAIT_S, self._on_reader_error)
        self._reader.start()
        self.get_logger().info(
            f'MAVLink bridge on {self._config.link.url} (autopilot {self._config.autopilot}, '
            f'signing {"on" if self._config.link.signing_key else "off"}, hover thrust '
            f'seed {self._config.hover_thrust_source}'
            f'{", estimated online" if self._config.estimator.enabled else ""}, arming '
            f'{"requested at start" if self._config.arm_on_start else "only on ibvs/arm"})')

    def _ros_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    # --- callbacks -------------------------------------------------------------------------
    def _heartbeat_clock(self) -> Callable[[], float] | None:
        """Return the clock of heartbeat_timeout_s: the ROS clock (s) under use_sim_time, or None.

        None: the bridge's steady clock (onboard). Simulated time: the autopilot's HEARTBEATs
        are 1 Hz of it (a firmware in lockstep), as MAVROS's connection timeout.
        """
        if not self.get_parameter('use_sim_time').value:
            return None
        clock = self.get_clock()
        return lambda: clock.now().nanoseconds * 1e-9

    def _on_force(self, msg: Vector3Stamped) -> None:
        frame_ok = msg.header.frame_id in ('map', '')
        F_I = vec_map_to_I(vector3(msg.vector)) if frame_ok else np.full(3, np.nan)
        with self._lock:
            reason = self._bridge.on_force(stamp_to_ns(msg.header.stamp), F_I, self._ros_ns())
            self._log_events()
        if reason or not frame_ok:
            self.log.error(f'force setpoint refused (frame {msg.header.frame_id!r}): {reason}',
                           LOG_THROTTLE_S)

    def _on_heading(self, msg: QuaternionStamped) -> None:
        with self._lock:
            reason = self._bridge.on_heading(stamp_to_ns(msg.header.stamp),
                                             quat_wxyz(msg.quaternion), self._ros_ns())
            self._log_events()
        if reason:
            self.log.error(f'heading setpoint refused: {reason}', LOG_THROTTLE_S)

    def _on_arm(self, request, response):
        """ibvs/arm: allow the bridge to arm the vehicle when it engages."""
        with self._lock:
            response.success, response.message = self._bridge.request_arm()
            self._log_events()
        self.get_logger().info(f'ibvs/arm: {response.message}')
        return response

    def _on_mode(self, msg: UInt8) -> None:
        with self._lock:
            self._bridge.on_supervisor_mode(msg.data)
            self._log_events()

    def _on_status(self, msg: DiagnosticArray) -> None:
        """Give the supervisor's mode of one frame to the core (the content of its force)."""
        stamp_ns, mode, err = mode_from_status(msg)
        with self._lock:
            err = err or self._bridge.on_supervisor_status(stamp_ns, mode)
        if err:
            self.log.error(f'ibvs/supervisor_status refused: {err}', LOG_THROTTLE_S)

    def _on_readable(self) -> None:
        """Reader thread, lock held: handle the pending messages, publish the IMU samples.

        The supervision step runs here only after messages other than the high-rate
        telemetry (``MavlinkBridge.poll``); the stream tick runs it in any case.
        """
        self._receive(None, supervise=False, ros_clock=self._ros_ns)

    def _on_reader_error(self, text: str) -> None:
        self.log.error(f'MAVLink receive step failed: {text}', LOG_THROTTLE_S)

    def _on_stream_tick(self) -> None:
        """Supervise the link and the sequencer; repeat the setpoint when none left."""
        with self._lock:
            if not self._bridge.tick_due():     # quiet: at idle_tick_rate_hz
                return
            ros_ns = self._ros_ns()
            self._receive(ros_ns)
            if not self._bridge.setpoints.enabled:
                self._check_imu_consumers()
            self._bridge.stream(ros_ns)    # a repeat if no setpoint left for 1 / stream_rate_hz
            self._log_events()
            pilot = self._bridge.pilot_input()
        self._publish_pilot_input(pilot)

    def _publish_pilot_input(self, value: PilotInput) -> None:
        """ibvs/pilot_input on change (latched: a late subscriber gets the last one)."""
        if value == self._pilot_published:
            return
        self._pilot_published = value
        self._pilot_pub.publish(UInt8(data=int(value)))
        self.get_logger().info(f'ibvs/pilot_input: {value.name}')

    def _on_heartbeat_tick(self) -> None:
        with self._lock:
            self._bridge.heartbeat()

    def _receive(self, ros_ns: int | None, supervise: bool = True,
                 ros_clock: Callable[[], int] | None = None) -> None:
        """Lock held: read what is pending, run the sequencer, publish new IMU samples."""
        for sample in self._bridge.poll(ros_ns, supervise, ros_clock):
            self._publish_imu(sample)
        self._log_events()

    def _publish_imu(self, sample: ImuSample) -> None:
        """imu/data to the co-located nodes in process, and through DDS when anyone there takes it.

        As rclcpp's intra-process publish: the inter-process publish (serialisation, the
        middleware's write) is skipped while no DDS subscription is matched (in the composed
        container every onboard consumer is in process); a recorder or a node in another
        process that subscribes gets the samples from its match on. Without one, the message
        is built only when a co-located node takes it (an idle graph never builds it). In
        process first: a sample a DDS subscriber has is already there for the co-located
        nodes' next take.
        """
        if self._imu_local is not None and self._imu_pub.get_subscription_count() == 0:
            self._imu_local.publish_lazy(lambda: self._imu_msg(sample))
            self.imu_dds_skipped += 1
            return
        msg = self._imu_msg(sample)
        if self._imu_local is not None:
            self._imu_local.publish(msg)
        self._imu_pub.publish(msg)

    def _check_imu_consumers(self) -> None:
        """Start the setpoint stream once imu/data has its consumers matched (then for good)."""
        matched = self._imu_pub.get_subscription_count() + (
            0 if self._imu_local is None else self._imu_local.subscriber_count)
        if matched >= self._min_imu_subscribers:
            self._bridge.setpoints.enabled = True
            self.get_logger().info(f'imu/data matched {matched} subscribers: setpoint stream on')
        else:
            self.log.info(
                f'setpoint stream held: imu/data matched {matched} of '
                f'{self._min_imu_subscribers} subscribers', LOG_THROTTLE_S)

    def _on_diagnostics(self) -> None:
        with self._lock:
            status = self._bridge.status()
        self._diag_pub.publish(self._diagnostics(status))

    # --- message building ------------------------------------------------------------------
    def _imu_msg(self, s: ImuSample) -> Imu:
        msg = Imu()
        ns_to_stamp(s.stamp_ns, msg.header.stamp)
        msg.header.frame_id = self._frame_id
        set_quat(msg.orientation, s.q_wxyz)
        set_vector3(msg.angular_velocity, s.angular_velocity_flu)
        msg.orientation_covariance = self._cov['orientation_covariance']
        msg.angular_velocity_covariance = self._cov['angular_velocity_covariance']
        if s.linear_acceleration_flu is None:
            msg.linear_acceleration_covariance = UNKNOWN_COVARIANCE
        else:
            set_vector3(msg.linear_acceleration, s.linear_acceleration_flu)
            msg.linear_acceleration_covariance = self._cov['linear_acceleration_covariance']
        return msg

    def _diagnostics(self, st: BridgeStatus) -> DiagnosticArray:
        status = DiagnosticStatus()
        status.name = f'{self.get_name()}: MAVLink link'
        status.hardware_id = self._config.link.url
        if not st.link_up or st.engage_state in ('refused', 'failed') \
                or st.autopilot_internal_errors:
            status.level = DiagnosticStatus.ERROR
        elif st.setpoint_source not in ('ibvs', 'none') or not st.time_sync.synced \
                or st.engage_state in ('wait_arm', 'held', 'landing'):
            status.level = DiagnosticStatus.WARN
        else:
            status.level = DiagnosticStatus.OK
        ts = st.time_sync
        status.message = (f'link {"up" if st.link_up else "LOST"}'
                          + (f' ({st.link_error})' if st.link_error and not st.link_up else '')
                          + f', {st.engage_state}'
                          + (f' ({st.engage_reason})' if st.engage_reason else '')
                          + ('' if ts.synced else ', clock not synced: no imu/data')
                          + (f', autopilot internal errors 0x{st.autopilot_internal_errors:x}'
                             if st.autopilot_internal_errors else ''))

        def fmt(v: float | int | bool | None, spec: str = '.3f', none: str = 'unknown') -> str:
            return none if v is None else format(v, spec)
        values = {'link': 'up' if st.link_up else 'lost',
                  'heartbeat_age_s': f'{st.heartbeat_age_s:.2f}',
                  'autopilot': st.autopilot, 'armed': str(st.armed),
                  'custom_mode': str(st.custom_mode), 'engage_state': st.engage_state,
                  'supervisor_mode': st.supervisor_mode, 'streaming': str(st.streaming),
                  'arm_requested': str(st.arm_requested),
                  'telemetry_slowed': str(st.telemetry_slowed),
                  'pilot_input': st.pilot_input,
                  'hover_thrust': fmt(st.hover_thrust),
                  'hover_thrust_seed': fmt(st.hover_thrust_seed),
                  'hover_thrust_source': st.hover_thrust_source,
                  'hover_estimate_std': fmt(st.hover_estimate_std, '.4f'),
                  'setpoint_source': st.setpoint_source,
                  'setpoint_rate_hz': f'{st.setpoint_rate_hz:.1f}',
                  'rejected_setpoints': str(st.rejected_setpoints),
                  'stale_setpoints': str(st.stale_setpoints),
                  'landed_state': fmt(st.landed_state, 'd'),
                  'armable': fmt(st.armable, '', 'unknown'),
                  'autopilot_internal_errors': f'0x{st.autopilot_internal_errors:x}',
                  'last_autopilot_reason': st.last_autopilot_reason,
                  'dead_bridge_failsafe': fmt(st.dead_bridge_failsafe, '', 'unknown'),
                  'clock_synced': 'yes' if ts.synced else 'no',
                  'clock_offset_ms': fmt(None if ts.offset_ns is None else ts.offset_ns / 1e6),
                  'clock_skew_ppm': fmt(ts.skew_ppm, '.1f'),
                  'timesync_accepted': str(ts.accepted),
                  'timesync_rejected': str(ts.rejected_rtt + ts.rejected_outliers),
                  'timesync_rejected_rtt': str(ts.rejected_rtt),
                  'timesync_rejected_outliers': str(ts.rejected_outliers),
                  'timesync_resets': str(ts.resets),
                  'timesync_reboots': str(ts.reboots),
                  'timesync_last_rtt_ms': fmt(None if ts.last_rtt_ns is None
                                              else ts.last_rtt_ns / 1e6, '.3f', 'none'),
                  'imu_dropped_unsynced': str(st.imu_dropped_unsynced),
                  'reader_wakeups': str(self._reader.wakeups),
                  'reader_errors': str(self._reader.errors)}
        values.update({k: str(v) for k, v in st.counters.items()})
        # what the autopilot does when we stop (the preflight gates on them): as read
        values['source_system'] = str(st.source_system)
        values.update({name: f'{v:g}' for name, v in sorted(st.dead_bridge_params.items())})
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        return msg

    def _log_events(self) -> None:
        log = self.get_logger()
        heading_warning = self._bridge.pop_heading_warning()
        if heading_warning:     # own call site: its throttle is not shared with the events'
            self.log.warning(heading_warning, LOG_THROTTLE_S)
        for level, text in self._bridge.pop_events():
            # throttled per kind of message, not per this call site: a one-off warning (PX4's
            # offboard-loss set-up) must not be held back by an unrelated one just before it
            if level == 'error':
                self.log.error(text, LOG_THROTTLE_S, key=message_kind(text))
            elif level == 'warn':
                self.log.warning(text, LOG_THROTTLE_S, key=message_kind(text))
            elif level == 'reason-error':          # the autopilot's words: each one logged
                log.error(text)                    # (the core repeats a text once per 5 s)
            elif level == 'reason-warn':
                log.warning(text)
            else:
                log.info(text)

    def destroy_node(self) -> None:
        """Stop the reader and close the MAVLink connection with the node."""
        self._reader.stop()
        with self._lock:
            self._bridge.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the node (``ros2 run ibvs_control mavlink_bridge``)."""
    run_node(MavlinkBridgeNode, 'mavlink_bridge', args, refuse=(ValueError, SigningError))
