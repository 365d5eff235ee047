"""The ibvs_control nodes in-process with real rclpy and fake publishers.

Detections are synthesised from the reference scenario's geometry (window corners of
world.yaml, pad marker centres of pad_layout.yaml) along a straight-line trajectory, rotated
into the camera optical frames with the mounts of vehicle.yaml.
"""
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point32, PolygonStamped, QuaternionStamped, Vector3Stamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Header, UInt8
from std_srvs.srv import Trigger

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_control.core.control_laws import GainError
from ibvs_common.core.frames import (
    bearings_I_to_C, GRAVITY, quat_ned_frd_to_enu_flu, vec_I_to_map)
from ibvs_control.force_controller_node import ForceControllerNode
from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode
from ibvs_control.mode_supervisor_node import ModeSupervisorNode
from ibvs_common.core.modes import Camera
from ibvs_common.node_common import (
    COMMAND_QOS, grid_from_msg, held_from_status, mode_from_status, MODE_QOS, pad_groups_msg,
    SENSOR_QOS, stamp_to_ns, superseded_msg, SUPERSEDED_TOPIC, supervisor_status_msg)

from test_control_mavlink import FakeAutopilot, PeerThread, same_rotation  # noqa: E402

VEHICLE = load_vehicle()
WORLD = load_world()
PAD = load_pad_layout()
WINDOW_I = WORLD.window.corners_I()
TAG = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'


def spin_until(executor, done, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        executor.spin_once(timeout_sec=0.01)
    return done()


def spin_for(executor, seconds):
    spin_until(executor, lambda: False, seconds)


def stamp(t):
    from builtin_interfaces.msg import Time
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def polygon(t, bearings, frame):
    msg = PolygonStamped()
    msg.header.stamp = stamp(t)
    msg.header.frame_id = frame
    msg.polygon.points = [Point32(x=float(b[0]), y=float(b[1]), z=float(b[2]))
                          for b in np.asarray(bearings, dtype=float).reshape(-1, 3)]
    return msg


def unit_rows(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def corners_C(xi, R_IB=np.eye(3)):
    return bearings_I_to_C(unit_rows(WINDOW_I - xi), R_IB, VEHICLE.cameras['front'].R_BC)


def landmarks_C(xi, names, R_IB=np.eye(3)):
    groups = [g for g in PAD.groups if g.name in names]
    pts = np.vstack([g.marker_centres_I() for g in groups])
    return (bearings_I_to_C(unit_rows(pts - xi), R_IB, VEHICLE.cameras['down'].R_BC),
            [g.name for g in groups])


def imu_msg(t, yaw=0.0):
    msg = Imu()
    msg.header.stamp = stamp(t)
    msg.header.frame_id = 'base_link'
    w, x, y, z = quat_ned_frd_to_enu_flu(np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]))
    msg.orientation.w, msg.orientation.x, msg.orientation.y, msg.orientation.z = w, x, y, z
    return msg


def flow_msg(t, phi_I, frame='map'):
    msg = Vector3Stamped()
    msg.header.stamp = stamp(t)
    msg.header.frame_id = frame
    msg.vector.x, msg.vector.y, msg.vector.z = (float(v) for v in vec_I_to_map(phi_I))
    return msg


class Feeder:
    """Fake perception + IMU (+ /clock) publishers on one test node."""

    def __init__(self, context, name):
        self.node = rclpy.create_node(name, context=context)
        n = self.node
        self.clock = n.create_publisher(Clock, '/clock', 10)
        self.imu = n.create_publisher(Imu, 'imu/data', SENSOR_QOS)
        self.corners = n.create_publisher(PolygonStamped, 'window/corners', SENSOR_QOS)
        self.landmarks = n.create_publisher(PolygonStamped, 'pad/landmarks', SENSOR_QOS)
        self.groups = n.create_publisher(JointState, 'pad/groups', SENSOR_QOS)
        self.front = n.create_publisher(Vector3Stamped, 'front_camera/translational_flow',
                                        SENSOR_QOS)
        self.down = n.create_publisher(Vector3Stamped, 'down_camera/translational_flow',
                                       SENSOR_QOS)
        self.mode = n.create_publisher(UInt8, 'ibvs/mode', MODE_QOS)
        self.modes = []
        n.create_subscription(UInt8, 'ibvs/mode', lambda m: self.modes.append(m.data),
                              MODE_QOS)
        self.forces, self.headings, self.features = [], [], []
        n.create_subscription(Vector3Stamped, 'ibvs/force_setpoint', self.forces.append,
                              COMMAND_QOS)
        n.create_subscription(QuaternionStamped, 'ibvs/heading_setpoint', self.headings.append,
                              COMMAND_QOS)
        n.create_subscription(JointState, 'ibvs/features', self.features.append, COMMAND_QOS)
        self.statuses = []
        n.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', self.statuses.append,
                              COMMAND_QOS)
        self.status = n.create_publisher(DiagnosticArray, 'ibvs/supervisor_status',
                                         COMMAND_QOS)
        self.superseded = n.create_publisher(Header, SUPERSEDED_TOPIC, COMMAND_QOS)

    def skipped(self, t, camera='front'):
        """Report the image of ``camera`` at time t skipped for a newer one (latest only)."""
        self.superseded.publish(superseded_msg(camera, round(t * 1e9)))

    def frame(self, t, xi, window=True, pad=None, front_flow=None, down_flow=None,
              groups_first=False):
        """Publish everything one camera frame at time t would produce at position xi.

        ``groups_first``: pad/groups before pad/landmarks (two topics are not ordered).
        """
        self.clock.publish(Clock(clock=stamp(t)))
        self.imu.publish(imu_msg(t))
        self.corners.publish(polygon(t, corners_C(xi) if window else [],
                                     'front_camera_optical_frame'))
        lm, names = landmarks_C(xi, pad) if pad else ([], [])
        pad_msgs = [self.landmarks, polygon(t, lm, 'down_camera_optical_frame')], \
            [self.groups, pad_groups_msg(stamp(t), 'down_camera_optical_frame', names)]
        for pub, msg in (pad_msgs[::-1] if groups_first else pad_msgs):
            pub.publish(msg)
        if front_flow is not None:
            self.front.publish(flow_msg(t, front_flow))
        if down_flow is not None:
            self.down.publish(flow_msg(t, down_flow))


def call(executor, node, srv_name):
    client = node.create_client(Trigger, srv_name)
    assert client.wait_for_service(timeout_sec=5.0)
    future = client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, 5.0)
    return future.result()


# --- mode supervisor ---------------------------------------------------------------------

