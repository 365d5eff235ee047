"""ROS 2 node ``sim``: the simulated Pelican-class quadrotor, its two cameras and its autopilot.

It IS the clock of the graph (publishes ``/clock``; every other node runs with use_sim_time).
Its own timer runs on the steady wall clock. Per camera period (20 ms of sim time) it publishes,
all stamped with the capture time: ``/clock``, ``front_camera/image_raw``,
``down_camera/image_raw`` (mono8, sensor-data QoS), their ``camera_info``,
``sim/ground_truth/odom`` (evaluation only) and, when they happen, contact events on
``sim/events`` (JSON in std_msgs/String, transient local). The autopilot speaks MAVLink on
``mavlink_url``. Pacing, wind, the cameras' read noise (``camera_read_noise_std``: no two
frames are bit-identical, as with a real sensor) and the initial condition are parameters
(docs/interfaces.md); so are the test-only faults (camera off or frozen, IMU off or NaN:
``fault_*``).

In lockstep the node is the test harness's clock, and only it waits: a frame's images leave
once ``imu/data`` (the bridge's, from this autopilot's telemetry) has reached the frame's
time, as a camera-IMU synchronised vehicle delivers them, so that the graph's attitude at the
stamp is the same in every run (:class:`~ibvs_sim.core.graph_sync.ImuBeforeImages`); then the
next 20 ms are simulated only after the graph answered the frame and published all its
products (:class:`~ibvs_sim.core.graph_sync.GraphProducts`: the supervisor's status of the
frame, then the detections and flows of the cameras that went out that the frame's mode
uses, including those it does not wait for). Both waits end after
``lockstep_timeout_s`` of wall clock (a dead node). The flight path has no wait of its own.
"""
from __future__ import annotations

import json
import time

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import String

from ibvs_common.core.camera import CameraModel
from ibvs_common.core.config import ConfigError, load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import (quat_from_rot, quat_wxyz_to_xyzw, rot_map_base_from_R_IB,
                                     vec_frd_to_flu, vec_I_to_map)
from ibvs_sim.config import CAMERAS, SimNodeConfig
from ibvs_sim.core.autopilot import Autopilot
from ibvs_sim.core.dynamics import State
from ibvs_sim.core.graph_sync import (FirstFrameHold, GraphProducts, ImuBeforeImages,
                                      STATUS_TOPIC)
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import FrameOutput, Simulation
from ibvs_sim.core.timing import AnswerLatency, wall_budget
from ibvs_common.core.modes import InputKind, modes_using
from ibvs_common.core.stamps import NS_PER_S
from ibvs_common.dds_profile import use_dds_profile_here
from ibvs_common.node_common import mode_from_status, stamp_to_ns
from ibvs_common.param_descriptors import declare_config
from ibvs_common.spin import run_node

NODE_NAME = 'sim'
MAP_FRAME = 'map'
BASE_FRAME = 'base_link'
MONO8 = 'mono8'
LOG_THROTTLE_S = 2.0
EVENTS_DEPTH = 20
RELIABLE_DEPTH = 10
SUBSCRIBER_SETTLE_S = 2.0     # s (wall), image subscribers and setpoints this long before frame 0:
#                               the other topics' discovery completes meanwhile (0.5 s lost the
#                               window detections of frames 0 and 1 in one lockstep start of 6)
STATS_PERIOD_S = 1.0          # s (wall), sim/stats
CLOCK_REPEAT_S = 0.1          # s (wall), /clock repeated while sim time stands still: a node
#                               whose /clock subscription matched late still learns the time
FAULT_ANSWER_WAIT_S = 0.3     # s (wall), lockstep: wait for the answer to (and the products of)
#                               a frame with images off or frozen (the graph may not answer it)
# lockstep: what the graph publishes for each camera frame (docs/interfaces.md), by camera
GRAPH_PRODUCTS = {'window/corners': (PolygonStamped, 'front'),
                  'front_camera/translational_flow': (Vector3Stamped, 'front'),
                  'pad/landmarks': (PolygonStamped, 'down'),
                  'pad/groups': (JointState, 'down'),
                  'down_camera/translational_flow': (Vector3Stamped, 'down')}
