"""The camera model of ibvs_sim: stamps at exposure, delivery later, jitter, drops, 30 Hz, blur.

Against values computed by hand here, not by the model: a stamp is the exposure's mid-point,
a delivery is the stamp plus the latency, a time offset stamps tau - offset, 30 Hz instants
are k / 30 s rounded to the 2 ms grid, the jitter has the asked distribution per seed.
"""
import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_common.core.frames import rot_z
from ibvs_common.core.modes import Mode
from ibvs_sim.config import SimNodeConfig
from ibvs_sim.core.camera_model import CameraTiming, FrameClock, frame_clocks, Jitter, StampAt
from ibvs_sim.core.capture import FrameCapture, interpolate, Pose
from ibvs_sim.core.dynamics import WindConfig
from ibvs_sim.core.graph_sync import GraphProducts, ImuBeforeImages, STATUS_TOPIC
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import FrameOutput, SimConfig, Simulation
from ibvs_sim.core.world import load_world
from ibvs_sim.testing import HoverAutopilot

MS = 1_000_000                # ns
STEP = 2 * MS                 # the physics step (500 Hz)


def _clock(seed=0, **timing):
    offsets = timing.pop('offsets', {'front': 0.0, 'down': 0.0})
    return FrameClock({c: CameraTiming(time_offset_s=o, **timing) for c, o in offsets.items()},
                      STEP, seed)


def test_the_stamp_is_the_exposure_mid_point_and_start_and_end_move_the_exposure():
    # 50 Hz, 10 ms exposure in 5 renders: frame 3's stamp instant is 60 ms; mid-exposure
    # stamps mean the exposure is [55, 65] ms, rendered at the middles of its fifths
    mid = _clock(exposure_s=0.010, exposure_samples=5).plan(3, None)
    assert mid.instant_ns == 60 * MS and mid.stamps_ns == {'front': 60 * MS, 'down': 60 * MS}
    assert mid.samples_ns == (56 * MS, 58 * MS, 60 * MS, 62 * MS, 64 * MS)
    assert np.mean(mid.samples_ns) == mid.stamps_ns['down']          # the exposure's middle
    start = _clock(exposure_s=0.010, exposure_samples=5, stamp_at=StampAt.START).plan(3, None)
    assert start.samples_ns == (61 * MS, 63 * MS, 65 * MS, 67 * MS, 69 * MS)   # [60, 70] ms
    end = _clock(exposure_s=0.010, exposure_samples=2, stamp_at=StampAt.END).plan(3, None)
    assert end.samples_ns == (int(52.5 * MS), int(57.5 * MS))            # [50, 60] ms
    # an instant exposure: one render at the stamp; frame 0's exposure never before t = 0
    assert _clock().plan(3, None).samples_ns == (60 * MS,)
    assert min(_clock(exposure_s=0.010, exposure_samples=5).plan(0, None).samples_ns) == 0


def test_delivery_is_the_stamp_plus_the_latency_on_the_physics_grid():
    clock = _clock(latency_s=0.030)
    for k in range(20):
        frame = clock.next()
        assert frame.delivery_ns == frame.stamps_ns['front'] + 30 * MS
    # a latency between two physics steps is delivered at the nearest one (31 ms -> 32)
    assert _clock(latency_s=0.031).plan(1, None).delivery_ns == 20 * MS + 32 * MS
    # never before the exposure ended: a mid-stamped 10 ms exposure without latency ends 5 ms
    # after its stamp, so it is delivered then (6 ms: the next step)
    late = _clock(exposure_s=0.010, exposure_samples=5).plan(1, None)
    assert late.delivery_ns == 20 * MS + 6 * MS


def test_a_time_offset_stamps_the_exposure_at_tau_minus_the_offset():
    """kalibr's timeshift_cam_imu: an image stamped s was exposed at IMU time s + offset."""
    clock = _clock(latency_s=0.020, offsets={'front': 0.004, 'down': -0.003})
    frame = clock.plan(5, None)
    tau = 100 * MS                                  # frame 5 of a 50 Hz camera
    assert frame.instant_ns == tau
    assert frame.stamps_ns == {'front': tau - 4 * MS, 'down': tau + 3 * MS}
    assert frame.delivery_ns == tau + 20 * MS      # the latency counts from the exposure
    # a stamp later than the delivery would say a time the clock has not reached: not before
    assert _clock(offsets={'down': -0.003}).plan(5, None).delivery_ns == tau + 4 * MS