def supervisor_on_sim_time(ctx, suffix):
    """A mode supervisor ``sup<suffix>`` on sim time and its Feeder, IDLE published."""
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup{suffix}_{TAG}', context=context,
                             parameter_overrides=[Parameter('use_sim_time', value=True)])
    feed = Feeder(context, f'feed{suffix}_{TAG}')
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    return sup, feed


def test_supervisor_whole_mode_sequence_on_sim_time(ctx):
    _, executor, _ = ctx
    sup, feed = supervisor_on_sim_time(ctx, '')

    dt, v = 0.02, 1.0
    t, xi = 1.0, np.array([-2.0, 0.0, -1.6])
    fed = []

    def step(**kw):   # one frame at a time: the subscriptions keep 2, a slow host drops
        nonlocal t
        feed.frame(t, xi, **kw)
        fed.append(int(round(t * 1e9)))
        assert spin_until(executor, lambda: len(feed.statuses) >= len(fed), 2.0)
        t += dt

    def d_wall():   # the front camera sees the wall, then (past it) the back wall
        return WORLD.wall_x - xi[0] if xi[0] < WORLD.wall_x else WORLD.back_wall_x - xi[0]

    for _ in range(10):
        step(front_flow=np.zeros(3))
    assert call(executor, feed.node, 'ibvs/start').success
    assert feed.modes[-1:] == [0]          # applied at the next frame, not between frames
    step(front_flow=np.zeros(3))
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)
    while d_wall() > 0.75:                 # mode 1: approach, the window fully visible
        xi = xi + [v * dt, 0, 0]
        step(front_flow=np.array([v / d_wall(), 0, 0]))
    while feed.modes[-1] != 3 and xi[0] < 1.0:   # window lost close: blind crossing
        xi = xi + [v * dt, 0, 0]
        step(window=False, pad=('A', 'B') if xi[0] > -0.3 else None,
             front_flow=np.array([v / d_wall(), 0, 0]),
             down_flow=np.array([v / -xi[2], 0, 0]))
    assert feed.modes[-1] == 3 and xi[0] > -0.2   # landing only after the crossing length
    xi = np.array([0.0, 0.0, xi[2]])
    while feed.modes[-1] != 4 and xi[2] < -0.05:  # mode 3: descend over the pad
        xi = xi + [0, 0, 0.75 * dt]
        step(window=False, pad=('A', 'B', 'C', 'D'), down_flow=np.array([0, 0, 0.75 / -xi[2]]),
             groups_first=len(fed) % 2 == 1)     # pairing is by stamp, not by arrival
    spin_for(executor, 0.1)
    assert feed.modes == [0, 1, 2, 3, 4]
    assert -xi[2] < 0.2
    assert not call(executor, feed.node, 'ibvs/start').success
    # one ibvs/supervisor_status per frame, stamped with it, carrying the mode after it
    assert spin_until(executor, lambda: len(feed.statuses) >= len(fed), 2.0)
    reported = [mode_from_status(m) for m in feed.statuses]
    assert [stamp_ns for stamp_ns, _, _ in reported] == fed
    modes = [mode for _, mode, _ in reported]
    assert sorted(set(modes)) == [0, 1, 2, 3, 4] and modes == sorted(modes)
    assert feed.statuses[-1].status[0].message == 'SHUTDOWN'


def test_supervisor_after_a_clock_step_back_idle_goes_on_and_flight_fails_safe(ctx):
    """A step back of the node clock (the system clock onboard; /clock here) is seen at once.

    IDLE: the frames after a 1 s step are evaluated as they come (before: refused as older
    than one evaluated, for the whole second). WINDOW: FAILSAFE at the next IMU sample (before:
    the inputs taken before the step looked fresh until the clock caught up, 1 s + timeouts).
    """
    _, executor, _ = ctx
    sup, feed = supervisor_on_sim_time(ctx, '_step')
    xi, t, fed = np.array([-2.0, 0.0, -1.6]), 5.0, []

    def step():
        nonlocal t
        feed.frame(t, xi, front_flow=np.zeros(3))
        fed.append(int(round(t * 1e9)))
        assert spin_until(executor, lambda: len(feed.statuses) >= len(fed), 2.0), \
            f'no status for the frame of {t:.2f} s'
        t += 0.02

    for _ in range(5):
        step()
    t -= 1.0                                         # the clock steps back by 1 s in IDLE
    for _ in range(5):
        step()
    assert [mode_from_status(m)[0] for m in feed.statuses] == fed and feed.modes == [0]
    assert call(executor, feed.node, 'ibvs/start').success
    step()                                           # the start is applied at a frame
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)
    for _ in range(5):
        step()
    t -= 1.0                                         # ... and by 1 s in WINDOW
    feed.clock.publish(Clock(clock=stamp(t)))
    feed.imu.publish(imu_msg(t))
    assert spin_until(executor, lambda: feed.modes[-1:] == [5], 2.0)
    assert spin_until(executor, lambda: mode_from_status(feed.statuses[-1])[1] == 5, 2.0)
    assert mode_from_status(feed.statuses[-1])[0] == int(round(t * 1e9))


def frame_to_status(executor, feed, t, xi, **kw):
    """Publish one frame's products (Feeder.frame) and spin until a new supervisor status."""
    n = len(feed.statuses)
    feed.frame(t, xi, **kw)
    assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)


def supervisor_with_grids(ctx, suffix):
    """A mode supervisor on sim time, its Feeder and the ibvs/frame_grid messages it sends."""
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup{suffix}_{TAG}', context=context,
                             parameter_overrides=[Parameter('use_sim_time', value=True)])
    feed = Feeder(context, f'feed{suffix}_{TAG}')
    grids = []
    feed.node.create_subscription(DiagnosticArray, 'ibvs/frame_grid', grids.append, MODE_QOS)
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    return sup, feed, grids


