"""mavlink_bridge: ibvs/force_setpoint + ibvs/heading_setpoint -> SET_ATTITUDE_TARGET; IMU back.

Thin ROS wrapper of :class:`ibvs_control.mavlink.bridge.MavlinkBridge` (docs/mavlink.md,
docs/interfaces.md). Subscribes ibvs/heading_setpoint (QuaternionStamped, map; created before
the force subscription, so that when both wait the heading of a frame is taken first),
ibvs/force_setpoint (Vector3Stamped, map, N), ibvs/mode (UInt8, transient local) and
ibvs/supervisor_status (DiagnosticArray, the mode of each frame); publishes imu/data
(sensor_msgs/Imu, base_link in map; stamps = the autopilot's sample times on the ROS clock by
MAVLink TIMESYNC, nothing before the clocks are synced) and /diagnostics; serves ibvs/arm
(std_srvs/Trigger: the bridge never arms the vehicle unless asked, here or by arm_on_start).
MAVLink input is handled as it arrives: a reader thread (``MavlinkReader``) waits on the
link's socket and runs the core's receive step under the node's lock, which every callback
also holds, so the core is never used from two threads at once. The stream timer (link
supervision, engage sequencing, a setpoint repeat when due; ``stream_rate_hz``) and the
heartbeat timer run on the steady clock: the autopilot's offboard timeout counts in its own
time, and a lockstep sim's /clock waits for our setpoints. The ROS time goes to the core with
every call.
"""
from __future__ import annotations

import math
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

from ibvs_common.core.config import ConfigError, load_vehicle
from ibvs_common.core.frames import vec_map_to_I
from ibvs_control.mavlink.bridge import BridgeConfig, BridgeStatus, MavlinkBridge
from ibvs_control.mavlink.hover import EstimatorConfig
from ibvs_control.mavlink.link import (
    LinkConfig, load_signing_key, MavlinkReader, SigningError)
from ibvs_control.mavlink.sequencer import SequencerConfig
from ibvs_control.mavlink.telemetry import ImuSample, load_px4_events, message_ids
from ibvs_control.mavlink.time_sync import TimeSyncConfig
from ibvs_common.intra_process import IntraProcessTopic
from ibvs_common.node_common import (
    COMMAND_QOS, FRAME_QOS, MODE_QOS, mode_from_status, ns_to_stamp, quat_wxyz, set_quat,
    set_vector3, stamp_to_ns, vector3)
from ibvs_common.param_descriptors import declare_all
from ibvs_common.spin import run_node
from ibvs_common.throttled_log import message_kind, ThrottledLog

DEFAULT_COVARIANCE = [1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4]
# PX4's onboard-link defaults that the bridge never reads (~300 of its ~400 messages/s,
# measured on PX4 v1.16 SITL): each costs the bridge a parse in Python (docs/mavlink.md)
DEFAULT_STREAMS_OFF = ('ATTITUDE', 'GLOBAL_POSITION_INT', 'LOCAL_POSITION_NED', 'ODOMETRY',
                       'ALTITUDE', 'DISTANCE_SENSOR', 'POSITION_TARGET_LOCAL_NED',
                       'SERVO_OUTPUT_RAW', 'VFR_HUD', 'GPS_RAW_INT')
