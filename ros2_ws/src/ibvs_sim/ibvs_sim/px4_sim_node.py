"""ROS 2 node ``px4_sim``: both cameras rendered from PX4 SIH's ground truth (``px4-sih`` mode).

PX4 SITL with its SIH simulator is the plant and the autopilot; this node integrates no
physics and emulates no autopilot. It reads SIH's HIL_STATE_QUATERNION on ``state_url``, maps
it to {I} and publishes on the system clock (no ``/clock``) the ground truth, both cameras on
their 50 Hz grid, contact events and ``sim/stats``. Parameters:
:class:`~ibvs_sim.config.Px4SimNodeConfig`; docs/px4_sih.md.
"""
from __future__ import annotations

import json
import time

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from ibvs_common.dds_profile import use_dds_profile_here
from ibvs_common.core.config import ConfigError, load_pad_layout, load_vehicle
from ibvs_common.core.stamps import NS_PER_S, stamp_to_ns
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node
from ibvs_sim.config import CAMERAS, Px4SimNodeConfig
from ibvs_sim.core.px4_plant import (ContactWatch, FrameClock, hil_state_sample, MocapRelay,
                                     NedToI, PositionFilter, px4_home, Px4PlantError, StateLink)
from ibvs_sim.core.render import SceneRenderer
from ibvs_sim.core.sensor_noise import ReadNoise
from ibvs_sim.core.timing import AnswerLatency
from ibvs_sim.core.world import load_world
from ibvs_sim.messages import camera_info_msg, image_msg, odometry_msg, stamp_from_ns

NODE_NAME = 'px4_sim'
LOG_THROTTLE_S = 2.0
EVENTS_DEPTH = 20
RELIABLE_DEPTH = 10
STATS_PERIOD_S = 1.0          # s (steady clock), sim/stats