def test_supervisor_counts_grid_frames_no_product_came_for_and_lowers_the_rate(ctx):
    """Frames a node behind never computed (latest only) are missed; gaps double the stride.

    Only every 4th front frame gets its window product, as from a detector three images
    behind, which reports the three it skipped (ibvs/frames_superseded): the frames between
    never open. A lone missed frame costs that frame; each further one in a gap counts as
    skipped for the rate governor, which first sheds the flows and then doubles the stride
    (published on ibvs/frame_grid) instead of keeping a rate the computer cannot hold.
    """
    _, executor, _ = ctx
    sup, feed, grids = supervisor_with_grids(ctx, '_missed')
    xi = np.array([-2.0, 0.0, -1.6])
    for k in range(0, 40, 4):                        # 3 frames missed in each gap
        n = len(feed.statuses)
        for j in range(k - 3, k) if k else ():
            feed.skipped(1.0 + 0.02 * j)
        feed.frame(1.0 + 0.02 * k, xi)
        assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)
        if sup._grids.stride(Camera.FRONT) > 1:
            break
    assert sup._grids.stride(Camera.FRONT) == 2 and sup._stats.missed >= 6
    assert sup._stats.undelivered == 0
    assert spin_until(executor, lambda: any(
        grid_from_msg(g, 'front') is not None and grid_from_msg(g, 'front')[0] == 2
        for g in grids), 2.0)
    # complete frames on every frame of the new grid: nothing more is missed (the grid may
    # count from the flow frame before the decision: its frames from the last one fed on)
    missed, ref = sup._stats.missed, sup._grids.ref_ns(Camera.FRONT) / 1e9
    last = 1.0 + 0.02 * k
    t0 = ref + 0.04 * round((last - ref) / 0.04)
    for k in range(1, 6):
        n = len(feed.statuses)
        feed.frame(t0 + 0.04 * k, xi)
        assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)
    assert sup._stats.missed == missed and sup._grids.stride(Camera.FRONT) == 2


@pytest.mark.parametrize('reported', [True, False])
def test_supervisor_sheds_the_flows_on_lone_frames_a_node_superseded(ctx, reported):
    """Every 2nd front frame lost one at a time: short of CPU when a node reported it.

    A lone missed frame costs only that frame for the stride rules, but at every frame the
    next step only sheds the flows: the supervisor counts the lone frames the detector
    reported superseding, and the governor sheds (ibvs/frame_grid: flow stride 2, every frame
    still expected). Unreported (the camera never delivered them), they change nothing.
    """
    _, executor, _ = ctx
    sup, feed, _ = supervisor_with_grids(ctx, f'_lone_{int(reported)}')
    xi = np.array([-2.0, 0.0, -1.6])
    for k in range(0, 40, 2):                        # 1 frame missed in each gap
        n = len(feed.statuses)
        if k and reported:
            feed.skipped(1.0 + 0.02 * (k - 1))
        feed.frame(1.0 + 0.02 * k, xi)
        assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)
        if sup._grids.flow_stride(Camera.FRONT) > 1:
            break
    shed = (sup._grids.stride(Camera.FRONT), sup._grids.flow_stride(Camera.FRONT))
    assert shed == ((1, 2) if reported else (1, 1))
    assert sup._stats.missed >= 3


def test_supervisor_keeps_the_rate_through_frames_the_camera_never_delivered(ctx):
    """A camera dropout is no want of CPU: the same gaps, unreported, leave the stride at 1.

    Every 4th front frame comes and no node reports skipping the three between (the camera
    never delivered them): they are missed and counted undelivered on /diagnostics, and the
    governor keeps every frame (it raised the stride to 2 for 2 s after a 0.2 s dropout).
    """
    _, executor, _ = ctx
    sup, feed, _ = supervisor_with_grids(ctx, '_dropout')
    xi = np.array([-2.0, 0.0, -1.6])
    for k in range(0, 40, 4):
        n = len(feed.statuses)
        feed.frame(1.0 + 0.02 * k, xi)
        assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)
    assert sup._grids.stride(Camera.FRONT) == 1
    assert sup._stats.missed == 27 and sup._stats.undelivered == 27
    values = sup._stats.values(sup._newest_ns, 1, 'front')
    assert values['frames_undelivered'] == '27' and values['frames_missed'] == '27'


def test_supervisor_refuses_a_superseded_report_of_an_unknown_camera(ctx, capfd):
    """ibvs/frames_superseded with a camera name that is not 'front' or 'down': a clear error,
    nothing noted (no gap is counted on it), the node goes on."""
    _, executor, _ = ctx
    sup, feed, _ = supervisor_with_grids(ctx, '_bad_superseded')
    feed.skipped(1.0, camera='side')
    feed.skipped(1.02, camera='front')
    assert spin_until(executor, lambda: sup._superseded.reported(Camera.FRONT, 1_020_000_000, 0),
                      2.0)
    assert not sup._superseded.reported('side', 1_000_000_000, 0)
    assert not sup._superseded.reported(Camera.FRONT, 1_000_000_000, 0)
    assert "refused: unknown camera 'side'" in capfd.readouterr().err


def handover_strides(ctx, suffix, grace_s):
    """Fly a supervisor to CROSSING, skip the floor camera's first 3 frames; return strides.

    The down frames open on their (empty) pad cue and miss the floor flow CROSSING needs
    (the flow's first pair after its gate opens, on a slow computer), then 4 complete ones
    come. Returns the down camera's (frame stride, flow stride) then.
    """
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup{suffix}_{TAG}', context=context,
                             parameter_overrides=[Parameter('use_sim_time', value=True),
                                                  Parameter('stride_handover_grace_s',
                                                            value=grace_s)])
    feed = Feeder(context, f'feed{suffix}_{TAG}')
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    dt, v, t, xi = 0.02, 1.0, 1.0, np.array([-2.0, 0.0, -1.6])

    def step(**kw):
        nonlocal t
        frame_to_status(executor, feed, t, xi, **kw)
        t += dt

    for _ in range(3):
        step(front_flow=np.zeros(3))
    assert call(executor, feed.node, 'ibvs/start').success
    step(front_flow=np.zeros(3))
    while WORLD.wall_x - xi[0] > 0.75:          # WINDOW: the approach
        xi = xi + [v * dt, 0, 0]
        step(front_flow=np.array([v / (WORLD.wall_x - xi[0]), 0, 0]))
    xi = xi + [v * dt, 0, 0]                    # the window lost close: CROSSING
    step(window=False, front_flow=np.array([v / (WORLD.wall_x - xi[0]), 0, 0]))
    assert spin_until(executor, lambda: feed.modes[-1:] == [2], 2.0)
    skipped = sup._stats.skipped

    def down_frame(**kw):     # opened, or dropped off a stride-2 grid (no status either way)
        nonlocal t
        off_grid, stamp_ns = sup._stats.off_grid_dropped, round(t * 1e9)
        feed.frame(t, xi, window=False, **kw)
        assert spin_until(executor, lambda: sup._stats.off_grid_dropped > off_grid or (
            sup._last_opened is not None and sup._last_opened[1] == stamp_ns), 2.0)
        t += dt

    for _ in range(3):                          # the floor flow's first frames miss
        down_frame()
    for _ in range(4):
        down_frame(down_flow=np.array([v / -xi[2], 0, 0]))
    spin_for(executor, 0.05)                    # the last frame's evaluation
    assert sup._stats.skipped - skipped >= 3 and sup._core.mode == 2
    return sup._grids.stride(Camera.DOWN), sup._grids.flow_stride(Camera.DOWN)


