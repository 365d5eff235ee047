"""force_controller: detections + flows + IMU + mode -> the paper's force F and a heading.

Thin ROS wrapper of :class:`ibvs_control.core.controller.IbvsController`. For each image stamp
it gathers window/corners, pad/landmarks, the flows and the supervisor's mode of that stamp
(``ibvs/supervisor_status``; :class:`~ibvs_control.core.stamp_sync.StampSynchronizer`,
wall-clock timeout ``sync_timeout_s``), steps the controller once in that mode with the IMU
attitude at (or just before) the stamp, and publishes, stamped with the image stamp:

- ``ibvs/force_setpoint`` (geometry_msgs/Vector3Stamped, frame map, newtons),
- ``ibvs/heading_setpoint`` (geometry_msgs/QuaternionStamped, frame map; yaw-only attitude of
  base_link), published before the force,
- ``ibvs/features`` (sensor_msgs/JointState as a named stamped vector: name = 'q_w.x', ...,
  'q_w_bar.*', 'q_t.*', 'phi_w.*', 'phi_t.*', 'eta_w.*', 'alpha_w'; position = values in {I};
  unavailable features are left out).

Every stamp is answered exactly once in every mode (IDLE included: the core gives hover), as
the sim's lockstep pacing waits for it. Gains are checked at start by
ControllerConfig.from_params: bad gains -> GainError, the process exits with status 1.
"""
from __future__ import annotations

import time

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PolygonStamped, QuaternionStamped, Vector3Stamped
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import String, UInt8

from ibvs_control.core.config import load_pad_layout, load_vehicle, load_world
from ibvs_control.core.control_laws import CrossingGains, LandingGains, WindowGains
from ibvs_control.core.controller import ControllerConfig, IbvsController
from ibvs_control.core.frames import (
    MAP_FRAME, R_IB_from_rot_map_base, rot_from_quat, vec_I_to_map)
from ibvs_control.core.modes import Mode
from ibvs_control.core.stamp_sync import (
    AttitudeHistory, check_bearings, check_flow, feature_vector, FLOWS, FrameBundle,
    heading_quat_enu_flu, InputKind, ModeTracker, PadPairing, StampSynchronizer,
    step_controller)
from ibvs_control.node_common import (
    COMMAND_QOS, mode_from_status, MODE_QOS, NS_PER_S, ns_to_stamp, parse_pad_groups,
    polygon_points, quat_wxyz, SENSOR_QOS, set_quat, set_vector3, stamp_to_ns, vector3)
from ibvs_control.spin import spin_guarded

LOG_THROTTLE_S = 2.0


def _gain_defaults() -> dict:
    """Parameter names and defaults of the gains (the paper's, from the core dataclasses)."""
    out = {}
    for prefix, kind in (('landing', LandingGains), ('window', WindowGains),
                         ('crossing', CrossingGains)):
        for f in kind.__dataclass_fields__.values():
            out[f'{prefix}.{f.name}'] = float(f.default)
    return out


def _mode(number) -> tuple[Mode | None, str]:
    """Convert a mode number from a message to (Mode, '') or (None, why it is refused)."""
    try:
        return Mode(int(number)), ''
    except (TypeError, ValueError):
        return None, f'unknown mode {number!r}: ignored'


GAIN_PARAMETERS = _gain_defaults()
PARAMETERS = {
    'crossing_law': 'closed',
    'sync_timeout_s': 0.03,
    'sync_poll_period_s': 0.005,
    'imu_history_s': 1.0,
    'vehicle_file': '',
    'world_file': '',
    'pad_layout_file': '',
}