class Px4SimNode(Node):
    """Render both cameras from PX4 SIH's ground truth; publish it, contacts and timing."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        cfg = declare_config(self, Px4SimNodeConfig)   # ValueError: a bad parameter
        self.cfg = cfg
        self.home = px4_home(cfg.home_lat_deg, cfg.home_lon_deg, cfg.home_alt_m)
        world = load_world(cfg.world_file or None)
        pad = load_pad_layout(cfg.pad_layout_file or None)
        vehicle = load_vehicle(cfg.vehicle_file or None)
        self.cameras = {name: vehicle.cameras[name] for name in CAMERAS}
        start = (tuple(float(x) for x in cfg.initial_position_I) if cfg.initial_override
                 else tuple(world.initial_position_I))
        self.frame = NedToI.from_start(start, world.floor_z, cfg.rest_height_m)
        self.renderers = {n: SceneRenderer(world, pad, vehicle.cameras[n]) for n in CAMERAS}
        self.read_noise = {n: ReadNoise(cfg.camera_read_noise_std,
                                        (vehicle.cameras[n].model.height,
                                         vehicle.cameras[n].model.width), cfg.seed, n)
                           for n in CAMERAS}
        self.filter = PositionFilter(cfg.position_filter_tau_s)
        self.contacts = ContactWatch(world, vehicle.envelope_radius, vehicle.envelope_height,
                                     cfg.airborne_clearance_m)
        self.mocap = MocapRelay(self.home, cfg.mocap_rate_hz) if cfg.mocap_rate_hz > 0 else None
        self.link = StateLink(cfg.state_url, cfg.state_rate_hz, threaded=True, relay=self.mocap)
        self.frames = FrameClock(self.cameras['down'].rate_hz, time.time_ns())
        self.latency = AnswerLatency()
        self.latest = None              # (TruthSample, receipt ns, system clock)
        self.frames_published = 0
        self.frames_stale = 0
        self.bad_samples = 0
        self.render_s: list[float] = []
        reliable = QoSProfile(depth=RELIABLE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=EVENTS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.image_pubs = {n: self.create_publisher(Image, f'{n}_camera/image_raw',
                                                    qos_profile_sensor_data) for n in CAMERAS}
        self.info_pubs = {n: self.create_publisher(CameraInfo, f'{n}_camera/camera_info',
                                                   reliable) for n in CAMERAS}
        self.odom_pub = self.create_publisher(Odometry, 'sim/ground_truth/odom', reliable)
        self.events_pub = self.create_publisher(String, 'sim/events', latched)
        self.stats_pub = self.create_publisher(DiagnosticArray, 'sim/stats', QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.create_subscription(Vector3Stamped, 'ibvs/force_setpoint', self._on_force,
                                 qos_profile_sensor_data)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # sim/stats from the tick itself: a 2 ms timer whose callback renders for tens of ms
        # starved a second timer (measured: sim/stats stopped while frames went on)
        self.create_timer(cfg.tick_period_s, self._on_tick, clock=steady)
        self._stats_due = time.monotonic() + STATS_PERIOD_S
        self.get_logger().info(
            f'px4_sim: ground truth from {cfg.state_url} at {cfg.state_rate_hz:g} Hz; PX4 '
            f'home {self.home} = {{I}} {list(self.frame.origin_I)} (take-off point below the '
            f'start {list(start)}); system clock, no /clock; motion capture to PX4 '
            + (f'at {cfg.mocap_rate_hz:g} Hz' if self.mocap else 'off'))

    def _on_force(self, msg: Vector3Stamped) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self.latency.answered(stamp_ns // 1_000_000, time.time_ns() / NS_PER_S)

    def _on_tick(self) -> None:
        if time.monotonic() >= self._stats_due:
            self._stats_due = time.monotonic() + STATS_PERIOD_S
            self._publish_stats()
        for m, receipt_ns in self.link.poll():
            self._on_state(m, receipt_ns)
        now_ns = time.time_ns()
        frame_ns = self.frames.due(now_ns)
        if frame_ns is None:
            return
        if self.latest is None or now_ns - self.latest[1] > self.cfg.state_timeout_s * 1e9:
            self.frames_stale += 1
            self.get_logger().warning(
                f'no ground truth from PX4 for {self.cfg.state_timeout_s} s: frame not '
                f'rendered ({self.frames_stale} so far; is PX4 SIH running on '
                f'{self.cfg.state_url}?)', throttle_duration_sec=LOG_THROTTLE_S)
            return
        sample, receipt_ns = self.latest
        state = sample.extrapolated((frame_ns - receipt_ns) / NS_PER_S)
        t0 = time.perf_counter()
        stamp = stamp_from_ns(frame_ns)
        for name, renderer in self.renderers.items():
            try:
                img = self.read_noise[name].apply(renderer.render(state.R_IB, state.xi_I),
                                                  self.frames_published)
            except ValueError as exc:           # RenderError: a pose the renderer refuses
                self.get_logger().error(f'frame not rendered: {exc}',
                                        throttle_duration_sec=LOG_THROTTLE_S)
                return
            cam = self.cameras[name]
            self.info_pubs[name].publish(camera_info_msg(cam.model, stamp, cam.frame_id))
            self.image_pubs[name].publish(image_msg(img, stamp, cam.frame_id))
        self.render_s = (self.render_s + [time.perf_counter() - t0])[-500:]
        self.frames_published += 1
        self.latency.published(frame_ns, frame_ns / NS_PER_S)

    def _on_state(self, msg, receipt_ns: int) -> None:
        try:
            raw = hil_state_sample(msg, self.home, self.frame)
            p = self.filter.update(receipt_ns / NS_PER_S, raw.p_ned_raw, raw.v_I)
            sample = hil_state_sample(msg, self.home, self.frame, p_ned=p)
        except (Px4PlantError, AttributeError, TypeError) as exc:
            self.bad_samples += 1
            self.get_logger().warning(f'HIL_STATE_QUATERNION ignored: {exc}',
                                      throttle_duration_sec=LOG_THROTTLE_S)
            return
        self.latest = (sample, receipt_ns)
        self.odom_pub.publish(odometry_msg(sample.state(), stamp_from_ns(receipt_ns)))
        event = self.contacts.check(receipt_ns / NS_PER_S, sample.xi_I, sample.v_I)
        if event is not None:
            self.events_pub.publish(String(data=json.dumps(event.to_dict())))
            self.get_logger().info(f'event: {event.to_dict()}')

    def _publish_stats(self) -> None:
        """sim/stats: frames published, dropped, stale; ground-truth rate; latency."""
        render = np.asarray(self.render_s) * 1e3
        values = {'pacing': 'px4_sih', 'frames_due': self.frames.due_count,
                  'frames_dropped': self.frames.dropped, 'frames_stale': self.frames_stale,
                  'ground_truth_rate_hz': round(self.link.measured_rate_hz(), 2),
                  'ground_truth_samples': self.link.received,
                  'ground_truth_bad': self.bad_samples,
                  'interval_requests': self.link.requests,
                  'mocap_sent': self.mocap.sent if self.mocap else 0,
                  'render_median_ms': float(np.median(render)) if render.size else None,
                  **self.latency.stats()}
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if self.frames.dropped else DiagnosticStatus.OK,
            name='sim: timing', message=f'{self.frames_published} frames published, '
            f'{self.frames.dropped} dropped',
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp_from_ns(time.time_ns())
        self.stats_pub.publish(msg)

    def destroy_node(self) -> None:
        """Close the ground-truth socket, then destroy the node."""
        self.link.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the node until Ctrl-C."""
    # an image publisher like the sim: its shared-memory segment holds the images it sends
    use_dds_profile_here()
    run_node(Px4SimNode, NODE_NAME, args, refuse=(ConfigError, ValueError, OSError))


if __name__ == '__main__':
    main()