@pytest.mark.parametrize('grace_s, level', [(0.2, (1, 1)), (0.0, (1, 2))])
def test_supervisor_handover_does_not_count_the_new_cameras_first_skipped_frames(
        ctx, grace_s, level):
    """WINDOW -> CROSSING: the floor camera's frames skipped before its first complete one
    (within stride_handover_grace_s) leave every frame computed; without the grace the same
    three skipped in a row take the governor's first step, the flows shed (the supervisor
    tells the governor of the camera change)."""
    assert handover_strides(ctx, f'_handover_{level[1]}', grace_s) == level


def test_shed_flows_are_held_by_the_supervisor_and_the_controller_alike(ctx):
    """The governor's first step: the wall flow on every 2nd frame, every frame still flown.

    Three WINDOW frames without their wall flow (a computer behind) shed the flows
    (ibvs/frame_grid: front_flow_stride 2). From then on the flow comes only for the flow
    grid's frames, as from the flow node: every frame still completes, a frame between two
    flow frames names the flow frame before it in its status, and the controller answers
    every frame with a force.
    """
    context, executor, nodes = ctx
    sup, feed, grids = supervisor_with_grids(ctx, '_shed')
    ctl = make_controller(context, f'ctl_shed_{TAG}', use_sim_time=True)
    nodes.append(ctl)
    executor.add_node(ctl)
    dt, t, xi = 0.02, 1.0, np.array([-2.0, 0.0, -1.6])
    phi = np.array([0.4, 0.0, 0.0])

    def step(**kw):
        nonlocal t
        frame_to_status(executor, feed, t, xi, **kw)
        t += dt

    for _ in range(3):
        step(front_flow=phi)
    assert call(executor, feed.node, 'ibvs/start').success
    for _ in range(3):
        step(front_flow=phi)
    assert feed.modes[-1] == 1                              # WINDOW
    for _ in range(3):                  # no wall flow: skipped once the next flow passes them
        stamp_ns = round(t * 1e9)
        feed.frame(t, xi)
        assert spin_until(executor, lambda: sup._frames.is_pending(stamp_ns), 2.0)
        t += dt
    step(front_flow=phi)
    assert sup._stats.skipped == 3
    assert (sup._grids.stride(Camera.FRONT), sup._grids.flow_stride(Camera.FRONT)) == (1, 2)
    assert spin_until(executor, lambda: any(
        grid_from_msg(g, 'front', flow=True) == (2, sup._grids.flow_grid(Camera.FRONT).ref_ns)
        for g in grids), 2.0)
    skipped, n_status = sup._stats.skipped, len(feed.statuses)
    stamps = []
    for _ in range(8):
        stamps.append(round(t * 1e9))
        on_flow_grid = sup._grids.flow_grid(Camera.FRONT).on_grid(stamps[-1])
        step(front_flow=phi if on_flow_grid else None)
    assert sup._stats.skipped == skipped                    # every frame flown
    held = {}
    for msg in feed.statuses[n_status:]:
        from_ns, err = held_from_status(msg)
        assert not err
        held[mode_from_status(msg)[0]] = from_ns.get('flow_front')
    assert sorted(held) == stamps
    assert [s - held[s] for s in stamps if held[s] is not None] == [round(dt * 1e9)] * 4
    assert spin_until(executor, lambda: {stamp_to_ns(f.header.stamp) for f in feed.forces}
                      >= set(stamps), 2.0)
    assert ctl.skipped == 0


def test_supervisor_stale_input_failsafe_and_abort(ctx):
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup2_{TAG}', context=context)
    feed = Feeder(context, f'feed2_{TAG}')
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    res = call(executor, feed.node, 'ibvs/start')
    assert not res.success and res.message           # nothing detected yet
    xi = np.array([-2.0, 0.0, -1.6])
    for _ in range(5):
        feed.frame(sup.get_clock().now().nanoseconds * 1e-9, xi, front_flow=np.zeros(3))
        spin_for(executor, 0.02)
    assert call(executor, feed.node, 'ibvs/start').success
    feed.frame(sup.get_clock().now().nanoseconds * 1e-9, xi, front_flow=np.zeros(3))
    # the start at that frame; then inputs stop: the IMU goes stale after 0.2 s -> FAILSAFE
    # (5), logged with its reason
    assert spin_until(executor, lambda: feed.modes[-1:] == [5], 3.0)
    assert feed.modes == [0, 1, 5]
    # a transition without a frame still gets a status (stamped now): the controller answers
    # it and every later stamp's mode is known
    assert spin_until(executor, lambda: feed.statuses
                      and mode_from_status(feed.statuses[-1])[1] == 5, 2.0)
    res = call(executor, feed.node, 'ibvs/abort')
    assert not res.success and 'FAILSAFE' in res.message


def test_supervisor_pilot_switch_starts_on_off_to_on_and_aborts_on_off(ctx, capfd):
    """ibvs/pilot_input (the bridge's reading of the pilot's RC switch, latched): ON already at
    boot starts nothing; OFF then ON starts at the next frame, as ibvs/start; OFF in flight
    aborts to FAILSAFE; a value outside the enum is refused with an error."""
    _, executor, _ = ctx
    sup, feed = supervisor_on_sim_time(ctx, '_pilot')
    pilot = feed.node.create_publisher(UInt8, 'ibvs/pilot_input', MODE_QOS)
    xi, t, fed = np.array([-2.0, 0.0, -1.6]), 1.0, []

    def step():
        nonlocal t
        feed.frame(t, xi, front_flow=np.zeros(3))
        fed.append(int(round(t * 1e9)))
        assert spin_until(executor, lambda: len(feed.statuses) >= len(fed), 2.0)
        t += 0.02

    for _ in range(5):
        step()
    pilot.publish(UInt8(data=2))                     # ON without an OFF before it
    spin_for(executor, 0.1)
    for _ in range(3):
        step()
    assert feed.modes == [0]
    pilot.publish(UInt8(data=7))                     # not a PilotInput: refused, logged
    spin_for(executor, 0.1)
    pilot.publish(UInt8(data=1))                     # OFF in IDLE: nothing to abort
    spin_for(executor, 0.1)
    step()
    assert feed.modes == [0]
    pilot.publish(UInt8(data=2))                     # OFF -> ON: the start, at the next frame
    spin_for(executor, 0.1)
    step()
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)
    for _ in range(3):
        step()
    pilot.publish(UInt8(data=1))                     # OFF in flight: abort
    assert spin_until(executor, lambda: feed.modes[-1:] == [5], 2.0)
    assert feed.modes == [0, 1, 5]
    err = capfd.readouterr().err
    assert 'pilot switch ON without an OFF before it' in err
    assert 'ibvs/pilot_input 7 is not a PilotInput value' in err
    assert 'pilot switch: start accepted' in err