UNKNOWN_COVARIANCE = np.array([-1.0] + [0.0] * 8)   # sensor_msgs/Imu: [0] = -1 "not provided"
LOG_THROTTLE_S = 2.0
MIN_HEARTBEAT_TIMEOUT_S = 3.0               # >= 3 periods of the autopilots' 1 Hz heartbeat
READER_WAIT_S = 0.1     # s (steady clock), the reader looks at a reopened link this often
PARAMETERS = {
    'url': 'udpin:0.0.0.0:14540',
    'source_system': 1,
    'target_system': 0,
    'target_component': 0,
    'heartbeat_timeout_s': 3.5,
    'reconnect_period_s': 1.0,
    'signing_key_file': '',
    'signing_link_id': 0,
    'autopilot': 'auto',
    'hover_thrust_source': 'autopilot',
    'hover_thrust': -1.0,
    'hover_estimator_enabled': True,
    'hover_estimator_process_noise': 0.0036,
    'hover_estimator_accel_noise': 2.0,
    'hover_estimator_max_deviation': 0.3,
    'vehicle_file': '',
    'param_timeout_s': 3.0,
    'attitude_rate_hz': 100.0,
    'streams_off': list(DEFAULT_STREAMS_OFF),
    'imu_rate_hz': 100.0,
    'thrust_rate_hz': 50.0,
    'status_rate_hz': 5.0,
    'heartbeat_request_hz': 5.0,
    'timesync_period_s': 0.1,
    'timesync_init_request_period_s': 0.05,
    'timesync_init_samples': 5,
    'timesync_max_rtt_s': 0.010,
    'timesync_alpha': 0.05,
    'timesync_beta': 0.002,
    'timesync_max_deviation_s': 0.010,
    'timesync_max_consecutive_outliers': 5,
    'stream_rate_hz': 30.0,
    'idle_tick_rate_hz': 10.0,
    'quiet_telemetry_rate_hz': 10.0,
    'quiet_telemetry_delay_s': 2.0,
    'heartbeat_rate_hz': 1.0,
    'diagnostics_rate_hz': 1.0,
    'hold_last_s': 0.25,
    'max_force_age_s': 0.25,
    'max_force_factor': 3.0,
    'max_tilt_rad': 0.6,
    'shutdown_ramp_s': 2.0,
    'min_imu_subscribers': 0,
    'prestream_s': 1.2,
    'command_retry_s': 1.0,
    'max_attempts': 5,
    'arm_on_start': False,
    'arm_backoff_max_s': 8.0,
    'arm_timeout_s': 60.0,
    'armable_unknown_wait_s': 1.0,
    'disarm_force_after_s': 1.0,
    'disarm_timeout_s': 10.0,
    'input_loss_action': 'auto',
    'px4_events_file': '',
    'frame_id': 'base_link',
    'orientation_covariance': DEFAULT_COVARIANCE,
    'angular_velocity_covariance': DEFAULT_COVARIANCE,
    'linear_acceleration_covariance': DEFAULT_COVARIANCE,
}
# Spec of each parameter: description with unit (and clock: ROS = the node's clock, sim time
# under use_sim_time; steady = monotonic), inclusive range (ibvs_common.param_descriptors).
PARAMETER_SPECS = {
    'url': ("MAVLink endpoint (pymavlink URL): PX4 'udpin:0.0.0.0:14540', serial "
            "'/dev/ttyUSB0,921600'; a udpin port is ours alone (one another socket holds is "
            "refused and retried every reconnect_period_s)",),
    'source_system': ("our MAVLink system id (the vehicle's)", 1, 255),
    'target_system': ("autopilot system id; 0 = learn from its first HEARTBEAT", 0, 255),
    'target_component': ("autopilot component id; 0 = learn from its first HEARTBEAT",
                         0, 255),
    'heartbeat_timeout_s': ('s (steady clock), no autopilot HEARTBEAT this long: link lost; '
                            f'>= {MIN_HEARTBEAT_TIMEOUT_S} (3 heartbeat periods)',
                            MIN_HEARTBEAT_TIMEOUT_S, None),
    'reconnect_period_s': ('s (steady clock), reopen a broken socket / serial port this often',
                           0.0, None),
    'signing_key_file': ("MAVLink 2 signing key file (32 bytes raw or 64 hex); '' = signing "
                         'off',),
    'signing_link_id': ('MAVLink 2 signing link id', 0, 255),
    'autopilot': ('auto (from HEARTBEAT) | px4 | ardupilot',),
    'hover_thrust_source': ('hover thrust seed: autopilot (MPC_THR_HOVER / MOT_THST_HOVER) | '
                            'config',),
    'hover_thrust': ('normalised thrust (0, 1]; <= 0 = the vehicle.yaml hover_thrust',
                     None, 1.0),
    'hover_estimator_enabled': ('estimate the hover thrust online (IMU vs applied thrust)',),
    'hover_estimator_process_noise': ('1/sqrt(s), hover thrust random walk', 0.0, None),
    'hover_estimator_accel_noise': ('m/s^2, accelerometer noise of one sample', 0.0, None),
    'hover_estimator_max_deviation': ('the estimate stays within seed * (1 -/+ this)',
                                      0.0, 1.0),
    'vehicle_file': ("vehicle YAML (mass, max thrust); '' = the installed vehicle.yaml",),
    'param_timeout_s': ('s (steady clock), unanswered autopilot parameter reads: fallback / '
                        'refuse', 0.0, None),
    'attitude_rate_hz': ('Hz, ATTITUDE_QUATERNION stream asked of the autopilot', 0.0, None),
    'imu_rate_hz': ('Hz, HIGHRES_IMU (PX4) / SCALED_IMU (ArduPilot) stream asked', 0.0, None),
    'thrust_rate_hz': ('Hz, ATTITUDE_TARGET stream asked (the thrust applied)', 0.0, None),
    'status_rate_hz': ('Hz, EXTENDED_SYS_STATE and SYS_STATUS streams asked', 0.0, None),
    'heartbeat_request_hz': ("Hz, ArduPilot's HEARTBEAT stream asked (PX4's is 1 Hz)",
                             0.0, None),
    'streams_off': ('MAVLink message names whose streams are switched off on this link '
                    '(SET_MESSAGE_INTERVAL -1): what the autopilot streams by default and the '
                    "bridge does not read; never one it reads. [''] = none",),
    'timesync_period_s': ('s (ROS clock) between TIMESYNC requests once synced', 0.0, None),
    'timesync_init_request_period_s': ('s (steady clock) between TIMESYNC requests while '
                                       'unsynced', 0.0, None),
    'timesync_init_samples': ('accepted TIMESYNC samples whose median starts the offset',
                              1, None),
    'timesync_max_rtt_s': ('s (ROS clock), TIMESYNC round trips above this are rejected',
                           0.0, None),
    'timesync_alpha': ('smoothing gain of the clock offset per accepted sample', 0.0, 1.0),
    'timesync_beta': ('smoothing gain of the clock skew per accepted sample', 0.0, 1.0),
    'timesync_max_deviation_s': ('s (ROS clock), a sample this far from the offset is an '
                                 'outlier', 0.0, None),
    'timesync_max_consecutive_outliers': ('outliers in a row taken as a time jump: reset, '
                                          're-sync', 0, None),
    'stream_rate_hz': ('Hz (steady clock timer), setpoint repeat when none left for 1/this, '
                       'link supervision, engage sequencing; > 0', 0.0, None),
    'idle_tick_rate_hz': ('Hz (steady clock), the same step while quiet (standby, supervisor '
                          'IDLE, clocks synced): also the keepalive stream rate then; > 2 '
                          '(PX4 wants > 2 Hz before OFFBOARD)', 2.0, None),
    'quiet_telemetry_rate_hz': ('Hz, the attitude, IMU and thrust streams asked while the '
                                'vehicle rests (disarmed, supervisor IDLE, no arm request, '
                                'no frame status), full rates again before anything engages '
                                'or at the first frame; 0 = full rates always', 0.0, None),
    'quiet_telemetry_delay_s': ('s (steady clock) at rest, and without a frame status, '
                                'before the streams slow down',
                                0.0, None),
    'heartbeat_rate_hz': ('Hz (steady clock timer), our HEARTBEAT; > 0', 0.0, None),
    'diagnostics_rate_hz': ('Hz (steady clock timer), /diagnostics; > 0', 0.0, None),
    'hold_last_s': ('s (ROS clock, vehicle time), the last valid setpoint is kept this long, '
                    'then the vehicle is handed back (input_loss_action)', 0.0, None),
    'max_force_age_s': ('s (ROS clock), a force computed from an image older than this when '
                        'it arrives is refused (not flown: the held setpoint goes on, and '
                        'after hold_last_s of refusals the vehicle is handed back): a graph '
                        'that falls behind does not fly old images; 0 = off', 0.0, None),
    'max_force_factor': ('|F| above this factor * m g is refused', 0.0, None),
    'max_tilt_rad': ('rad, tilt limit of the thrust direction', 0.0, math.pi),
    'shutdown_ramp_s': ('s (ROS clock, force stamps), SHUTDOWN: thrust ramp to 0, then disarm',
                        0.0, None),
    'min_imu_subscribers': ('no setpoint stream until imu/data has matched this many '
                            'subscribers', 0, None),
    'prestream_s': ('s (steady clock), PX4: setpoint stream before OFFBOARD (> 1 s)',
                    0.0, None),
    'command_retry_s': ('s (steady clock), resend an ineffective command after this',
                        0.0, None),
    'max_attempts': ('mode-switch attempts before FAILED', 1, None),
    'arm_on_start': ('true: an arm request from the start (sim scenario only); otherwise only '
                     'the ibvs/arm service arms',),
    'arm_backoff_max_s': ('s (steady clock), arming retries back off (doubling) up to this',
                          0.0, None),
    'arm_timeout_s': ('s (steady clock), arming refused this long: FAILED', 0.0, None),
    'armable_unknown_wait_s': ('s (steady clock), disarmed and no SYS_STATUS pre-arm report '
                               'yet: the mode switch waits this long for one, then tries',
                               0.0, None),
    'disarm_force_after_s': ('s (ROS clock, IMU stamps), touchdown rule: evidence and first '
                             'refusal this old before a forced disarm', 0.0, None),
    'disarm_timeout_s': ("s (steady clock), still armed this long after the ramp: the "
                         "autopilot's land mode", 0.0, None),
    'input_loss_action': ('forces lost: stop | land | auto (PX4: stop, ArduPilot: land)',),
    'px4_events_file': ("PX4 all_events.json(.xz) to name EVENT ids; '' = ids only",),
    'frame_id': ('frame_id of imu/data',),
    'orientation_covariance': ('rad^2, imu/data orientation covariance (row-major 3x3)',),
    'angular_velocity_covariance': ('(rad/s)^2, imu/data angular velocity covariance '
                                    '(row-major 3x3)',),
    'linear_acceleration_covariance': ('(m/s^2)^2, imu/data linear acceleration covariance '
                                       '(row-major 3x3)',),
}


