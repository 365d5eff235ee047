"""Throughput of the simulator (issue 14 item 5): parallel renders, wall budget, flight timing.

The cameras rendered on parallel threads must give the very images of one after the other
(the lockstep reference repeats bit for bit); the wall budget and the run's sim/wall figure are
the permanent measurements of docs/sim.md and docs/performance.md.
"""
import numpy as np
import pytest

from ibvs_bringup.preflight import GraphHealth
from ibvs_harness.run_scenario import flight_timing, main, parse_args
from ibvs_harness.scenario import MAX_SIM_TIME_S
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_common.core.frames import rot_from_euler_zyx
from ibvs_sim.core.graph_sync import ImuBeforeImages
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import FrameOutput, SimConfig, Simulation
from ibvs_sim.core.timing import wall_budget
from ibvs_sim.core.world import load_world

from ibvs_sim.testing import HoverAutopilot


@pytest.fixture(scope='module')
def configs():
    return load_world(), load_pad_layout(), load_vehicle()


def _sim(configs, **kw):
    world, pad, vehicle = configs
    return Simulation(world, pad, vehicle, HoverAutopilot(),
                      SimConfig(pacing=Pacing.LOCKSTEP, read_noise_std=1.5, **kw))


def test_parallel_renders_are_the_serial_ones_bit_for_bit(configs):
    parallel, serial = _sim(configs), _sim(configs, parallel_render=False)
    world = configs[0]
    path = np.linspace(world.initial_position_I, [0.0, 0.0, -0.3], 6)
    try:
        for k, xi in enumerate(path):
            R_IB = rot_from_euler_zyx(0.1 * np.sin(k), 0.08 * np.cos(k), 0.2 * k)
            a = parallel.cameras.render(R_IB, xi, k)
            b = serial.cameras.render(R_IB, xi, k)
            assert list(a) == list(b) == ['front', 'down']        # the cameras' order
            for cam in a:
                assert a[cam].dtype == np.uint8 and np.array_equal(a[cam], b[cam])
        assert parallel.cameras._render_pool is not None and serial.cameras._render_pool is None
    finally:
        parallel.close()
    parallel.close()                                             # idempotent
    assert parallel.cameras._render_pool is None
    assert set(parallel.cameras.render(np.eye(3), path[0], 0)) == {'front', 'down'}
    parallel.close()


def test_frames_of_a_parallel_sim_repeat_those_of_a_serial_one(configs):
    runs = []
    for parallel in (True, False):
        sim = _sim(configs, parallel_render=parallel)
        runs.append([sim.step_frame() for _ in range(3)])
        sim.close()
    for a, b in zip(*runs):
        assert a.t_ns == b.t_ns
        assert all(np.array_equal(a.images[c], b.images[c]) for c in ('front', 'down'))


def test_the_sim_counts_its_wall_time_in_physics_and_render(configs):
    sim = _sim(configs)
    assert sim.physics.wall_s == sim.cameras.wall_s == 0.0
    sim.step_frame()                                   # frame 0: render only
    assert sim.physics.wall_s == 0.0 and sim.cameras.wall_s > 0.0
    render0 = sim.cameras.wall_s
    sim.step_frame()
    assert sim.physics.wall_s > 0.0 and sim.cameras.wall_s > render0
    sim.close()


def test_wall_budget_per_frame_and_the_graph_wait_as_the_rest():
    out = wall_budget(2.0, 50, {'physics': 0.1, 'render': 0.5, 'publish': 0.1,
                                'imu_hold': 0.05})
    assert out['sim_wall_s'] == 2.0
    assert out['wall_physics_ms_per_frame'] == pytest.approx(2.0)
    assert out['wall_render_ms_per_frame'] == pytest.approx(10.0)
    assert out['wall_imu_hold_ms_per_frame'] == pytest.approx(1.0)
    assert out['wall_graph_wait_ms_per_frame'] == pytest.approx(25.0)     # 1.25 s / 50
    # parts measured on another clock may exceed the wall: the wait is never negative
    assert wall_budget(1.0, 10, {'render': 1.2})['wall_graph_wait_ms_per_frame'] == 0.0
    assert wall_budget(1.0, 0, {}) == {} and wall_budget(0.0, 5, {}) == {}


def test_imu_hold_counts_the_wall_time_frames_were_held():
    hold = ImuBeforeImages(timeout_s=1.0)
    hold.note_imu(0)
    frame = FrameOutput(20_000_000, {}, None, [])
    assert hold.hold(frame, now=10.0) is None
    assert hold.release(10.004) is None
    hold.note_imu(20_000_000)
    assert hold.release(10.010) is frame
    assert hold.held_s == pytest.approx(0.010)
    assert hold.hold(FrameOutput(20_000_000, {}, None, []), now=11.0) is not None   # covered
    assert hold.held_s == pytest.approx(0.010)


class FakeMonitor:
    def __init__(self, first, sim_s):
        self.first_truth_wall, self._sim_s = first, sim_s

    def now_s(self):
        return self._sim_s


def test_flight_timing_is_sim_time_over_wall_time_since_frame_0():
    out = flight_timing(FakeMonitor(100.0, 14.6), 120.0)
    assert out == {'flight_sim_s': 14.6, 'wall_s': 20.0, 'sim_over_wall': 0.73}
    assert flight_timing(FakeMonitor(None, 3.0), 120.0) == {}      # no frame 0 seen
    assert flight_timing(None, 120.0) == {}                        # no monitor


def test_max_sim_time_option():
    assert parse_args(['--run-name', 'x']).max_sim_time_s == MAX_SIM_TIME_S
    assert parse_args(['--run-name', 'x', '--max-sim-time', '1.5']).max_sim_time_s == 1.5


@pytest.mark.parametrize('bad', ['0', '-1', 'nan'])
def test_a_max_sim_time_that_is_not_positive_is_refused(bad, tmp_path, capsys):
    code = main(['--run-name', 'x', '--results-root', str(tmp_path), '--max-sim-time', bad])
    assert code == 2
    assert '--max-sim-time must be > 0' in capsys.readouterr().err
    assert not (tmp_path / 'x').exists()            # refused before anything was written


class FakeSub:
    def __init__(self, topic):
        self.topic_name = topic


class FakeNode:
    """Just what GraphHealth needs of a node."""

    def __init__(self):
        self.destroyed = []

    def create_subscription(self, msg_type, topic, callback, qos):
        return FakeSub(topic if topic.startswith('/') else '/' + topic)

    def destroy_subscription(self, sub):
        self.destroyed.append(sub.topic_name)


def test_preflight_only_subscriptions_are_dropped_after_the_preflight():
    node = FakeNode()
    health = GraphHealth(node)
    health.stop_preflight_only()
    assert sorted(node.destroyed) == ['/down_camera/camera_info', '/front_camera/camera_info',
                                      '/imu/data', '/window/corners']
    assert sorted(s.topic_name for s in health.subs) == ['/diagnostics', '/ibvs/mode']