def test_supervisor_bad_messages_no_output_no_exception(ctx, capfd):
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup3_{TAG}', context=context)
    feed = Feeder(context, f'feed3_{TAG}')
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    now = sup.get_clock().now().nanoseconds * 1e-9
    bad = corners_C(np.array([-2.0, 0.0, -1.6]))
    bad[1, 0] = np.nan
    feed.imu.publish(imu_msg(now))
    feed.corners.publish(polygon(now, bad, 'front_camera_optical_frame'))
    feed.corners.publish(polygon(now, bad[:3], 'front_camera_optical_frame'))
    feed.landmarks.publish(polygon(now, 2.0 * np.ones((4, 3)), 'down_camera_optical_frame'))
    feed.front.publish(flow_msg(now, np.array([np.nan, 0, 0])))
    bad_imu = imu_msg(now)
    bad_imu.orientation.w = bad_imu.orientation.x = bad_imu.orientation.y = 0.0
    bad_imu.orientation.z = 0.0
    feed.imu.publish(bad_imu)
    spin_for(executor, 0.5)
    assert feed.modes == [0]
    assert not call(executor, feed.node, 'ibvs/start').success   # NaN window != detected
    err = capfd.readouterr().err
    assert 'refused' in err


# --- force controller --------------------------------------------------------------------

def make_controller(context, name, **params):
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return ForceControllerNode(node_name=name, context=context, parameter_overrides=overrides)


def controller_with_feeder(ctx, suffix, **params):
    """A force controller ``fc<suffix>`` and its Feeder on the test executor."""
    context, executor, nodes = ctx
    fc = make_controller(context, f'fc{suffix}_{TAG}', **params)
    feed = Feeder(context, f'feedfc{suffix}_{TAG}')
    nodes += [fc, feed.node]
    executor.add_node(fc)
    executor.add_node(feed.node)
    return fc, feed


def stamps_of(msgs):
    return [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs]


def status(feed, t, mode, camera=None):
    """Publish the supervisor's status of the frame at t (s) of ``camera`` in ``mode``."""
    feed.status.publish(supervisor_status_msg(int(round(t * 1e9)), mode, 'm',
                                              DiagnosticStatus.OK, {}, camera))


def test_controller_observer_reads_imu_specific_force_in_flu(ctx):
    """disturbance_law observer: imu/data linear_acceleration (base_link FLU) reaches d_hat in {I}.

    Hovering level, facing north: the accelerometer reads +g up plus 0.5 m/s^2 to the LEFT
    (FLU y), i.e. a force towards the west (-y in {I}, north-east-down); F = m g e3, so
    Delta / m = f_I + F / m = (0, -0.5, 0). An all-zero reading (an unfilled field) is ignored.
    """
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, 'obs', disturbance_law='observer')
    spin_for(executor, 0.3)
    for i in range(100):                       # 2 s = 4 observer time constants
        t = 20.0 + 0.02 * i
        for sub in (0.005, 0.015):
            msg = imu_msg(t - 0.02 + sub)
            msg.linear_acceleration.y, msg.linear_acceleration.z = 0.5, GRAVITY
            feed.imu.publish(msg)
            feed.imu.publish(imu_msg(t - 0.02 + sub + 0.001))   # zeros: not a flying reading
        feed.corners.publish(polygon(t, [], 'front_camera_optical_frame'))   # IDLE's product
        spin_for(executor, 0.003)
        status(feed, t, 0)     # answered before the next: the subscriptions keep 2 frames
        assert spin_until(executor, lambda: len(feed.forces) > i and len(feed.features) > i,
                          2.0)
    named = dict(zip(feed.features[-1].name, feed.features[-1].position))   # ibvs/features
    d_hat = [named[f'd_hat.{axis}'] for axis in 'xyz']                       # {I}, m/s^2
    assert d_hat == pytest.approx([0.0, -0.5 * (1 - np.exp(-2.0 / 0.5)), 0.0], abs=0.02)


def test_controller_answers_every_status_once_in_idle(ctx):
    """Each status is answered once, from its frame's products; a frame without one is not.

    IDLE needs the window product (detected or not): a frame whose window detection never
    came is skipped at its deadline (never answered from a missing product), and counted.
    """
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, '')
    spin_for(executor, 0.3)
    xi = np.array([-2.0, 0.1, -1.82])
    sent, skipped = [], []
    for i in range(12):
        t = 10.0 + 0.02 * i      # stamps long past on the system clock: deadlines from arrival
        feed.imu.publish(imu_msg(t - 0.001))
        if i % 3:   # every third frame the window detector says nothing: skipped
            feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
            sent.append(int(round(t * 1e9)))
        else:
            skipped.append(int(round(t * 1e9)))
        spin_for(executor, 0.01)
        status(feed, t, 0)
        if i % 3:
            assert spin_until(executor, lambda: len(feed.forces) >= len(sent), 2.0)
        else:
            assert spin_until(executor, lambda: fc.skipped >= len(skipped), 2.0)
    spin_for(executor, 0.2)
    assert stamps_of(feed.forces) == sent and fc.skipped == len(skipped)
    hover_map = vec_I_to_map(np.array([0, 0, VEHICLE.mass * GRAVITY]))
    for f in feed.forces:
        assert f.header.frame_id == 'map'
        assert np.allclose([f.vector.x, f.vector.y, f.vector.z], hover_map)
    assert stamps_of(feed.headings) == sent
    # heading: the yaw of the IMU (0, north) as base_link in map = ENU yaw +90 deg
    q = feed.headings[0].quaternion
    assert np.allclose([q.w, q.z], [np.cos(np.pi / 4), np.sin(np.pi / 4)], atol=1e-9)

    # a status a little out of order (within MAX_BACKSTEP_S) or repeated: dropped
    n = len(feed.forces)
    for t in (10.15, 11.0, 11.0):                    # one at a time: FRAME_QOS keeps 2
        feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
        spin_for(executor, 0.01)
        status(feed, t, 0)
        spin_for(executor, 0.1)
    assert stamps_of(feed.forces[n:]) == [int(11.0 * 1e9)]
    # a status 1 s back: the clock stepped back, the frames start again from it (before,
    # every status up to 11.0 s would have been dropped as older than one answered)
    status(feed, 10.0, 0)
    spin_for(executor, 0.01)
    feed.corners.publish(polygon(10.0, corners_C(xi), 'front_camera_optical_frame'))
    assert spin_until(executor, lambda: len(feed.forces) == n + 2, 2.0)
    assert stamps_of(feed.forces[n:]) == [int(11.0 * 1e9), int(10.0 * 1e9)]