def test_30_hz_stamps_are_k_over_30_rounded_to_the_2_ms_grid():
    clock = _clock(rate_hz=30.0)
    instants = [clock.next().instant_ns for _ in range(91)]
    by_hand = [0, 34, 66, 100, 134, 166, 200]      # k / 30 s, nearest 2 ms
    assert instants[:7] == [t * MS for t in by_hand]
    exact = np.arange(91) * 1e9 / 30.0
    assert np.max(np.abs(np.array(instants) - exact)) <= 1 * MS     # +-1 ms stamp jitter
    assert all(t % STEP == 0 for t in instants)
    assert instants[90] == 3 * 1_000 * MS          # 90 frames: exactly 3 s, no drift


@pytest.mark.parametrize('kind, std_ms', [(Jitter.UNIFORM, 5.0 / np.sqrt(3.0)),
                                          (Jitter.NORMAL, 5.0)])
def test_the_delivery_jitter_has_its_distribution_and_its_seed(kind, std_ms):
    n = 4000
    clock = _clock(seed=7, latency_s=0.030, jitter_s=0.005, jitter=kind)
    draws = np.array([clock.jitter_ns(k) for k in range(n)]) / MS
    assert abs(draws.mean()) < 4 * std_ms / np.sqrt(n)
    assert draws.std() == pytest.approx(std_ms, rel=0.05)
    if kind is Jitter.UNIFORM:
        assert draws.min() >= -5.0 and draws.max() <= 5.0 and draws.min() < -4.9
        assert draws.max() > 4.9
    frames = [clock.next() for _ in range(200)]
    lateness = np.array([f.delivery_ns - f.instant_ns for f in frames]) / MS
    assert np.all(lateness >= 2.0)                 # never before the exposure (or t = 0)
    assert np.all(np.diff([f.delivery_ns for f in frames]) >= STEP)   # in order
    # the same seed gives the same deliveries, another seed others
    again = _clock(seed=7, latency_s=0.030, jitter_s=0.005, jitter=kind)
    assert [again.next().delivery_ns for _ in range(200)] == [f.delivery_ns for f in frames]
    other = _clock(seed=8, latency_s=0.030, jitter_s=0.005, jitter=kind)
    assert [other.next().delivery_ns for _ in range(200)] != [f.delivery_ns for f in frames]


def test_dropped_frames_have_their_probability_per_camera_never_frame_0():
    clock = _clock(seed=3, drop_probability=0.2)
    frames = [clock.next() for _ in range(5000)]
    assert frames[0].dropped == ()
    lost = np.array([[c in f.dropped for c in ('front', 'down')] for f in frames[1:]])
    assert lost.mean(axis=0) == pytest.approx([0.2, 0.2], abs=0.02)
    assert abs(np.corrcoef(lost.T)[0, 1]) < 0.05     # each camera on its own
    assert all(set(f.cameras) | set(f.dropped) == {'front', 'down'} for f in frames)


def test_cameras_with_another_rate_get_a_clock_of_their_own():
    clocks = frame_clocks({'front': CameraTiming(rate_hz=30.0, time_offset_s=0.001),
                           'down': CameraTiming(rate_hz=50.0)}, STEP, 0)
    assert [c.cameras for c in clocks] == [('front',), ('down',)]
    shared = frame_clocks({'front': CameraTiming(time_offset_s=0.001),
                           'down': CameraTiming(time_offset_s=-0.002)}, STEP, 0)
    assert [c.cameras for c in shared] == [('front', 'down')]
    with pytest.raises(ValueError):
        CameraTiming(exposure_s=0.021)             # longer than a 50 Hz frame
    with pytest.raises(ValueError):
        CameraTiming(drop_probability=1.0)


class PoseRig:
    """A camera rig whose 'image' is the pose: x of the body in mm, as grey levels."""

    def __init__(self):
        self.renders = []

    def render_clean(self, names, R_IB, xi_I):
        self.renders.append(float(xi_I[0]))
        return {n: np.full((2, 2), round(xi_I[0] * 1000.0) % 256, np.uint8) for n in names}

    def add_noise(self, name, image, frame_index):
        return image