class ForceControllerNode(Node):
    """ROS side of the outer-loop IBVS controller."""

    def __init__(self, node_name: str = 'force_controller', **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        for name, default in {**GAIN_PARAMETERS, **PARAMETERS}.items():
            self.declare_parameter(name, default)
        p = {name: self.get_parameter(name).value
             for name in {**GAIN_PARAMETERS, **PARAMETERS}}
        vehicle = load_vehicle(p['vehicle_file'] or None)
        r_w = load_world(p['world_file'] or None).window.width
        gains = {k: p[k] for k in GAIN_PARAMETERS}
        gains['crossing_law'] = p['crossing_law']
        pad = load_pad_layout(p['pad_layout_file'] or None)
        config = ControllerConfig.from_params(gains, vehicle, r_w, pad)   # raises GainError
        self._controller = IbvsController(config)
        self._sync = StampSynchronizer(p['sync_timeout_s'], wait_for_imu=True,
                                       optional=(*FLOWS, InputKind.MODE))
        self._attitudes = AttitudeHistory(int(p['imu_history_s'] * NS_PER_S))
        self._modes = ModeTracker()
        self._pad_pairing = PadPairing()

        self._force_pub = self.create_publisher(Vector3Stamped, 'ibvs/force_setpoint',
                                                COMMAND_QOS)
        self._heading_pub = self.create_publisher(QuaternionStamped, 'ibvs/heading_setpoint',
                                                  COMMAND_QOS)
        self._features_pub = self.create_publisher(JointState, 'ibvs/features', COMMAND_QOS)
        self.create_subscription(PolygonStamped, 'window/corners', self._on_window, SENSOR_QOS)
        self.create_subscription(PolygonStamped, 'pad/landmarks', self._on_pad, SENSOR_QOS)
        self.create_subscription(String, 'pad/groups', self._on_groups, SENSOR_QOS)
        self.create_subscription(Vector3Stamped, 'front_camera/translational_flow',
                                 self._on_front_flow, SENSOR_QOS)
        self.create_subscription(Vector3Stamped, 'down_camera/translational_flow',
                                 self._on_down_flow, SENSOR_QOS)
        self.create_subscription(Imu, 'imu/data', self._on_imu, SENSOR_QOS)
        self.create_subscription(UInt8, 'ibvs/mode', self._on_mode, MODE_QOS)
        self.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', self._on_status,
                                 COMMAND_QOS)
        self.create_timer(p['sync_poll_period_s'], self._on_sync_timer,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'force controller: gains {config.landing}, {config.window}, '
                               f'{config.crossing}, crossing law {config.crossing_law.value}')

    # --- inputs ----------------------------------------------------------------------------
    def _on_window(self, msg: PolygonStamped) -> None:
        bearings, err = check_bearings(polygon_points(msg), expected=4)
        self._add(InputKind.WINDOW, msg.header.stamp, bearings, err)

    def _on_pad(self, msg: PolygonStamped) -> None:
        bearings, err = check_bearings(polygon_points(msg))
        if err:                                  # answered as "no pad" for this stamp
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
        self._add_flow(InputKind.FLOW_FRONT, msg)

    def _on_down_flow(self, msg: Vector3Stamped) -> None:
        self._add_flow(InputKind.FLOW_DOWN, msg)

    def _add_flow(self, kind: InputKind, msg: Vector3Stamped) -> None:
        phi_I, err = check_flow(vector3(msg.vector), msg.header.frame_id)
        self._add(kind, msg.header.stamp, phi_I, err)

    def _on_imu(self, msg: Imu) -> None:
        try:
            R_IB = R_IB_from_rot_map_base(rot_from_quat(quat_wxyz(msg.orientation)))
        except ValueError as exc:
            self.get_logger().error(f'imu/data refused: {exc}',
                                    throttle_duration_sec=LOG_THROTTLE_S)
            return
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self._attitudes.add(stamp_ns, R_IB):
            for bundle in self._sync.note_imu(stamp_ns):
                self._answer(bundle)

    def _on_mode(self, msg: UInt8) -> None:
        """Note the latest mode (frames without their own status fly it)."""
        mode, err = _mode(msg.data)
        if err:
            self._refused(InputKind.MODE, err)
        else:
            self._modes.note(mode)

    def _on_status(self, msg: DiagnosticArray) -> None:
        """Add the supervisor's mode for one frame as the MODE input of that stamp."""
        stamp_ns, number, err = mode_from_status(msg)
        mode, err = (None, err) if err else _mode(number)
        if err:
            self._refused(InputKind.MODE, err)
            return
        self._modes.note(mode)
        bundles, dropped = self._sync.add(InputKind.MODE, stamp_ns, mode, time.monotonic())
        if dropped:
            self.get_logger().warning(f'dropped: {dropped}', throttle_duration_sec=LOG_THROTTLE_S)
        for bundle in bundles:
            self._answer(bundle)

    def _refused(self, kind: InputKind, err: str) -> None:
        self.get_logger().error(f'{kind.value} refused: {err}',
                                throttle_duration_sec=LOG_THROTTLE_S)

    def _add(self, kind: InputKind, stamp, value, err: str) -> None:
        """Give one input to the synchroniser (a bad one counts as 'not detected')."""
        if err:
            self._refused(kind, err)
        bundles, dropped = self._sync.add(kind, stamp_to_ns(stamp), value, time.monotonic())
        if dropped:
            self.get_logger().warning(f'dropped: {dropped}', throttle_duration_sec=LOG_THROTTLE_S)
        for bundle in bundles:
            self._answer(bundle)

    def _on_sync_timer(self) -> None:
        for bundle in self._sync.poll(time.monotonic()):
            self._answer(bundle)

    # --- output ----------------------------------------------------------------------------
    def _answer(self, bundle: FrameBundle) -> None:
        if bundle.missing:
            self.get_logger().warning(
                f'frame {bundle.stamp_ns / NS_PER_S:.3f} s answered without '
                f'{", ".join(bundle.missing)} (late or lost; lockstep runs stop repeating '
                'exactly)',
                throttle_duration_sec=LOG_THROTTLE_S)
        out, F_I = step_controller(self._controller, self._modes.mode_at(bundle), bundle,
                                   self._attitudes.at(bundle.stamp_ns))
        if out is None:
            self.get_logger().warning('no IMU attitude (or no valid output): answering with '
                                      'hover', throttle_duration_sec=LOG_THROTTLE_S)
        else:
            heading = QuaternionStamped()
            ns_to_stamp(bundle.stamp_ns, heading.header.stamp)
            heading.header.frame_id = MAP_FRAME
            set_quat(heading.quaternion, heading_quat_enu_flu(out.yaw_des))
            self._heading_pub.publish(heading)
        force = Vector3Stamped()
        ns_to_stamp(bundle.stamp_ns, force.header.stamp)
        force.header.frame_id = MAP_FRAME
        set_vector3(force.vector, vec_I_to_map(F_I))
        self._force_pub.publish(force)
        if out is not None:
            names, values = feature_vector(out.features)
            features = JointState(name=names, position=values)
            ns_to_stamp(bundle.stamp_ns, features.header.stamp)
            features.header.frame_id = ''   # values are in the paper frame {I}
            self._features_pub.publish(features)


def main(args=None) -> None:
    """Run the node (``ros2 run ibvs_control force_controller``); exit 1 on bad gains."""
    rclpy.init(args=args)
    node = None
    try:
        node = ForceControllerNode()
        spin_guarded(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:   # GainError, ConfigError: never fly with a bad configuration
        rclpy.logging.get_logger('force_controller').fatal(f'refusing to start: {exc}')
        raise SystemExit(1)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