def test_controller_that_fell_behind_answers_the_newest_frames_not_a_backlog(ctx):
    """Statuses queue at most 2 deep (FRAME_QOS): 12 frames while the controller was busy.

    Only the newest two are answered: a node that falls behind skips to the newest frames
    instead of answering ever older ones (with depth 10 it answered the last 10, up to 0.2 s
    old at 50 Hz).
    """
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, '9')
    spin_for(executor, 0.3)
    xi = np.array([-2.0, 0.1, -1.82])
    sent = []
    for i in range(12):                  # published without spinning: nobody takes them
        t = 10.0 + 0.02 * i
        feed.imu.publish(imu_msg(t - 0.001))
        feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
        status(feed, t, 0)
        sent.append(int(round(t * 1e9)))
    assert spin_until(executor, lambda: len(feed.forces) >= 2, 3.0)
    spin_for(executor, 0.3)
    assert stamps_of(feed.forces) == sent[-2:]


def window_frame_without_flow(ctx, suffix):
    """A controller on sim time (40 ms deadline) with a WINDOW frame open at t = 5 s.

    Its status, IMU sample and window came; the front flow it needs did not. Return
    (controller, feeder, t, xi).
    """
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, suffix, use_sim_time=True, frame_deadline_s=0.04)
    xi = np.array([-2.0, 0.1, -1.82])
    t = 5.0
    feed.clock.publish(Clock(clock=stamp(t)))
    spin_for(executor, 0.3)
    feed.imu.publish(imu_msg(t))
    feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
    status(feed, t, 1)
    spin_for(executor, 0.3)
    return fc, feed, t, xi


def test_controller_waits_for_a_needed_product_until_the_deadline_on_the_ros_clock(ctx):
    """WINDOW needs the front flow: no answer while sim time stands still, skipped after.

    The deadline counts from the frame's first input (here its status) on the ROS clock, so
    a late camera's frame still gets its products; a frame without them by then is skipped,
    never answered. An unneeded product (the pad, whose detector is dead here) never delays
    a frame.
    """
    _, executor, _ = ctx
    fc, feed, t, xi = window_frame_without_flow(ctx, '7')
    spin_for(executor, 0.2)            # half a second of wall clock, sim time stands still
    assert feed.forces == [] and fc.skipped == 0
    feed.clock.publish(Clock(clock=stamp(t + 0.039)))
    spin_for(executor, 0.2)
    assert feed.forces == [] and fc.skipped == 0
    feed.clock.publish(Clock(clock=stamp(t + 0.041)))
    assert spin_until(executor, lambda: fc.skipped == 1, 2.0)
    feed.front.publish(flow_msg(t, np.zeros(3)))      # too late: its frame was skipped
    spin_for(executor, 0.2)
    assert feed.forces == []
    # next frame, as a late camera delivers it: its status and window come 30 ms after its
    # stamp, its front flow 35 ms later still (65 ms after the stamp): answered
    t2 = t + 0.06
    feed.clock.publish(Clock(clock=stamp(t2 + 0.03)))
    spin_for(executor, 0.1)
    feed.imu.publish(imu_msg(t2))
    feed.corners.publish(polygon(t2, corners_C(xi), 'front_camera_optical_frame'))
    status(feed, t2, 1)
    spin_for(executor, 0.1)
    feed.clock.publish(Clock(clock=stamp(t2 + 0.065)))
    spin_for(executor, 0.1)
    feed.front.publish(flow_msg(t2, np.zeros(3)))
    assert spin_until(executor, lambda: len(feed.forces) == 1, 2.0)
    assert stamps_of(feed.forces) == [int(round(t2 * 1e9))]
    # and one with window + front flow of its stamp, no pad at all: answered at once
    t3 = t2 + 0.02
    feed.imu.publish(imu_msg(t3))
    feed.corners.publish(polygon(t3, corners_C(xi), 'front_camera_optical_frame'))
    feed.front.publish(flow_msg(t3, np.zeros(3)))
    status(feed, t3, 1)
    assert spin_until(executor, lambda: len(feed.forces) == 2, 2.0)
    assert stamps_of(feed.forces[1:]) == [int(round(t3 * 1e9))]


def test_a_deadline_takes_the_products_waiting_in_the_readers_first(ctx):
    """A product in its reader when the frame's deadline timer runs completes the frame.

    In a busy process the product's own event may wait behind image callbacks until after
    the deadline; the deadline takes what has arrived before judging the frame (here the
    deadline runs before any spin took the flow: answered, not skipped).
    """
    _, executor, _ = ctx
    fc, feed, t, _ = window_frame_without_flow(ctx, '8')
    assert feed.forces == [] and fc.skipped == 0          # WINDOW waits for its front flow
    feed.front.publish(flow_msg(t, np.zeros(3)))
    time.sleep(0.1)                                       # in the reader, not taken
    taken = fc._products.taken_waiting
    fc._on_deadline()
    assert fc._products.taken_waiting == taken + 1
    assert spin_until(executor, lambda: len(feed.forces) == 1, 2.0) and fc.skipped == 0
    assert stamps_of(feed.forces) == [int(round(t * 1e9))]


def test_controller_hands_a_switch_to_an_unsynchronised_camera_over_to_its_next_frame(ctx):
    """WINDOW -> CROSSING decided on a front frame: the floor flow has no image of its stamp.

    Cameras that are not synchronised (a time offset, their own clocks): the front frame at t
    switched to CROSSING, the down camera's images are stamped 3 ms before and 17 ms after.
    The frame is released as a handover when the down flow passes it, sim time standing
    still (no deadline), not counted as skipped and not answered; the down frame after it is
    the first flown in CROSSING. With synchronised cameras the switch frame is flown.
    """
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, 'ho', use_sim_time=True, frame_deadline_s=0.04)
    t = 50.0
    feed.clock.publish(Clock(clock=stamp(t)))
    spin_for(executor, 0.3)
    feed.imu.publish(imu_msg(t))
    feed.down.publish(flow_msg(t - 0.003, np.array([0.3, 0.0, 0.0])))
    status(feed, t, 2, 'front')
    spin_for(executor, 0.3)
    assert feed.forces == [] and fc.handovers == 0          # waiting: it may still come
    t_down = t + 0.017
    feed.imu.publish(imu_msg(t_down))
    feed.down.publish(flow_msg(t_down, np.array([0.3, 0.0, 0.0])))
    assert spin_until(executor, lambda: fc.handovers == 1, 2.0)
    assert fc.skipped == 0 and feed.forces == []
    status(feed, t_down, 2, 'down')
    assert spin_until(executor, lambda: len(feed.forces) == 1, 2.0)
    assert stamps_of(feed.forces) == [int(round(t_down * 1e9))]
    # synchronised cameras: the switch frame has its floor flow and is flown in CROSSING
    t2 = t + 0.1
    feed.clock.publish(Clock(clock=stamp(t2)))
    feed.imu.publish(imu_msg(t2))
    status(feed, t2, 2, 'front')
    feed.down.publish(flow_msg(t2, np.array([0.3, 0.0, 0.0])))
    assert spin_until(executor, lambda: len(feed.forces) == 2, 2.0)
    assert stamps_of(feed.forces[1:]) == [int(round(t2 * 1e9))] and fc.handovers == 1