def test_an_exposure_averages_the_renders_at_the_interpolated_poses():
    """Motion blur: the mean of the renders at the exposure's instants, between physics steps.

    The body moves along x at 1 mm per ms; frame 1's 10 ms exposure, mid-stamped at 20 ms, is
    [15, 25] ms, rendered 4 times at the middles of its quarters (between physics steps): x
    there is 16.25 ... 23.75 mm, and their mean is x at the stamp, 20 mm.
    """
    clock = _clock(exposure_s=0.010, exposure_samples=4, offsets={'down': 0.0})
    rig = PoseRig()
    capture = FrameCapture([clock], rig)

    def pose(t_ns):
        return Pose(t_ns, np.eye(3), np.array([0.001 * t_ns / MS, 0.0, 0.0]))

    t = 0
    capture.expose(pose(0), pose(0))
    while t < 40 * MS:
        capture.expose(pose(t), pose(t + STEP))
        t += STEP
    frame = [f for f in capture.pending if f.plan.index == 1][0]
    assert frame.plan.samples_ns == (int(16.25 * MS), int(18.75 * MS), int(21.25 * MS),
                                     int(23.75 * MS))
    assert rig.renders[4:8] == pytest.approx([0.01625, 0.01875, 0.02125, 0.02375])
    assert frame.images['down'][0, 0] == 20       # (16 + 19 + 21 + 24) / 4 grey levels
    # the interpolation itself: halfway in position, halfway in angle; the ends exactly
    a, b = Pose(0, np.eye(3), np.zeros(3)), Pose(STEP, rot_z(0.2), np.array([2.0, 0.0, 0.0]))
    R, xi = interpolate(a, b, STEP // 2)
    assert xi == pytest.approx([1.0, 0.0, 0.0]) and R == pytest.approx(rot_z(0.1))
    assert interpolate(a, b, STEP)[0] is b.R_IB and interpolate(a, b, 0)[1] is a.xi_I


@pytest.fixture(scope='module')
def configs():
    return load_world(), load_pad_layout(), load_vehicle()


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def _sim(configs, timing, products=None, clock=None, pacing=Pacing.LOCKSTEP, **kw):
    world, pad, vehicle = configs
    cfg = SimConfig(pacing=pacing, render=False, lockstep_timeout_s=1.0,
                    camera_timing={c: timing for c in ('front', 'down')}, **kw)
    return Simulation(world, pad, vehicle, HoverAutopilot(), cfg, wall_clock=clock or Clock(),
                      products=products)


def test_lockstep_delivers_a_late_frame_after_the_next_one_was_exposed(configs):
    """30 ms latency at 50 Hz: the frame of 0 ms goes out at 30 ms, that of 20 ms at 50 ms.

    Physics runs on between a frame's exposure and its delivery: the frame of 20 ms shows the
    vehicle (pushed along x by a wind) where it was at 20 ms, as a latency-free sim renders
    it, and goes out with the ground truth of 50 ms; the frame of 40 ms is exposed before the
    one of 20 ms is delivered, and the sim waits for the answer to the frame's stamp, not to
    its delivery time.
    """
    wind = WindConfig(steady_force_I=(3.0, 0.0, 0.0))
    sim = _sim(configs, CameraTiming(latency_s=0.030), wind=wind)
    sim.capture.rig = rig = PoseRig()
    ap = sim.autopilot
    out = sim.tick()
    assert (out.t_ns, out.stamps_ns) == (30 * MS, {'front': 0, 'down': 0})
    assert out.answer_ns == 0 and sim.answer_ms == 0 and sim.t_ns == 30 * MS
    assert sim.tick() is None                      # no answer yet: sim time stands still
    ap.last_setpoint_time_boot_ms = 0              # the answer echoes the stamp, 0 ms
    out = sim.tick()
    assert out.t_ns == 50 * MS and out.stamp_ns('front') == 20 * MS
    assert [f.plan.instant_ns for f in sim.capture.pending] == [40 * MS]   # exposed already
    ap.last_setpoint_time_boot_ms = 20
    assert sim.tick().t_ns == 70 * MS
    ideal, truth = _sim(configs, CameraTiming(), wind=wind), {}
    for _ in range(4):                             # a latency-free sim: 0, 20, 40, 60 ms
        ideal.autopilot.last_setpoint_time_boot_ms = ideal.answer_ms
        frame = ideal.tick()
        truth[frame.t_ns] = frame.state.xi_I[0]
    assert rig.renders[:3] == [truth[0], truth[20 * MS], truth[40 * MS]]    # at the stamps
    assert truth[40 * MS] < out.state.xi_I[0] < truth[60 * MS]              # 50 ms


def test_a_30_hz_lockstep_run_delivers_on_the_rounded_grid(configs):
    sim = _sim(configs, CameraTiming(rate_hz=30.0))
    ap = sim.autopilot
    times = []
    for _ in range(7):
        out = sim.tick()
        times.append(out.t_ns // MS)
        ap.last_setpoint_time_boot_ms = out.answer_ns // MS
    assert times == [0, 34, 66, 100, 134, 166, 200]


def test_no_answer_is_awaited_when_the_image_of_the_modes_camera_was_dropped(configs):
    """The graph evaluates its mode on one camera: without that image it owes no answer."""
    products = GraphProducts({})
    products.note_status(0, Mode.LANDING)          # the down camera's mode
    sim = _sim(configs, CameraTiming(drop_probability=0.5), products)
    ap = sim.autopilot
    out = sim.tick()                               # frame 0: never dropped
    counts = {True: 0, False: 0}
    for _ in range(40):
        owed = 'down' in out.stamps_ns
        counts[owed] += 1
        assert (sim.answer_ms is not None) == owed == (out.answer_ns is not None)
        ap.last_setpoint_time_boot_ms = None
        nxt = sim.tick()
        if owed:
            assert nxt is None                     # waits for the answer to the down image
            ap.last_setpoint_time_boot_ms = out.answer_ns // MS
            nxt = sim.tick()
        assert nxt is not None and nxt.t_ns > out.t_ns
        out = nxt
    assert counts[True] > 5 and counts[False] > 5
    assert sim.lockstep.timeouts == 0


def test_the_products_awaited_follow_each_cameras_stamp_and_the_status_only_when_owed():
    used_in = {'window/corners': {Mode.IDLE, Mode.WINDOW},
               'down_camera/translational_flow': {Mode.CROSSING, Mode.LANDING}}
    products = GraphProducts({'window/corners': 'front',
                              'down_camera/translational_flow': 'down'}, used_in=used_in)
    live = {'window/corners': 1, 'down_camera/translational_flow': 1, STATUS_TOPIC: 1}
    products.note_status(0, Mode.WINDOW)
    assert products.mode_camera() == 'front'
    # the front image stamped 4 ms before the down one (time offsets): each its own stamp
    products.expect(36 * MS, ['front', 'down'], live, {'front': 36 * MS, 'down': 40 * MS})
    assert products.missing() == [STATUS_TOPIC]
    products.note_status(36 * MS, Mode.CROSSING)
    assert products.mode_camera() == 'down'
    products.note('down_camera/translational_flow', 36 * MS)      # not the down image's
    assert products.missing() == ['down_camera/translational_flow']
    products.note('down_camera/translational_flow', 40 * MS)
    assert products.missing() == []
    # only the front image went out while the mode is on the down camera: no status owed
    products.expect(60 * MS, ['front'], live, status=False)
    assert products.missing() == []


def test_images_wait_for_every_imu_sample_sent_by_their_delivery():
    hold = ImuBeforeImages(timeout_s=1.0)
    hold.note_imu(40 * MS)
    late = FrameOutput(50 * MS, {}, None, [], {'down': 20 * MS}, 20 * MS, imu_ns=50 * MS)
    assert hold.hold(late, now=0.0) is None         # the stamp is covered, the delivery not
    hold.note_imu(50 * MS)
    assert hold.release(now=0.1) is late


def test_frames_stop_waiting_for_an_imu_that_stopped_until_it_comes_again():
    """imu/data comes from the bridge: a bridge that died would hold every frame for the
    time-out. Two time-outs in a row and frames go at once, until a newer sample comes."""
    hold = ImuBeforeImages(timeout_s=1.0)
    hold.note_imu(20 * MS)

    def frame(ms):
        return FrameOutput(ms * MS, {}, None, [], {'down': ms * MS}, ms * MS)

    for k, ms in enumerate((40, 60)):
        assert hold.hold(frame(ms), now=10.0 * k) is None
        assert hold.release(now=10.0 * k + 0.5) is None
        assert hold.release(now=10.0 * k + 1.0).t_ns == ms * MS and hold.timed_out
    assert hold.silent and hold.timeouts == 2
    assert hold.hold(frame(80), now=30.0).t_ns == 80 * MS       # not held
    hold.note_imu(100 * MS)                                     # imu/data again
    assert not hold.silent
    assert hold.hold(frame(120), now=31.0) is None              # held again
    # one time-out between covered frames never silences it
    hold = ImuBeforeImages(timeout_s=1.0)
    for k in range(4):
        hold.note_imu((40 * k + 20) * MS)
        assert hold.hold(frame(40 * k + 20), now=float(k)) is not None    # covered
        assert hold.hold(frame(40 * k + 40), now=float(k)) is None
        assert hold.release(now=k + 1.0) is not None
    assert hold.timeouts == 4 and not hold.silent


def test_the_node_parameters_make_each_cameras_timing_with_the_true_offsets(configs):
    from dataclasses import replace
    vehicle = configs[2]
    truth = replace(vehicle, cameras={
        'front': replace(vehicle.cameras['front'], time_offset_s=0.004),
        'down': replace(vehicle.cameras['down'], rate_hz=30.0)})
    cfg = SimNodeConfig(camera_latency_s=0.03, camera_jitter_s=0.005,
                        camera_jitter_distribution='normal', camera_drop_probability=0.1,
                        camera_exposure_s=0.004, camera_exposure_samples=3,
                        camera_stamp_at='start', camera_rate_hz=[0.0, 0.0])
    timing = cfg.camera_timing(truth)
    assert timing['front'] == CameraTiming(50.0, 0.03, 0.005, Jitter.NORMAL, 0.1, 0.004, 3,
                                           StampAt.START, 0.004)
    assert timing['down'].rate_hz == 30.0 and timing['down'].time_offset_s == 0.0
    assert SimNodeConfig(camera_rate_hz=[30.0, 0.0]).camera_timing(vehicle)['front'].rate_hz \
        == 30.0
    for bad in ({'camera_jitter_distribution': 'cauchy'}, {'camera_stamp_at': 'middle'},
                {'camera_rate_hz': [30.0]}, {'camera_drop_probability': 1.0}):
        with pytest.raises(ValueError, match=list(bad)[0]):
            SimNodeConfig(**bad)
    with pytest.raises(ValueError, match='exposure'):
        SimNodeConfig(camera_exposure_s=0.05).camera_timing(vehicle)


@pytest.mark.parametrize('name, field, default, most', [
    ('accel_noise_std_mps2', 'accel_noise_std', (0.28, 0.95, 0.80), 5.0),
    ('gyro_noise_std_radps', 'gyro_noise_std', (0.005, 0.005, 0.005), 1.0)])
def test_a_noise_parameter_reaches_the_autopilot_and_is_checked(configs, name, field, default,
                                                                most):
    """accel_noise_std_mps2 (PX4 SIH's by default), gyro_noise_std_radps (0.005 by default):
    3 stds (FRD); a wrong one is refused."""
    vehicle = configs[2]
    assert getattr(SimNodeConfig().autopilot_config(vehicle, 0.0), field) == default
    cfg = SimNodeConfig(**{name: [0.0, 0.1, 0.2]})
    assert getattr(cfg.autopilot_config(vehicle, 0.0), field) == (0.0, 0.1, 0.2)
    for bad in ([0.1, 0.1], [0.1, -0.1, 0.1], [0.1, float('nan'), 0.1], [0.1, float('inf'), 0.1],
                [0.1, 0.1, most + 0.5]):
        with pytest.raises(ValueError, match=name):
            SimNodeConfig(**{name: bad}).autopilot_config(vehicle, 0.0)
