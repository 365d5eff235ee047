"""mode_supervisor: the flight-mode state machine on ROS (SPEC.md section 3).

Thin ROS wrapper of :class:`ibvs_control.core.supervisor.ModeSupervisor`. Converts the
detections to {I} (bearings: optical -> body FRD by the camera mount R_BC of vehicle.yaml ->
{I} by the latest IMU attitude; flows: map -> {I}) and calls the core's ``on_*`` with the
message stamps; a timer calls ``update(now)`` (node clock: sim time under use_sim_time) for the
triggers and the staleness rules. Publishes ``ibvs/mode`` (std_msgs/UInt8, reliable,
transient local, depth 1) at start and on every transition (each logged with its reason);
serves ``ibvs/start`` and ``ibvs/abort`` (std_srvs/Trigger, success + message from the core).

``pad/groups`` (std_msgs/String "A,B") has no header: it is paired with the ``pad/landmarks``
message whose landmark count it explains (4 per group), whichever of the two comes first.
"""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from sensor_msgs.msg import Imu
from std_msgs.msg import String, UInt8
from std_srvs.srv import Trigger

from ibvs_control.core.config import load_pad_layout, load_vehicle, load_world
from ibvs_control.core.frames import (
    bearings_C_to_I, R_IB_from_rot_map_base, rot_from_quat, vec_map_to_I)
from ibvs_control.core.modes import Mode
from ibvs_control.core.stamp_sync import (
    AttitudeHistory, check_bearings, check_vector, PadPairing)
from ibvs_control.core.supervisor import ModeSupervisor, SupervisorConfig
from ibvs_control.node_common import (
    MODE_QOS, NS_PER_S, parse_pad_groups, polygon_points, quat_wxyz, SENSOR_QOS, stamp_to_ns,
    vector3)
from ibvs_control.spin import spin_guarded

LOG_THROTTLE_S = 2.0
MAP_FRAME = 'map'
LANDMARKS_PER_GROUP = 4
ATTITUDE_HISTORY_NS = 1_000_000_000      # IMU attitudes kept to derotate at an input's stamp
# Core parameters that come from the shared YAML files, not from params.yaml.
FROM_FILES = ('r_w', 'group_half_sides')
PARAMETERS = {
    'update_rate_hz': 20.0,
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
        if not p['update_rate_hz'] > 0.0:
            raise ValueError('update_rate_hz must be > 0')
        self._core = ModeSupervisor(config)
        self._R_BC = {name: vehicle.cameras[name].R_BC for name in ('front', 'down')}
        self._attitudes = AttitudeHistory(ATTITUDE_HISTORY_NS)   # R_IB by stamp
        self._pad_pairing = PadPairing(LANDMARKS_PER_GROUP)
        self._n_reported = 0
        self._published: Mode | None = None

        self._mode_pub = self.create_publisher(UInt8, 'ibvs/mode', MODE_QOS)
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

    def _to_I(self, msg: PolygonStamped, camera: str, expected: int | None
              ) -> tuple[bool, np.ndarray | None]:
        """Validate bearings and derotate them to {I}: (usable?, bearings in {I} or None)."""
        bearings, err = check_bearings(polygon_points(msg), expected)
        if err:
            self._error(f'{camera} bearings refused: {err}')
            return False, None
        if bearings is None:
            return True, None
        R_IB = self._attitudes.at(stamp_to_ns(msg.header.stamp))   # at or just before
        if R_IB is None:
            self._error('no IMU attitude yet: cannot derotate bearings')
            return False, None
        return True, bearings_C_to_I(bearings, R_IB, self._R_BC[camera])

    # --- inputs ----------------------------------------------------------------------------
    def _on_imu(self, msg: Imu) -> None:
        try:
            R_IB = R_IB_from_rot_map_base(rot_from_quat(quat_wxyz(msg.orientation)))
        except ValueError as exc:
            self._error(f'imu/data refused: {exc}')
            return
        self._attitudes.add(stamp_to_ns(msg.header.stamp), R_IB)
        self._core.on_imu(stamp_to_ns(msg.header.stamp) / NS_PER_S, R_IB)

    def _on_window(self, msg: PolygonStamped) -> None:
        ok, corners_I = self._to_I(msg, 'front', expected=4)
        if ok:
            t = stamp_to_ns(msg.header.stamp) / NS_PER_S
            self._core.on_window(t, corners_I)
            self._update(t)

    def _on_landmarks(self, msg: PolygonStamped) -> None:
        ok, landmarks_I = self._to_I(msg, 'down', expected=None)
        if ok:
            self._pad_pairing.add_landmarks(stamp_to_ns(msg.header.stamp) / NS_PER_S,
                                            landmarks_I)
        else:
            self._pad_pairing.drop_landmarks()

    def _on_groups(self, msg: String) -> None:
        pair = self._pad_pairing.add_groups(parse_pad_groups(msg.data))
        if pair is not None:
            t, landmarks_I, groups = pair
            self._core.on_pad(t, landmarks_I, list(groups))
            self._update(t)

    def _on_front_flow(self, msg: Vector3Stamped) -> None:
        self._on_flow('front', msg)

    def _on_down_flow(self, msg: Vector3Stamped) -> None:
        self._on_flow('down', msg)

    def _on_flow(self, camera: str, msg: Vector3Stamped) -> None:
        phi, err = check_vector(vector3(msg.vector))
        if err or msg.header.frame_id != MAP_FRAME:
            self._error(f'{camera} flow refused: {err or "frame " + msg.header.frame_id}')
            return
        t = stamp_to_ns(msg.header.stamp) / NS_PER_S
        self._core.on_flow(t, camera, vec_map_to_I(phi))
        self._update(t)

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

    def _update(self, t: float) -> None:
        """Evaluate the triggers at ``t`` and publish what changed.

        Called with each input's stamp, so that a transition happens at the frame whose input
        caused it whatever the scheduling (lockstep runs repeat), and by the timer with the
        node clock, so that staleness is detected when inputs stop.
        """
        if self._core.update(t):
            self._publish_mode()

    def _on_timer(self) -> None:
        self._update(self._now())


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
