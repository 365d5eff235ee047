"""ROS 2 node ``sim``: the simulated quadrotor, its two cameras and its autopilot (docs/sim.md).

A thin wrapper over :class:`~ibvs_sim.driver.SimDriver`: parameters
(:class:`~ibvs_sim.config.SimNodeConfig`), publishers, the lockstep's subscriptions and a
steady-clock timer. It is the clock of the graph (``/clock``; the other nodes use sim time)
and publishes, stamped with each frame's capture time, ``front_camera/image_raw`` and
``down_camera/image_raw`` (mono8, sensor-data QoS), their ``camera_info``,
``sim/ground_truth/odom`` (evaluation only), contact events on ``sim/events`` (JSON, transient
local) and its timing on ``sim/stats``. The autopilot speaks MAVLink on ``mavlink_url``.
"""
from __future__ import annotations

import json

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import Bool, String

from ibvs_common.core.config import ConfigError, load_pad_layout, load_vehicle
from ibvs_common.dds_profile import use_dds_profile_here
from ibvs_common.node_common import grid_from_msg, MODE_QOS, mode_from_status, stamp_to_ns
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_sim.config import CAMERAS, SimNodeConfig
from ibvs_sim.core.dynamics import State
from ibvs_sim.core.events import SimEvent
from ibvs_sim.core.graph_sync import STATUS_TOPIC
from ibvs_sim.core.world import load_world
from ibvs_sim.driver import SimDriver
from ibvs_sim.messages import camera_info_msg, image_msg, odometry_msg, stamp_from_ns

NODE_NAME = 'sim'
EVENTS_DEPTH = 20
RELIABLE_DEPTH = 10
STATS_PERIOD_S = 1.0          # s (wall), sim/stats
# lockstep: the message type of each product of the graph (graph_sync.PRODUCT_CAMERAS)
PRODUCT_TYPES = {'window/corners': PolygonStamped,
                 'front_camera/translational_flow': Vector3Stamped,
                 'pad/landmarks': PolygonStamped, 'pad/groups': JointState,
                 'down_camera/translational_flow': Vector3Stamped}


