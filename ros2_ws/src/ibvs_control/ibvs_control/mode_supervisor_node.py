"""mode_supervisor: the flight-mode state machine on ROS (SPEC.md section 3).

Thin ROS wrapper of :class:`ibvs_control.core.supervisor.ModeSupervisor`. The inputs of one
camera frame (window corners, pad landmarks + groups, the two flows, all with the frame's
stamp) are gathered by a :class:`StampSynchronizer` (released once the IMU reaches the stamp
and every expected input is in, or after ``sync_timeout_s`` of wall clock), converted to {I}
(bearings: optical -> body FRD by the camera mount R_BC of vehicle.yaml -> {I} by the IMU
attitude at the stamp; flows: map -> {I}) and given to the core in a fixed order, then the
frame is closed (``end_frame``: auto-start, triggers, staleness). So the mode of each frame
depends on that frame's inputs, not on the order in which DDS delivered them. A node-clock
timer calls ``update(now)`` for the staleness rules when inputs stop.

Publishes ``ibvs/mode`` (std_msgs/UInt8, reliable, transient local, depth 1) at start and on
every transition (each logged with its reason), and ``ibvs/supervisor_status``
(diagnostic_msgs/DiagnosticArray, reliable) for every evaluated frame, stamped with it: the
force controller flies that frame in that mode. Serves ``ibvs/start`` and ``ibvs/abort``
(std_srvs/Trigger, success + message from the core).

``pad/groups`` (std_msgs/String "A,B") has no header: it is paired with the ``pad/landmarks``
message just before it (PadPairing).
"""
from __future__ import annotations

from dataclasses import fields
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from sensor_msgs.msg import Imu
from std_msgs.msg import String, UInt8
from std_srvs.srv import Trigger

from ibvs_control.core.config import load_pad_layout, load_vehicle, load_world
from ibvs_control.core.frames import (
    bearings_C_to_I, R_IB_from_rot_map_base, rot_from_quat)
from ibvs_control.core.modes import Mode
from ibvs_control.core.stamp_sync import (
    AttitudeHistory, check_bearings, check_flow, FrameBundle, InputKind, PadPairing,
    StampSynchronizer)
from ibvs_control.core.supervisor import ModeSupervisor, SupervisorConfig
from ibvs_control.node_common import (
    COMMAND_QOS, MODE_QOS, NS_PER_S, parse_pad_groups, polygon_points, quat_wxyz, SENSOR_QOS,
    stamp_to_ns, supervisor_status_msg, vector3)
from ibvs_control.spin import spin_guarded

LOG_THROTTLE_S = 2.0
LANDMARKS_PER_GROUP = 4
ATTITUDE_HISTORY_NS = 1_000_000_000      # IMU attitudes kept to derotate at an input's stamp
# Core parameters that come from the shared YAML files, not from params.yaml.
FROM_FILES = ('r_w', 'group_half_sides')
PARAMETERS = {
    'update_rate_hz': 20.0,
    'sync_timeout_s': 0.03,
    'sync_poll_period_s': 0.005,
    'vehicle_file': '',
    'world_file': '',
    'pad_layout_file': '',
}


def _core_defaults() -> dict:
    """Supervisor thresholds and timeouts (floats) with the core's defaults."""
    return {f.name: float(f.default) for f in fields(SupervisorConfig)
            if f.name not in FROM_FILES}