def test_controller_bad_inputs_still_answered_without_nan(ctx):
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, '2')
    spin_for(executor, 0.3)
    xi = np.array([-2.0, 0.1, -1.82])
    bad = corners_C(xi)
    bad[0, 2] = np.nan
    cases = [bad, corners_C(xi)[:3], np.zeros((4, 3))]
    for i, corners in enumerate(cases):
        t = 20.0 + 0.02 * i
        feed.imu.publish(imu_msg(t))
        feed.corners.publish(polygon(t, corners, 'front_camera_optical_frame'))
        feed.landmarks.publish(polygon(t, [], 'down_camera_optical_frame'))
        feed.front.publish(flow_msg(t, np.array([np.nan, 0.0, 0.0])))
        spin_for(executor, 0.02)
        status(feed, t, 1)
        assert spin_until(executor, lambda: len(feed.forces) > i, 2.0)
    nan_imu = imu_msg(20.1)
    nan_imu.orientation.w = float('nan')
    feed.imu.publish(nan_imu)
    feed.corners.publish(polygon(20.1, corners_C(xi), 'front_camera_optical_frame'))
    feed.front.publish(flow_msg(20.1, np.zeros(3)))
    spin_for(executor, 0.02)
    status(feed, 20.1, 1)
    assert spin_until(executor, lambda: len(feed.forces) >= 4, 2.0)
    for f in feed.forces:
        assert np.all(np.isfinite([f.vector.x, f.vector.y, f.vector.z]))


def test_controller_window_mode_force_heading_features(ctx):
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, '3')
    spin_for(executor, 0.3)
    xi = np.array([-2.0, 0.3, -1.82])
    for i in range(6):
        t = 30.0 + 0.02 * i
        feed.imu.publish(imu_msg(t))
        spin_for(executor, 0.01)
        feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
        feed.landmarks.publish(polygon(t, [], 'down_camera_optical_frame'))
        feed.front.publish(flow_msg(t, np.zeros(3)))
        spin_for(executor, 0.02)
        status(feed, t, 1)
        assert spin_until(executor, lambda: len(feed.forces) > i, 2.0)
    assert spin_until(executor, lambda: len(feed.features) >= 6, 2.0)
    f = feed.forces[-1]
    F_map = np.array([f.vector.x, f.vector.y, f.vector.z])
    hover_map = vec_I_to_map(np.array([0, 0, VEHICLE.mass * GRAVITY]))
    assert np.all(np.isfinite(F_map)) and not np.allclose(F_map, hover_map)
    names = feed.features[-1].name
    assert 'alpha_w' in names and 'q_w.x' in names and 'q_w_bar.z' in names
    assert len(names) == len(feed.features[-1].position)
    assert stamps_of(feed.features[-1:]) == stamps_of(feed.forces[-1:])
    # the window is centred at y = 0 and the vehicle sits at y = +0.3: push towards -y_I,
    # i.e. (m v_dot = -F + m g e3) F_y_I > 0, which is +x in map
    assert F_map[0] > 0.0


def test_controller_flies_the_mode_reported_for_each_stamp(ctx):
    # The supervisor's status for each frame says which law flies it: IDLE hovers, WINDOW
    # flies the window law; the status may come before its frame's products.
    _, executor, _ = ctx
    fc, feed = controller_with_feeder(ctx, '6', use_sim_time=True)
    feed.clock.publish(Clock(clock=stamp(40.0)))
    spin_for(executor, 0.3)
    xi = np.array([-2.0, 0.3, -1.82])
    hover_map = vec_I_to_map(np.array([0, 0, VEHICLE.mass * GRAVITY]))
    forces = []
    for i, mode in enumerate((0, 1, 1, 0)):
        t = 40.0 + 0.02 * i
        ns = int(round(t * 1e9))
        n = len(feed.forces)
        feed.clock.publish(Clock(clock=stamp(t)))
        status(feed, t, mode)
        spin_for(executor, 0.02)
        feed.imu.publish(imu_msg(t))
        feed.corners.publish(polygon(t, corners_C(xi), 'front_camera_optical_frame'))
        feed.landmarks.publish(polygon(t, [], 'down_camera_optical_frame'))
        feed.groups.publish(pad_groups_msg(stamp(t), 'down_camera_optical_frame', []))
        feed.front.publish(flow_msg(t, np.zeros(3)))
        assert spin_until(executor, lambda: len(feed.forces) > n, 2.0)
        f = feed.forces[-1]
        assert stamps_of([f]) == [ns]
        forces.append(np.array([f.vector.x, f.vector.y, f.vector.z]))
    assert np.allclose(forces[0], hover_map) and np.allclose(forces[3], hover_map)
    assert not np.allclose(forces[1], hover_map) and not np.allclose(forces[2], hover_map)