# the product behind each topic: its node computes it only in the modes that use it
PRODUCT_KINDS = {'window/corners': InputKind.WINDOW,
                 'front_camera/translational_flow': InputKind.FLOW_FRONT,
                 'pad/landmarks': InputKind.PAD, 'pad/groups': InputKind.PAD,
                 'down_camera/translational_flow': InputKind.FLOW_DOWN}


def stamp_from_ns(t_ns: int) -> Time:
    """builtin_interfaces/Time of a sim time in integer nanoseconds."""
    return Time(sec=int(t_ns // NS_PER_S), nanosec=int(t_ns % NS_PER_S))


def image_msg(img: np.ndarray, stamp: Time, frame_id: str) -> Image:
    """Mono8 sensor_msgs/Image from an (H, W) uint8 array."""
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = MONO8
    msg.is_bigendian = 0
    msg.step = int(img.shape[1])
    msg.data = np.ascontiguousarray(img).tobytes()
    return msg


def camera_info_msg(model: CameraModel, stamp: Time, frame_id: str) -> CameraInfo:
    """Build the CameraInfo of a calibrated camera: K, D, R = I, P = [K | 0]."""
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = model.width, model.height
    msg.distortion_model = model.distortion_model
    msg.d = [float(x) for x in model.D]
    msg.k = [float(x) for x in model.K.ravel()]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    P = np.hstack([model.K, np.zeros((3, 1))])
    msg.p = [float(x) for x in P.ravel()]
    return msg


def odometry_msg(state: State, stamp: Time) -> Odometry:
    """Build the ground truth as nav_msgs/Odometry (map ENU / base_link FLU).

    Pose of base_link in map; twist in base_link (Odometry's convention: child frame).
    """
    R_map_base = rot_map_base_from_R_IB(state.R_IB)
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = MAP_FRAME
    msg.child_frame_id = BASE_FRAME
    p = vec_I_to_map(state.xi_I)
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = map(float, p)
    q = quat_wxyz_to_xyzw(quat_from_rot(R_map_base))
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q)
    v_base = R_map_base.T @ vec_I_to_map(state.v_I)
    w_base = vec_frd_to_flu(state.Omega_B)
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    lin.x, lin.y, lin.z = map(float, v_base)
    ang.x, ang.y, ang.z = map(float, w_base)
    return msg


class SimNode(Node):
    """Publish camera frames, camera info, ground truth and /clock from :class:`Simulation`."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        cfg = declare_config(self, SimNodeConfig)      # ValueError: a bad parameter
        world = load_world(cfg.world_file or None)
        pad = load_pad_layout(cfg.pad_layout_file or None)
        vehicle = load_vehicle(cfg.vehicle_file or None)
        self.cameras = {name: vehicle.cameras[name] for name in CAMERAS}
        self.autopilot = Autopilot(cfg.autopilot_config(vehicle, world.floor_z))
        products = GraphProducts({t: cam for t, (_, cam) in GRAPH_PRODUCTS.items()},
                                 {t: modes_using(k) for t, k in PRODUCT_KINDS.items()})
        sim_config = cfg.sim_config(self.cameras['down'].rate_hz)
        self.sim = Simulation(world, pad, vehicle, self.autopilot, sim_config,
                              products=products, clock_sink=self._publish_clock)
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
        self.latency = AnswerLatency()
        self.faults = cfg.camera_faults()
        self._clock_ns = -1
        self._clock_wall = 0.0
        self._ended_logged = False
        self._events_published = 0
        self._first_frame_wall: float | None = None   # steady s, frame 0 published
        self._publish_wall_s = 0.0                     # perf_counter s spent publishing
        self.imu_hold = ImuBeforeImages(sim_config.lockstep_timeout_s,
                                        enabled=sim_config.pacing is Pacing.LOCKSTEP)
        if self.imu_hold.enabled:
            self.create_subscription(Imu, 'imu/data', self._on_imu, qos_profile_sensor_data)
            for topic, (msg_type, _) in GRAPH_PRODUCTS.items():
                self.create_subscription(msg_type, topic, self._product_callback(topic),
                                         qos_profile_sensor_data)
            self.create_subscription(DiagnosticArray, STATUS_TOPIC, self._on_status, reliable)
        min_counts = {n: cfg.min_image_subscribers for n in self.image_pubs}
        self.first_frame_hold = FirstFrameHold(
            min_counts, SUBSCRIBER_SETTLE_S, cfg.subscriber_wait_timeout_s, time.monotonic(),
            need_setpoints=cfg.start_on_setpoints)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = self.create_timer(cfg.tick_period_s, self._on_tick, clock=steady)
        self.create_timer(STATS_PERIOD_S, self._publish_stats, clock=steady)
        self.get_logger().info(
            f'sim: {cfg.pacing} pacing (real-time factor {cfg.real_time_factor:g}), '
            f'MAVLink {cfg.mavlink_url}, start at '
            f'{self.sim.state.xi_I.tolist()} ({{I}}, m), wind {tuple(cfg.wind_force_map)} N (map)')

    def _first_frame_may_go(self) -> bool:
        """Ask the hold (core) with the subscriber counts; log the wait and a timeout."""
        counts = {n: pub.get_subscription_count() for n, pub in self.image_pubs.items()}
        streaming = self.sim.poll_before_start()
        state = (f'subscribers {counts} (needed {self.first_frame_hold.min_counts}), '
                 f'setpoints streaming: {streaming}')
        if self.first_frame_hold.ready(counts, time.monotonic(), streaming):
            if self.first_frame_hold.timed_out:
                self.get_logger().warning(f'frame 0 goes without its whole graph: {state}')
            return True
        self.get_logger().info(f'frame 0 waits for the graph: {state}',
                               throttle_duration_sec=LOG_THROTTLE_S)
        return False

    def _on_imu(self, msg: Imu) -> None:
        self.imu_hold.note_imu(stamp_to_ns(msg.header.stamp))

    def _on_status(self, msg: DiagnosticArray) -> None:
        stamp_ns, mode, err = mode_from_status(msg)
        if not err:
            self.sim.lockstep.products.note_status(stamp_ns, mode)

    def _product_callback(self, topic: str):
        def note(msg: PolygonStamped | Vector3Stamped | JointState) -> None:
            stamp_ns = stamp_to_ns(msg.header.stamp)
            if self.sim.lockstep.products.note(topic, stamp_ns):
                self.get_logger().info(
                    f'lockstep: {topic} published again (stamp t = {stamp_ns / NS_PER_S:.3f} '
                    f's, sim t = {self.sim.t:.3f} s): waited for again')
        return note

    def _on_tick(self) -> None:
        if not self.first_frame_hold.released and not self._first_frame_may_go():
            return
        held = self.imu_hold.release(time.monotonic())
        if held is not None:
            if self.imu_hold.timed_out:
                self.get_logger().warning(
                    f'lockstep: imu/data did not reach t = {held.t:.3f} s within '
                    f'{self.imu_hold.timeout_s} s (wall): frame published without it',
                    throttle_duration_sec=LOG_THROTTLE_S)
            self._publish(held)
        if self.imu_hold.holding:
            return
        timeouts_before = self.sim.lockstep.timeouts
        dropped_before = self.sim.realtime.frames_dropped
        given_up_before = len(self.sim.lockstep.given_up)
        try:
            out = self.sim.tick()
        except ValueError as exc:   # RenderError, non-finite state: stop, do not publish NaN
            self.sim.ended = True
            self.get_logger().error(f'simulation stopped: {exc}',
                                    throttle_duration_sec=LOG_THROTTLE_S)
            return
        if self.sim.lockstep.timeouts > timeouts_before:
            self.get_logger().warning(
                f'lockstep: no setpoint answered a frame within '
                f'{self.sim.config.lockstep_timeout_s} s (wall): simulated up to '
                f't = {self.sim.t:.3f} s with the last one; {self.sim.lockstep.timeouts} '
                'time-outs so far (the run no longer repeats exactly)',
                throttle_duration_sec=LOG_THROTTLE_S)
        if len(self.sim.lockstep.given_up) > given_up_before:
            self.get_logger().warning(
                f'lockstep: {", ".join(self.sim.lockstep.given_up[given_up_before:])} not '
                f'published within {self.sim.lockstep.answer_wait_s} s (wall) of the frame at t = '
                f'{(self.sim.lockstep.products.frame_ns or 0) / NS_PER_S:.3f} s: no longer '
                'waited for until it comes again')
        if self.sim.realtime.frames_dropped > dropped_before:
            self.get_logger().warning(
                f'free-running: could not render on time at t = {self.sim.t:.3f} s: '
                f'{self.sim.realtime.frames_dropped} frame(s) dropped so far (lower '
                'real_time_factor)',
                throttle_duration_sec=LOG_THROTTLE_S)
        answers = self.sim.autopilot.new_setpoints
        while answers:
            self.latency.answered(*answers.popleft())
        if self.sim.config.pacing is Pacing.REALTIME or self._clock_ns >= 0:
            # free-running: /clock runs on between frames; lockstep: repeated while it waits
            self._publish_clock(self.sim.t_ns if self.sim.config.pacing is Pacing.REALTIME
                                else self._clock_ns)
        if out is not None:
            # an injected IMU fault: imu/data will not reach the frame, do not wait for it
            if not self.autopilot.config.imu_fault_at(out.t):
                out = self.imu_hold.hold(out, time.monotonic())
            if out is not None:
                self._publish(out)
        elif self.sim.ended and not self._ended_logged:
            self._ended_logged = True
            for event in self.sim.events[self._events_published:]:
                self._publish_event(event)
            self.get_logger().error(
                f'run ended at t = {self.sim.t:.3f} s: '
                f'{self.sim.events[-1].to_dict() if self.sim.events else "(no event)"}')

    def _publish_clock(self, t_ns: int) -> None:
        """Publish /clock when time moved, or again after CLOCK_REPEAT_S of wall clock."""
        now = time.monotonic()
        if t_ns > self._clock_ns or (t_ns == self._clock_ns
                                     and now - self._clock_wall >= CLOCK_REPEAT_S):
            self._clock_ns, self._clock_wall = t_ns, now
            self.clock_pub.publish(ClockMsg(clock=stamp_from_ns(t_ns)))

    def _publish_stats(self) -> None:
        """sim/stats: frames published, dropped, answered, the image -> setpoint latency.

        Also the autopilot's own TIMESYNC requests and the bridge's answers to them (checked:
        ts1 one of the requests), as PX4 asks.
        """
        counters = self.autopilot.counters
        values = {'pacing': self.sim.config.pacing.value,
                  'real_time_factor': self.sim.config.real_time_factor,
                  'sim_time_s': self.sim.t, 'frames_dropped': self.sim.realtime.frames_dropped,
                  'stalls': self.sim.realtime.stalls,
                  'lockstep_timeouts': self.sim.lockstep.timeouts,
                  'products_given_up': len(self.sim.lockstep.given_up),
                  'imu_hold_timeouts': self.imu_hold.timeouts,
                  'autopilot_timesync_requests': counters.timesync_requests_sent,
                  'autopilot_timesync_answers': counters.timesync_answers_received,
                  'autopilot_timesync_foreign': counters.timesync_answers_foreign,
                  **self.latency.stats(),
                  **self._wall_budget()}
        status = DiagnosticStatus(
            level=(DiagnosticStatus.WARN if self.sim.realtime.frames_dropped
                   else DiagnosticStatus.OK),
            name='sim: timing', message=f"{values['frames_published']} frames published, "
            f"{self.sim.realtime.frames_dropped} dropped",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp_from_ns(self.sim.t_ns)
        self.stats_pub.publish(msg)

    def _wall_budget(self) -> dict:
        """Where the wall clock went since frame 0 (``timing.wall_budget``)."""
        if self._first_frame_wall is None:
            return {}
        return wall_budget(time.monotonic() - self._first_frame_wall, self.latency.frames, {
            'physics': self.sim.physics.wall_s, 'render': self.sim.cameras.wall_s,
            'publish': self._publish_wall_s, 'imu_hold': self.imu_hold.held_s})

    def _publish(self, out: FrameOutput) -> None:
        t0 = time.perf_counter()
        if self._first_frame_wall is None:
            self._first_frame_wall = time.monotonic()
        try:
            self._publish_frame(out)
        finally:
            self._publish_wall_s += time.perf_counter() - t0

    def _publish_frame(self, out: FrameOutput) -> None:
        stamp = stamp_from_ns(out.t_ns)
        # a guard, no-op as the sim runs: the clock already moved to the frame's time
        # (lockstep: Simulation.clock_sink before the frame's telemetry; realtime: each tick)
        self._publish_clock(out.t_ns)
        images, withheld, frozen = self.faults.apply(out.t, out.images)
        # lockstep: the graph may have nothing to answer (its mode's camera is off), or drop
        # a frozen camera's images (its products are then given up after this short wait)
        imu_fault = self.autopilot.config.imu_fault_at(out.t)
        self.sim.lockstep.answer_wait_s = (FAULT_ANSWER_WAIT_S if withheld or frozen
                                           or imu_fault else self.sim.config.lockstep_timeout_s)
        if imu_fault:
            self.get_logger().warning(f'fault injection: IMU {imu_fault} at t = {out.t:.3f} s',
                                      throttle_duration_sec=LOG_THROTTLE_S)
        if withheld:
            self.get_logger().warning(f'fault injection: {", ".join(withheld)} camera off at '
                                      f't = {out.t:.3f} s', throttle_duration_sec=LOG_THROTTLE_S)
        if frozen:
            self.get_logger().warning(
                f'fault injection: {", ".join(frozen)} camera frozen at t = {out.t:.3f} s: '
                f'its image of t = {self.faults.held[frozen[0]][0]:.3f} s again, new stamp',
                throttle_duration_sec=LOG_THROTTLE_S)
        for name, img in images.items():
            cam = self.cameras[name]
            self.info_pubs[name].publish(camera_info_msg(cam.model, stamp, cam.frame_id))
            self.image_pubs[name].publish(image_msg(img, stamp, cam.frame_id))
        self.latency.published(out.t_ns, time.monotonic())
        self.odom_pub.publish(odometry_msg(out.state, stamp))
        for event in out.events:
            self._publish_event(event)
        if self.imu_hold.enabled:
            cameras = list(images)
            self.sim.lockstep.products.expect(out.t_ns, cameras,
                                              {t: self.count_publishers(t)
                                               for t in (*GRAPH_PRODUCTS, STATUS_TOPIC)})

    def _publish_event(self, event) -> None:
        self._events_published += 1
        self.events_pub.publish(String(data=json.dumps(event.to_dict())))
        self.get_logger().info(f'event: {event.to_dict()}')

    def destroy_node(self) -> None:
        """Close the MAVLink endpoint, then destroy the node."""
        self.autopilot.close()
        self.sim.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the sim node until Ctrl-C (demo_nodes_py pattern)."""
    # the images' shared-memory segment is the sim's: lossless under a plain `ros2 run` too
    use_dds_profile_here()
    run_node(SimNode, NODE_NAME, args, refuse=(ConfigError, ValueError, OSError))


if __name__ == '__main__':
    main()