class ModeSupervisorNode(Node):
    """ROS side of the mode supervisor."""

    def __init__(self, node_name: str = 'mode_supervisor', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        core_params = _core_defaults()
        for name, default in {**core_params, **PARAMETERS}.items():
            self.declare_parameter(name, default)
        p = {name: self.get_parameter(name).value for name in {**core_params, **PARAMETERS}}
        vehicle = load_vehicle(p['vehicle_file'] or None)
        world = load_world(p['world_file'] or None)
        pad = load_pad_layout(p['pad_layout_file'] or None)
        config = SupervisorConfig.from_params(
            {**{k: float(p[k]) for k in core_params}, 'r_w': world.window.width,
             'group_half_sides': {g.name: g.c for g in pad.groups}})
        for name in ('update_rate_hz', 'sync_timeout_s', 'sync_poll_period_s'):
            if not float(p[name]) > 0.0:
                raise ValueError(f'{name} must be > 0, got {p[name]}')
        self._core = ModeSupervisor(config)
        self._R_BC = {name: vehicle.cameras[name].R_BC for name in ('front', 'down')}
        self._attitudes = AttitudeHistory(ATTITUDE_HISTORY_NS)   # R_IB by stamp
        self._pad_pairing = PadPairing(LANDMARKS_PER_GROUP)
        self._sync = StampSynchronizer(float(p['sync_timeout_s']), wait_for_imu=True)
        self._n_reported = 0
        self._published: Mode | None = None

        self._mode_pub = self.create_publisher(UInt8, 'ibvs/mode', MODE_QOS)
        self._status_pub = self.create_publisher(DiagnosticArray, 'ibvs/supervisor_status',
                                                 COMMAND_QOS)
        self.create_subscription(PolygonStamped, 'window/corners', self._on_window, SENSOR_QOS)
        self.create_subscription(PolygonStamped, 'pad/landmarks', self._on_landmarks,
                                 SENSOR_QOS)
        self.create_subscription(String, 'pad/groups', self._on_groups, SENSOR_QOS)
        self.create_subscription(Vector3Stamped, 'front_camera/translational_flow',
                                 self._on_front_flow, SENSOR_QOS)
        self.create_subscription(Vector3Stamped, 'down_camera/translational_flow',
                                 self._on_down_flow, SENSOR_QOS)
        self.create_subscription(Imu, 'imu/data', self._on_imu, SENSOR_QOS)
        self.create_service(Trigger, 'ibvs/start', self._on_start)
        self.create_service(Trigger, 'ibvs/abort', self._on_abort)
        self.create_timer(1.0 / p['update_rate_hz'], self._on_timer)   # node clock
        self.create_timer(float(p['sync_poll_period_s']), self._on_sync_timer,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._publish_mode()
        self.get_logger().info(f'mode supervisor ready in {self._core.mode.name}: {config}')

    # --- helpers ---------------------------------------------------------------------------
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds / NS_PER_S

    def _error(self, text: str) -> None:
        self.get_logger().error(text, throttle_duration_sec=LOG_THROTTLE_S)

    def _publish_mode(self) -> None:
        """Log the core's new transitions and publish the mode when it changed."""
        for tr in self._core.transitions[self._n_reported:]:
            self.get_logger().info(f'mode {tr.from_mode.name} -> {tr.to_mode.name} at '
                                   f't = {tr.t:.3f} s: {tr.reason}')
        self._n_reported = len(self._core.transitions)
        if self._core.mode != self._published:
            self._published = self._core.mode
            self._mode_pub.publish(UInt8(data=int(self._core.mode)))

    def _to_I(self, bearings_C: np.ndarray | None, stamp_ns: int, camera: str
              ) -> tuple[bool, np.ndarray | None]:
        """Derotate bearings to {I} with the attitude at the stamp: (usable?, bearings or None)."""
        if bearings_C is None:
            return True, None
        R_IB = self._attitudes.at(stamp_ns)   # at or just before
        if R_IB is None:
            self._error('no IMU attitude yet: cannot derotate bearings')
            return False, None
        return True, bearings_C_to_I(bearings_C, R_IB, self._R_BC[camera])

    # --- inputs ----------------------------------------------------------------------------
    def _on_imu(self, msg: Imu) -> None:
        try:
            R_IB = R_IB_from_rot_map_base(rot_from_quat(quat_wxyz(msg.orientation)))
        except ValueError as exc:
            self._error(f'imu/data refused: {exc}')
            return
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self._attitudes.add(stamp_ns, R_IB):
            self._core.on_imu(stamp_ns / NS_PER_S, R_IB)
            self._evaluate(self._sync.note_imu(stamp_ns))

    def _on_window(self, msg: PolygonStamped) -> None:
        bearings, err = check_bearings(polygon_points(msg), expected=4)
        self._add(InputKind.WINDOW, msg.header.stamp, bearings, err)

    def _on_landmarks(self, msg: PolygonStamped) -> None:
        bearings, err = check_bearings(polygon_points(msg))
        if err:                                  # evaluated as "no pad" for this stamp
            self._pad_pairing.drop_landmarks()
            self._add(InputKind.PAD, msg.header.stamp, None, err)
        else:                                    # the PAD input waits for its groups
            self._pad_pairing.add_landmarks(msg.header.stamp, bearings)

    def _on_groups(self, msg: String) -> None:
        pair = self._pad_pairing.add_groups(parse_pad_groups(msg.data))
        if pair is not None:
            stamp, bearings, groups = pair
            self._add(InputKind.PAD, stamp, (bearings, groups), '')

    def _on_front_flow(self, msg: Vector3Stamped) -> None:
        self._on_flow(InputKind.FLOW_FRONT, msg)

    def _on_down_flow(self, msg: Vector3Stamped) -> None:
        self._on_flow(InputKind.FLOW_DOWN, msg)

    def _on_flow(self, kind: InputKind, msg: Vector3Stamped) -> None:
        phi_I, err = check_flow(vector3(msg.vector), msg.header.frame_id)
        self._add(kind, msg.header.stamp, phi_I, err)

    def _add(self, kind: InputKind, stamp, value, err: str) -> None:
        """Give one input to the synchroniser (a refused one counts as 'not detected')."""
        if err:
            self._error(f'{kind.value} refused: {err}')
        bundles, dropped = self._sync.add(kind, stamp_to_ns(stamp), value, time.monotonic())
        if dropped:
            self.get_logger().warning(f'dropped: {dropped}', throttle_duration_sec=LOG_THROTTLE_S)
        self._evaluate(bundles)

    def _on_sync_timer(self) -> None:
        self._evaluate(self._sync.poll(time.monotonic()))

    # --- evaluation ------------------------------------------------------------------------
    def _evaluate(self, bundles: list[FrameBundle]) -> None:
        """Give each released frame's inputs to the core in a fixed order and close it."""
        for bundle in bundles:
            t = bundle.stamp_ns / NS_PER_S
            if bundle.missing:
                self.get_logger().warning(
                    f'frame {t:.3f} s evaluated without {", ".join(bundle.missing)} (late or '
                    'lost; lockstep runs stop repeating exactly)',
                    throttle_duration_sec=LOG_THROTTLE_S)
            if InputKind.WINDOW in bundle.values:
                ok, corners_I = self._to_I(bundle.get(InputKind.WINDOW), bundle.stamp_ns,
                                           'front')
                if ok:
                    self._core.on_window(t, corners_I)
            if InputKind.PAD in bundle.values:
                landmarks_C, groups = bundle.get(InputKind.PAD) or (None, ())
                ok, landmarks_I = self._to_I(landmarks_C, bundle.stamp_ns, 'down')
                if ok:
                    self._core.on_pad(t, landmarks_I, list(groups))
            for kind, camera in ((InputKind.FLOW_FRONT, 'front'), (InputKind.FLOW_DOWN, 'down')):
                if bundle.get(kind) is not None:
                    self._core.on_flow(t, camera, bundle.get(kind))
            self._core.end_frame(t)
            if self._core.auto_start_refusal:
                self._error(f'auto-start refused: {self._core.auto_start_refusal}')
            self._publish_mode()
            self._publish_status(bundle.stamp_ns)

    def _publish_status(self, stamp_ns: int) -> None:
        mode = self._core.mode
        level = DiagnosticStatus.WARN if mode == Mode.FAILSAFE else DiagnosticStatus.OK
        height = self._core.height_estimate
        values = {'pad_height_estimate_m': 'none' if height is None else f'{height:.4f}'}
        self._status_pub.publish(supervisor_status_msg(stamp_ns, int(mode), mode.name, level,
                                                       values))

    # --- services and timer ----------------------------------------------------------------
    def _on_start(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        response.success, response.message = self._core.start(self._now())
        self.get_logger().info(f'ibvs/start: {response.message}')
        self._publish_mode()
        return response

    def _on_abort(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        response.success, response.message = self._core.abort(self._now(), 'ibvs/abort called')
        self.get_logger().info(f'ibvs/abort: {response.message}')
        self._publish_mode()
        return response

    def _on_timer(self) -> None:
        """Staleness when inputs stop (frames are evaluated as they are released)."""
        if self._core.update(self._now()):
            self._publish_mode()


def main(args=None) -> None:
    """Run the node (``ros2 run ibvs_control mode_supervisor``)."""
    rclpy.init(args=args)
    node = None
    try:
        node = ModeSupervisorNode()
        spin_guarded(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:   # ConfigError or a bad parameter: refuse to start
        rclpy.logging.get_logger('mode_supervisor').fatal(f'refusing to start: {exc}')
        raise SystemExit(1)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