def config_from_parameters(p: dict) -> BridgeConfig:
    """Return the typed configuration of the parameters (PARAMETERS keys); ValueError: why.

    Also used by the SITL tests to run the core with the shipped params.yaml.
    """
    try:
        vehicle = load_vehicle(p['vehicle_file'] or None)
    except ConfigError as exc:
        raise ValueError(str(exc)) from exc
    key = None
    if p['signing_key_file']:
        key = load_signing_key(p['signing_key_file'])
    if not p['heartbeat_timeout_s'] >= MIN_HEARTBEAT_TIMEOUT_S:
        raise ValueError(f'heartbeat_timeout_s must be >= {MIN_HEARTBEAT_TIMEOUT_S} s (3 '
                         f'heartbeat periods), got {p["heartbeat_timeout_s"]}')
    events = None
    if p['px4_events_file']:
        try:
            events = load_px4_events(p['px4_events_file'])
        except (OSError, ValueError) as exc:
            raise ValueError(f'px4_events_file {p["px4_events_file"]}: {exc}') from exc
    hover = p['hover_thrust'] if p['hover_thrust'] > 0.0 else vehicle.hover_thrust
    link = LinkConfig(url=p['url'], source_system=p['source_system'],
                      target_system=p['target_system'],
                      target_component=p['target_component'],
                      heartbeat_timeout_s=p['heartbeat_timeout_s'],
                      reconnect_period_s=p['reconnect_period_s'], signing_key=key,
                      signing_link_id=p['signing_link_id'])
    seq = SequencerConfig(prestream_s=p['prestream_s'],
                          command_retry_s=p['command_retry_s'],
                          max_attempts=p['max_attempts'],
                          arm_backoff_max_s=p['arm_backoff_max_s'],
                          arm_timeout_s=p['arm_timeout_s'],
                          armable_unknown_wait_s=p['armable_unknown_wait_s'],
                          disarm_force_after_s=p['disarm_force_after_s'],
                          disarm_timeout_s=p['disarm_timeout_s'],
                          input_loss_action=p['input_loss_action'])
    for k in ('stream_rate_hz', 'heartbeat_rate_hz', 'diagnostics_rate_hz'):
        if not p[k] > 0.0:
            raise ValueError(f'{k} must be > 0')
    sync = TimeSyncConfig(
        period_s=p['timesync_period_s'],
        init_request_period_s=p['timesync_init_request_period_s'],
        init_samples=p['timesync_init_samples'], max_rtt_s=p['timesync_max_rtt_s'],
        alpha=p['timesync_alpha'], beta=p['timesync_beta'],
        max_deviation_s=p['timesync_max_deviation_s'],
        max_consecutive_outliers=p['timesync_max_consecutive_outliers'])
    estimator = EstimatorConfig(
        enabled=bool(p['hover_estimator_enabled']),
        process_noise=p['hover_estimator_process_noise'],
        accel_noise=p['hover_estimator_accel_noise'],
        max_deviation=p['hover_estimator_max_deviation'])
    return BridgeConfig(
        link=link, mass=vehicle.mass, max_thrust_factor=vehicle.max_thrust_factor,
        configured_hover_thrust=hover, autopilot=p['autopilot'],
        hover_thrust_source=p['hover_thrust_source'], param_timeout_s=p['param_timeout_s'],
        attitude_rate_hz=p['attitude_rate_hz'], imu_rate_hz=p['imu_rate_hz'],
        thrust_rate_hz=p['thrust_rate_hz'], status_rate_hz=p['status_rate_hz'],
        heartbeat_request_hz=p['heartbeat_request_hz'],
        streams_off=message_ids(n for n in p['streams_off'] if n.strip()),
        stream_rate_hz=p['stream_rate_hz'], idle_tick_rate_hz=p['idle_tick_rate_hz'],
        quiet_telemetry_rate_hz=p['quiet_telemetry_rate_hz'],
        quiet_telemetry_delay_s=p['quiet_telemetry_delay_s'],
        time_sync=sync, hold_last_s=p['hold_last_s'], max_force_age_s=p['max_force_age_s'],
        max_force_factor=p['max_force_factor'], max_tilt_rad=p['max_tilt_rad'],
        shutdown_ramp_s=p['shutdown_ramp_s'], arm_on_start=bool(p['arm_on_start']),
        px4_events=events, sequencer=seq, estimator=estimator)