def test_controller_refuses_bad_gains(ctx):
    context, _, _ = ctx
    with pytest.raises(GainError):
        make_controller(context, f'fc4_{TAG}', **{'window.kd': 0.5})   # 0.25 < r_w/2
    env = dict(os.environ)
    proc = subprocess.run(
        [sys.executable, '-c', 'from ibvs_control.force_controller_node import main; main()',
         '--ros-args', '-r', f'__node:=fc5_{TAG}', '-p', 'window.kd:=0.5'],
        env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert 'Proposition' in proc.stderr + proc.stdout


# --- MAVLink bridge ----------------------------------------------------------------------

def test_bridge_node_imu_setpoint_and_diagnostics(ctx):
    from diagnostic_msgs.msg import DiagnosticArray
    context, executor, nodes = ctx
    # Clocks stand still: the autopilot's boot time 1.5 s, our ROS time (/clock) 4.0 s, so the
    # TIMESYNC offset is exactly 2.5 s (rtt 0) and the mapped times are exact.
    peer = FakeAutopilot(time.monotonic, yaw_ned=np.pi / 2, boot_clock=lambda: 1_500_000_000,
                         armed=False, landed=True,
                         params={'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 4})
    runner = PeerThread(peer)
    try:
        bridge = MavlinkBridgeNode(
            node_name=f'bridge_{TAG}', context=context, parameter_overrides=[
                Parameter('use_sim_time', value=True),
                Parameter('url', value=f'udpout:127.0.0.1:{peer.udp_port}'),
                Parameter('hover_thrust_source', value='config'),
                Parameter('hover_estimator_enabled', value=False),
                Parameter('diagnostics_rate_hz', value=5.0),
                Parameter('pilot_switch_channel', value=7)])
        feed = Feeder(context, f'feedbr_{TAG}')
        nodes += [bridge, feed.node]
        imus, diags = [], []
        feed.node.create_subscription(Imu, 'imu/data', imus.append, SENSOR_QOS)
        feed.node.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
        pilot = []
        feed.node.create_subscription(UInt8, 'ibvs/pilot_input', lambda m: pilot.append(m.data),
                                      MODE_QOS)
        heading = feed.node.create_publisher(QuaternionStamped, 'ibvs/heading_setpoint',
                                             COMMAND_QOS)
        force = feed.node.create_publisher(Vector3Stamped, 'ibvs/force_setpoint', COMMAND_QOS)
        arm = feed.node.create_client(Trigger, 'ibvs/arm')
        feed.node.create_timer(0.02, lambda: feed.clock.publish(Clock(clock=stamp(4.0))))
        executor.add_node(bridge)
        executor.add_node(feed.node)
        assert spin_until(executor, lambda: len(imus) >= 3 and diags, 5.0)
        q = imus[-1].orientation
        assert np.allclose([abs(q.w), q.x, q.y, q.z], [1, 0, 0, 0], atol=1e-6)  # east = ENU
        assert imus[-1].header.frame_id == 'base_link'
        assert all(stamps_of([m]) == [4_000_000_000] for m in imus)   # 1.5 s boot + 2.5 s
        acc = imus[-1].linear_acceleration                 # HIGHRES_IMU, FRD -> FLU
        assert (acc.x, acc.y) == (0.0, 0.0) and acc.z == pytest.approx(GRAVITY)
        h = QuaternionStamped()
        h.header.stamp = stamp(4.321)
        h.header.frame_id = 'map'
        w, x, y, z = quat_ned_frd_to_enu_flu(np.array([1.0, 0, 0, 0]))
        h.quaternion.w, h.quaternion.x, h.quaternion.y, h.quaternion.z = w, x, y, z
        heading.publish(h)
        spin_for(executor, 0.1)
        force.publish(flow_msg(4.321, np.array([0.0, 0.0, VEHICLE.mass * GRAVITY])))
        assert spin_until(executor, lambda: any(m.time_boot_ms == 1821
                                                for _, m in peer.setpoints), 3.0)
        m = [m for _, m in peer.setpoints if m.time_boot_ms == 1821][-1]
        assert m.thrust == pytest.approx(VEHICLE.hover_thrust)
        assert np.allclose(np.abs(m.q), [1, 0, 0, 0], atol=1e-6)    # level, yaw 0 (north)
        # Next frame as the controller sends it, heading then force, both queued before the
        # executor runs: the heading subscription comes first, the setpoint of that stamp
        # carries that stamp's heading.
        yaw = 0.5
        h.header.stamp = stamp(4.341)
        w, x, y, z = quat_ned_frd_to_enu_flu(np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]))
        h.quaternion.w, h.quaternion.x, h.quaternion.y, h.quaternion.z = w, x, y, z
        heading.publish(h)
        force.publish(flow_msg(4.341, np.array([0.0, 0.0, VEHICLE.mass * GRAVITY])))
        assert spin_until(executor, lambda: len([m for _, m in peer.setpoints
                                                 if m.time_boot_ms == 1841]) >= 1, 3.0)
        for m in [m for _, m in list(peer.setpoints) if m.time_boot_ms == 1841]:
            assert same_rotation(m.q, [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        # ibvs/arm: never armed unless asked; the request is accepted and waits for the
        # engagement (no supervisor here)
        assert not peer.armed and not [c for c in peer.commands
                                       if c[1].command == 400]
        assert arm.wait_for_service(timeout_sec=2.0)
        future = arm.call_async(Trigger.Request())
        assert spin_until(executor, future.done, 3.0)
        assert future.result().success and 'arm' in future.result().message
        spin_for(executor, 0.4)
        keys = {kv.key: kv.value for kv in diags[-1].status[0].values}
        assert keys['link'] == 'up' and keys['autopilot'] == 'px4'
        assert 'setpoint_rate_hz' in keys and 'hover_thrust_source' in keys
        assert keys['headings_missing'] == '0'
        assert keys['arm_requested'] == 'True' and keys['armed'] == 'False'
        assert keys['landed_state'] == '1' and keys['armable'] == 'True'
        assert keys['clock_synced'] == 'yes' and keys['clock_offset_ms'] == '2500.000'
        assert int(keys['timesync_accepted']) >= 5
        # the dead-bridge failsafe as read (PX4 sends the INT32 bytewise) and our system id:
        # what the preflight gates on
        assert keys['COM_OBL_RC_ACT'] == '4' and keys['COM_OF_LOSS_T'] == '1'
        assert keys['source_system'] == '1' and keys['dead_bridge_failsafe'] == 'True'
        assert not peer.armed
        # the pilot's switch on RC channel 7 (RC_CHANNELS), published on change, latched
        assert pilot == [0] and keys['pilot_input'] == 'UNKNOWN'
        peer.rc = [1500] * 6 + [1100] + [1500] + [0xFFFF] * 10
        assert spin_until(executor, lambda: pilot[-1:] == [1], 3.0)
        peer.rc = [1500] * 6 + [1900] + [1500] + [0xFFFF] * 10
        assert spin_until(executor, lambda: pilot[-1:] == [2], 3.0)
        assert pilot == [0, 1, 2]
    finally:
        runner.close()


@pytest.mark.parametrize('sim_time', [False, True])
def test_bridge_times_heartbeats_on_the_ros_clock_under_sim_time(ctx, sim_time):
    """heartbeat_timeout_s: the steady clock onboard, the ROS clock under use_sim_time (0 s
    before any /clock here), as MAVROS's connection timeout."""
    context, executor, nodes = ctx
    bridge = MavlinkBridgeNode(
        node_name=f'bridge_hbclock_{TAG}', context=context, parameter_overrides=[
            Parameter('use_sim_time', value=sim_time),
            Parameter('url', value='udpin:127.0.0.1:0')])
    nodes.append(bridge)
    link = bridge._bridge.link
    if sim_time:
        assert link._heartbeat_clock is not link._clock and link._heartbeat_clock() == 0.0
    else:
        assert link._heartbeat_clock is link._clock