class SimNode(Node):
    """Messages in and out of :class:`~ibvs_sim.driver.SimDriver`, its parameters and timers."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        cfg = declare_config(self, SimNodeConfig)      # ValueError: a bad parameter
        world = load_world(cfg.world_file or None)
        pad = load_pad_layout(cfg.pad_layout_file or None)
        # the calibration the onboard nodes were given (camera_info), and the truth the sim
        # flies and renders (docs/sim.md "Camera model")
        vehicle = load_vehicle(cfg.vehicle_file or None)
        truth = load_vehicle(cfg.true_vehicle_file or cfg.vehicle_file or None)
        self.cameras = {name: vehicle.cameras[name] for name in CAMERAS}
        for name in CAMERAS:
            onboard, true = vehicle.cameras[name].model, truth.cameras[name].model
            if (onboard.width, onboard.height) != (true.width, true.height):
                raise ConfigError(f'{name} camera: the true vehicle file renders '
                                  f'{true.width}x{true.height} images, the calibration '
                                  f'describes {onboard.width}x{onboard.height}')
        reliable = QoSProfile(depth=RELIABLE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=EVENTS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.image_pubs = {n: self.create_publisher(Image, f'{n}_camera/image_raw',
                                                    qos_profile_sensor_data) for n in CAMERAS}
        self.info_pubs = {n: self.create_publisher(CameraInfo, f'{n}_camera/camera_info',
                                                   reliable) for n in CAMERAS}
        self.odom_pub = self.create_publisher(Odometry, 'sim/ground_truth/odom', reliable)
        self.clock_pub = self.create_publisher(ClockMsg, '/clock', reliable)
        self.events_pub = self.create_publisher(String, 'sim/events', latched)
        self.stats_pub = self.create_publisher(DiagnosticArray, 'sim/stats', QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.driver = SimDriver(world, pad, truth, cfg, port=self, log=self.get_logger())
        self.sim, self.autopilot = self.driver.sim, self.driver.autopilot
        if self.driver.imu_hold.enabled:
            self.create_subscription(Imu, 'imu/data', self._on_imu, qos_profile_sensor_data)
            for topic, msg_type in PRODUCT_TYPES.items():
                self.create_subscription(msg_type, topic, self._product_callback(topic),
                                         qos_profile_sensor_data)
        # the graph's modes and frame grids: which frames it computes (lockstep owes no wait
        # to the others; sim/stats counts the answers of those it computes in either pacing)
        self.create_subscription(DiagnosticArray, STATUS_TOPIC, self._on_status, reliable)
        self.create_subscription(DiagnosticArray, 'ibvs/frame_grid', self._on_grid, MODE_QOS)
        # the pilot's hand on the radio's mission switch (pilot_switch_channel)
        self.create_subscription(Bool, 'sim/pilot_switch', self._on_pilot_switch, reliable)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = self.create_timer(cfg.tick_period_s, self.driver.tick, clock=steady)
        self.create_timer(STATS_PERIOD_S, self._publish_stats, clock=steady)
        self.get_logger().info(
            f'sim: {cfg.pacing} pacing (real-time factor {cfg.real_time_factor:g}), '
            f'MAVLink {cfg.mavlink_url}, start at '
            f'{self.sim.state.xi_I.tolist()} ({{I}}, m), wind {tuple(cfg.wind_force_map)} N (map)')
        for name, timing in self.sim.config.timings().items():
            self.get_logger().info(
                f'{name} camera: {timing.rate_hz:g} Hz, latency {timing.latency_s * 1e3:g} ms, '
                f'jitter {timing.jitter_s * 1e3:g} ms ({timing.jitter.value}), drop '
                f'{timing.drop_probability:g}, exposure {timing.exposure_s * 1e3:g} ms '
                f'({timing.exposure_samples} renders), stamp at {timing.stamp_at.value}, time '
                f'offset {timing.time_offset_s * 1e3:g} ms, lever arm '
                f'{truth.cameras[name].t_BC.tolist()} m (true vehicle '
                f"{cfg.true_vehicle_file or cfg.vehicle_file or 'vehicle.yaml'})")

    # --- in ---
    def _on_pilot_switch(self, msg: Bool) -> None:
        """sim/pilot_switch: the pilot flips the radio's mission switch ON (true) or OFF."""
        why = self.driver.flip_pilot_switch(bool(msg.data))
        if why:
            self.get_logger().error(f'sim/pilot_switch ignored: {why}')
        else:
            self.get_logger().info(f'pilot switch {"ON" if msg.data else "OFF"} at sim t = '
                                   f'{self.sim.t:.3f} s')

    def _on_imu(self, msg: Imu) -> None:
        self.driver.note_imu(stamp_to_ns(msg.header.stamp))

    def _on_status(self, msg: DiagnosticArray) -> None:
        stamp_ns, mode, err = mode_from_status(msg)
        if not err:
            self.driver.note_status(stamp_ns, mode)

    def _on_grid(self, msg: DiagnosticArray) -> None:
        """ibvs/frame_grid: which frames the graph computes (lockstep owes no wait to others)."""
        for camera in self.cameras:
            for flow in (False, True):
                grid = grid_from_msg(msg, camera, flow)
                if grid is not None:
                    self.driver.note_grid(camera, *grid, flow=flow)

    def _product_callback(self, topic: str):
        def note(msg: PolygonStamped | Vector3Stamped | JointState) -> None:
            self.driver.note_product(topic, stamp_to_ns(msg.header.stamp))
        return note

    # --- out (the driver's GraphPort) ---
    def publish_clock(self, t_ns: int) -> None:
        """Publish ``/clock`` at sim time ``t_ns``."""
        self.clock_pub.publish(ClockMsg(clock=stamp_from_ns(t_ns)))

    def publish_images(self, images: dict, stamps_ns: dict) -> None:
        """Publish each camera's camera_info (the onboard calibration) and image, stamped."""
        for name, img in images.items():
            cam = self.cameras[name]
            stamp = stamp_from_ns(stamps_ns[name])
            self.info_pubs[name].publish(camera_info_msg(cam.model, stamp, cam.frame_id))
            self.image_pubs[name].publish(image_msg(img, stamp, cam.frame_id))

    def publish_ground_truth(self, t_ns: int, state: State) -> None:
        """Publish the ground truth of sim time ``t_ns`` as odometry."""
        self.odom_pub.publish(odometry_msg(state, stamp_from_ns(t_ns)))

    def publish_event(self, event: SimEvent) -> None:
        """Publish a contact event as JSON."""
        self.events_pub.publish(String(data=json.dumps(event.to_dict())))

    def count_image_subscribers(self) -> dict:
        """Return camera -> the number of subscribers of its images."""
        return {n: pub.get_subscription_count() for n, pub in self.image_pubs.items()}

    def _publish_stats(self) -> None:
        """sim/stats: frames published, dropped, answered, the latency, the wall budget."""
        values = self.driver.stats()
        dropped = values['frames_dropped']
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if dropped else DiagnosticStatus.OK,
            name='sim: timing', message=f"{values['frames_published']} frames published, "
            f'{dropped} dropped',
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp_from_ns(self.sim.t_ns)
        self.stats_pub.publish(msg)

    def destroy_node(self) -> None:
        """Close the MAVLink endpoint, then destroy the node."""
        self.driver.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the sim node until Ctrl-C (demo_nodes_py pattern)."""
    # the images' shared-memory segment is the sim's: lossless under a plain `ros2 run` too
    use_dds_profile_here()
    run_node(SimNode, NODE_NAME, args, refuse=(ConfigError, ValueError, OSError))


if __name__ == '__main__':
    main()