class MavlinkBridgeNode(Node):
    """ROS side of the MAVLink bridge."""

    def __init__(self, node_name: str = 'mavlink_bridge',
                 imu_local: IntraProcessTopic | None = None, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.log = ThrottledLog(self.get_logger())     # throttled messages cost nothing
        p = declare_all(self, PARAMETERS, PARAMETER_SPECS)   # ValueError: bad type or range
        self._config = config_from_parameters(p)
        self._frame_id = p['frame_id']
        # float64 arrays: a message takes them as they are (a list is checked and copied)
        self._cov = {k: np.array(p[k], dtype=np.float64) for k in (
            'orientation_covariance', 'angular_velocity_covariance',
            'linear_acceleration_covariance')}
        self._bridge = MavlinkBridge(self._config)
        self._lock = threading.Lock()           # the core: reader thread vs. executor
        self._min_imu_subscribers = int(p['min_imu_subscribers'])
        if self._min_imu_subscribers < 0:
            raise ValueError(f'min_imu_subscribers must be >= 0, got {self._min_imu_subscribers}')
        self._bridge.stream_enabled = self._min_imu_subscribers == 0

        self._imu_pub = self.create_publisher(Imu, 'imu/data', COMMAND_QOS)
        self._imu_local = imu_local             # the composed container's co-located nodes
        self.imu_dds_skipped = 0                # samples not published through DDS (no reader)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
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
        self.create_timer(1.0 / p['stream_rate_hz'], self._on_stream_tick, clock=steady)
        self.create_timer(1.0 / p['heartbeat_rate_hz'], self._on_heartbeat_tick, clock=steady)
        self.create_timer(1.0 / p['diagnostics_rate_hz'], self._on_diagnostics, clock=steady)
        self._reader = MavlinkReader(self._bridge.link, self._lock, self._on_readable,
                                     READER_WAIT_S, self._on_reader_error)
        self._reader.start()
        self.get_logger().info(
            f'MAVLink bridge on {self._config.link.url} (autopilot {p["autopilot"]}, '
            f'signing {"on" if self._config.link.signing_key else "off"}, hover thrust '
            f'seed {p["hover_thrust_source"]}'
            f'{", estimated online" if p["hover_estimator_enabled"] else ""}, arming '
            f'{"requested at start" if p["arm_on_start"] else "only on ibvs/arm"})')

    def _ros_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    # --- callbacks -------------------------------------------------------------------------
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
            if not self._bridge.stream_enabled:
                self._check_imu_consumers()
            self._bridge.stream(ros_ns)    # a repeat if no setpoint left for 1 / stream_rate_hz
            self._log_events()

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
            self._bridge.stream_enabled = True
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
