"""The sim node in-process: images, camera_info, ground truth and /clock, consistently stamped."""
import json
import os
import re
import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from ibvs_common.core.config import load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import vec_I_to_map
from ibvs_sim.sim_node import SimNode

CAMERAS = ('front', 'down')
BODY_RATES_IGNORED = 0b00000111   # SET_ATTITUDE_TARGET type_mask bits 0-2


@pytest.fixture()
def ros_context():
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _stamp_ns(header_or_time):
    t = getattr(header_or_time, 'stamp', header_or_time)
    return t.sec * 1_000_000_000 + t.nanosec


#: The sim's autopilot on a port the kernel picks at the bind (``sim.autopilot.local_port``):
#: nothing can take it between a check and the bind, as with a port chosen first.
KERNEL_PORT = 'udpin:127.0.0.1:0'


def _spin_until(executor, done, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not done():
        executor.spin_once(timeout_sec=0.05)
    return done()


def _true_vehicle(tmp_path) -> str:
    """A true vehicle unlike the calibration: other focal lengths, lever arms, time offsets."""
    import yaml
    from ibvs_common.core.config import default_config_path
    data = yaml.safe_load(open(default_config_path('vehicle.yaml')).read())
    for cam in data['cameras'].values():
        cam['K'][0] *= 1.02
        cam['K'][4] *= 1.02
        cam['t_BC'] = [0.05, 0.0, 0.02]
        cam['time_offset_s'] = 0.002
    path = tmp_path / 'true_vehicle.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_sim_node_publishes_consistent_frames(ros_context, tmp_path):
    """Images, camera_info, odometry, /clock; camera_info is the onboard calibration's.

    The sim renders a true vehicle whose intrinsics differ (true_vehicle_file) and stamps its
    images 2 ms before their exposure (its time offset), but publishes the calibration the
    onboard nodes read (vehicle_file), as a camera driver publishes the file it was given.
    """
    tag = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
    params = [Parameter('pacing', value='realtime'),
              Parameter('true_vehicle_file', value=_true_vehicle(tmp_path)),
              Parameter('start_on_setpoints', value=False),   # no companion in this test
              Parameter('real_time_factor', value=0.25),      # time between frames to spare
              Parameter('mavlink_url', value=KERNEL_PORT),
              Parameter('initial_override', value=True),
              Parameter('initial_position_I', value=[-1.5, 0.2, -1.5]),
              Parameter('initial_yaw', value=0.1)]
    sim = SimNode(node_name=f'sim_test_{tag}', parameter_overrides=params, context=ros_context)
    probe = rclpy.create_node(f'sim_probe_{tag}', context=ros_context)
    got = {k: [] for k in ('front_image', 'down_image', 'front_info', 'down_info', 'odom',
                           'clock', 'events')}
    for cam in CAMERAS:
        probe.create_subscription(Image, f'{cam}_camera/image_raw',
                                  lambda m, c=cam: got[f'{c}_image'].append(m),
                                  qos_profile_sensor_data)
        probe.create_subscription(CameraInfo, f'{cam}_camera/camera_info',
                                  lambda m, c=cam: got[f'{c}_info'].append(m), 10)
    probe.create_subscription(Odometry, 'sim/ground_truth/odom', got['odom'].append, 10)
    probe.create_subscription(Clock, '/clock', got['clock'].append, 10)
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    probe.create_subscription(String, 'sim/events', got['events'].append, latched)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(sim)
    executor.add_node(probe)
    try:
        ok = _spin_until(executor, lambda: all(len(got[k]) >= 5 for k in
                                               ('front_image', 'down_image', 'odom', 'clock',
                                                'front_info', 'down_info')), 30.0)
        assert ok, {k: len(v) for k, v in got.items()}
        _spin_until(executor, lambda: False, 0.3)     # /clock of the last frames, too
    finally:
        executor.shutdown()
        probe.destroy_node()
        sim.destroy_node()

    vehicle = load_vehicle()
    clock_ns = [_stamp_ns(m.clock) for m in got['clock']]
    # free-running: /clock runs on between frames (several per camera period), never back
    assert clock_ns == sorted(clock_ns) and len(set(clock_ns)) > len(got['front_image'])
    for cam in CAMERAS:
        cfg = vehicle.cameras[cam]
        for img in got[f'{cam}_image']:
            assert img.encoding == 'mono8' and img.step == img.width == 752
            assert img.height == 480 and len(img.data) == 752 * 480
            assert img.header.frame_id == cfg.frame_id
            assert _stamp_ns(img.header) <= clock_ns[-1]
            pixels = np.frombuffer(bytes(img.data), np.uint8)
            assert pixels.std() > 10
        info = got[f'{cam}_info'][0]
        assert info.distortion_model == 'plumb_bob' and info.header.frame_id == cfg.frame_id
        assert np.allclose(info.k, cfg.model.K.ravel()) and np.allclose(info.d, cfg.model.D)
        assert np.allclose(np.reshape(info.p, (3, 4))[:, :3], cfg.model.K)
        assert np.allclose(info.r, np.eye(3).ravel())
        info_ns = {_stamp_ns(m.header) for m in got[f'{cam}_info']}
        assert {_stamp_ns(m.header) for m in got[f'{cam}_image']} <= info_ns
    # frames are 20 ms apart in sim time, exposed from 0 on, stamped 2 ms before (the true
    # time offset), and published at the exposure (no latency; not before the stamp's time)
    stamps = sorted(_stamp_ns(m.header) for m in got['down_image'])
    assert stamps[0] == -2_000_000
    assert all(d % 20_000_000 == 0 and d > 0 for d in np.diff(stamps))
    # ground truth: map / base_link, ENU of the overridden initial position at t = 0
    odom0 = min(got['odom'], key=lambda m: _stamp_ns(m.header))
    assert odom0.header.frame_id == 'map' and odom0.child_frame_id == 'base_link'
    p = odom0.pose.pose.position
    assert [p.x, p.y, p.z] == pytest.approx(vec_I_to_map(np.array([-1.5, 0.2, -1.5])), abs=1e-6)
    assert all(_stamp_ns(m.header) <= clock_ns[-1] for m in got['odom'])
    assert got['events'] == []


def test_sim_node_default_initial_condition_and_bad_parameter(ros_context):
    tag = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
    with pytest.raises(ValueError):
        SimNode(node_name=f'sim_bad_{tag}', context=ros_context,
                parameter_overrides=[Parameter('pacing', value='fast')])
    sim = SimNode(node_name=f'sim_def_{tag}', context=ros_context,
                  parameter_overrides=[Parameter('mavlink_url',
                                                 value=KERNEL_PORT)])
    try:
        assert sim.sim.state.xi_I == pytest.approx(load_world().initial_position_I)
    finally:
        sim.destroy_node()


def test_event_json_schema():
    from ibvs_sim.core.events import EventType, SimEvent
    e = SimEvent(EventType.COLLISION, 3.5, 'window_frame', np.array([-0.8, 0.1, -1.0]), 1.2)
    d = json.loads(json.dumps(e.to_dict()))
    assert d == {'type': 'collision', 't': 3.5, 'surface': 'window_frame',
                 'position_map': [0.1, -0.8, 1.0], 'speed_mps': 1.2}


def test_sim_node_lockstep_advances_on_answers_only(ros_context):
    os.environ['MAVLINK20'] = '1'
    from pymavlink import mavutil
    tag = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
    sim = SimNode(node_name=f'sim_lock_{tag}', context=ros_context, parameter_overrides=[
        Parameter('pacing', value='lockstep'), Parameter('lockstep_timeout_s', value=60.0),
        Parameter('start_on_setpoints', value=False),
        Parameter('mavlink_url', value=KERNEL_PORT)])
    probe = rclpy.create_node(f'sim_lock_probe_{tag}', context=ros_context)
    gcs = mavutil.mavlink_connection(f'udpout:127.0.0.1:{sim.autopilot.local_port}',
                                     source_system=255, source_component=190)
    stamps = []
    answer = {'on': False}

    def answer_frame(t_ns):
        # level attitude, hover thrust, body rates ignored; time_boot_ms echoes the frame
        gcs.mav.set_attitude_target_send(t_ns // 1_000_000, 1, 1, BODY_RATES_IGNORED,
                                         [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.5)

    def on_image(msg):
        stamps.append(_stamp_ns(msg.header))
        if answer['on']:
            answer_frame(stamps[-1])

    probe.create_subscription(Image, 'down_camera/image_raw', on_image, qos_profile_sensor_data)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(sim)
    executor.add_node(probe)
    try:
        assert _spin_until(executor, lambda: len(stamps) >= 1, 20.0)
        _spin_until(executor, lambda: False, 0.5)
        assert stamps == [0]                      # unanswered: sim time stands still
        answer['on'] = True
        answer_frame(0)
        assert _spin_until(executor, lambda: len(stamps) >= 12, 30.0), stamps
    finally:
        executor.shutdown()
        probe.destroy_node()
        sim.destroy_node()
        gcs.close()
    frames = sorted(set(stamps))
    assert np.array_equal(np.diff(frames), np.full(len(frames) - 1, 20_000_000))
    assert sim.sim.lockstep.timeouts == 0


def test_sim_node_read_noise_and_frozen_front_camera(ros_context):
    """Noise: no two consecutive frames alike; a frozen camera repeats one image re-stamped."""
    tag = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
    params = [Parameter('pacing', value='realtime'),
              Parameter('start_on_setpoints', value=False),
              Parameter('real_time_factor', value=0.25),
              Parameter('mavlink_url', value=KERNEL_PORT),
              Parameter('fault_front_camera_freeze_s', value=[0.04, 100.0])]
    sim = SimNode(node_name=f'sim_freeze_{tag}', parameter_overrides=params, context=ros_context)
    probe = rclpy.create_node(f'sim_freeze_probe_{tag}', context=ros_context)
    got = {cam: [] for cam in CAMERAS}
    for cam in CAMERAS:
        probe.create_subscription(Image, f'{cam}_camera/image_raw', got[cam].append,
                                  qos_profile_sensor_data)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(sim)
    executor.add_node(probe)
    try:
        assert _spin_until(executor, lambda: all(len(v) >= 6 for v in got.values()), 30.0), \
            {k: len(v) for k, v in got.items()}
    finally:
        executor.shutdown()
        probe.destroy_node()
        sim.destroy_node()
    assert sim.sim.config.read_noise_std == 1.5               # params.yaml's default
    for cam in CAMERAS:
        msgs = sorted(got[cam], key=lambda m: _stamp_ns(m.header))
        stamps = [_stamp_ns(m.header) for m in msgs]
        assert len(set(stamps)) == len(stamps)                  # new stamps every frame
        data = {s: bytes(m.data) for s, m in zip(stamps, msgs)}
        if cam == 'down':   # live (a still vehicle's frames differ too: test_sim_sensor_noise)
            assert all(data[a] != data[b] for a, b in zip(stamps, stamps[1:]))
        else:               # frozen from 0.04 s: the image of 0.04 s, re-stamped
            frozen = [d for s, d in data.items() if s >= 40_000_000]
            assert len(frozen) >= 4 and len(set(frozen)) == 1
            assert all(d != frozen[0] for s, d in data.items() if s < 40_000_000)


@pytest.mark.parametrize('overrides, reason', [
    ({'firmware': 'betaflight'},
     "parameter firmware must be one of ('', 'px4', 'ardupilot'), got 'betaflight'"),
    ({'firmware': 'px4'}, "firmware 'px4' runs in lockstep only"),
    ({'firmware': 'ardupilot'}, "firmware 'ardupilot' runs in lockstep only"),
    ({'firmware': 'ardupilot', 'pilot_switch_channel': 7},
     'firmware ardupilot takes no RC input from the sim'),
])
def test_sim_node_refuses_a_bad_firmware_parameter(ros_context, overrides, reason):
    """An unknown firmware, or a firmware off lockstep, is refused by name before any socket
    opens or any firmware is waited for (the node never starts on it)."""
    tag = f'{os.getpid()}_{int(time.monotonic() * 1e3) % 100000}'
    with pytest.raises(ValueError, match=re.escape(reason)):
        SimNode(node_name=f'sim_fw_{tag}', context=ros_context, parameter_overrides=[
            Parameter('mavlink_url', value=KERNEL_PORT), Parameter('pacing', value='realtime'),
            *(Parameter(k, value=v) for k, v in overrides.items())])
