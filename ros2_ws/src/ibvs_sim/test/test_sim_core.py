"""Simulation loop of ibvs_sim: pacing (lockstep, realtime), determinism and contact events."""
import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import euler_zyx_from_rot, GRAVITY, rot_x
from ibvs_common.core.modes import Mode
from ibvs_sim.core.autopilot import AttitudeReference
from ibvs_sim.core.dynamics import PlantParams, WindConfig
from ibvs_sim.core.events import EventType
from ibvs_sim.core.graph_sync import FirstFrameHold, GraphProducts, STATUS_TOPIC
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import SimConfig, Simulation
from ibvs_sim.core.timing import AnswerLatency


class FakeAutopilot:
    """Constant reference; records polls; answers frames when told to."""

    def __init__(self, thrust=0.5, q=(1.0, 0.0, 0.0, 0.0), R_err=None):
        self.thrust, self.q = thrust, np.array(q)
        self.R_err = np.eye(3) if R_err is None else R_err    # estimate = R_IB R_err
        self.last_setpoint_time_boot_ms = None
        self.awaits_setpoints = True
        self.polls = 0
        self.receiving_polls = 0
        self.telemetry_times = []       # sim times of the polls that may send telemetry

    def poll(self, state, receive=True, telemetry=True):
        self.polls += 1
        self.receiving_polls += int(receive)
        if telemetry:
            self.telemetry_times.append(state.t)

    def attitude_reference(self, state):
        return AttitudeReference(self.q, self.thrust, 'offboard')

    def estimate_error(self, t):
        return self.R_err


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture(scope='module')
def configs():
    return load_world(), load_pad_layout(), load_vehicle()


def _sim(configs, ap, clock=None, products=None, clock_sink=None, **kw):
    world, pad, vehicle = configs
    cfg = SimConfig(render=kw.pop('render', False), **kw)
    return Simulation(world, pad, vehicle, ap, cfg, wall_clock=clock or FakeClock(),
                      products=products, clock_sink=clock_sink)


def test_first_frame_is_the_initial_condition_with_images(configs):
    ap = FakeAutopilot()
    sim = _sim(configs, ap, render=True)
    out = sim.tick()
    assert out.t_ns == 0
    assert out.state.xi_I == pytest.approx(configs[0].initial_position_I)
    assert set(out.images) == {'front', 'down'}
    assert out.images['down'].shape == (480, 752) and out.images['down'].dtype == np.uint8


def test_lockstep_waits_for_the_answer_or_the_timeout(configs):
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.LOCKSTEP, lockstep_timeout_s=1.0)
    assert sim.tick().t_ns == 0
    assert sim.tick() is None                      # no setpoint yet
    clock.now += 0.5
    assert sim.tick() is None
    ap.last_setpoint_time_boot_ms = 0              # the answer to frame t = 0 ms
    out = sim.tick()
    assert out.t_ns == 20_000_000
    assert sim.tick() is None                      # the answer to 20 ms has not come
    ap.last_setpoint_time_boot_ms = 19             # stale answer: still waiting
    assert sim.tick() is None
    clock.now += 1.0                               # wall-clock timeout
    assert sim.tick().t_ns == 40_000_000
    assert sim.lockstep.timeouts == 1


def test_lockstep_stops_waiting_for_answers_once_the_autopilot_flies_its_own_mode(configs):
    # A bridge that handed the vehicle back to the autopilot's failsafe sends no setpoints:
    # lockstep must not stall every frame for the time-out (a campaign run stalled for hours).
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.LOCKSTEP, lockstep_timeout_s=5.0)
    assert sim.tick().t_ns == 0
    assert sim.tick() is None                      # awaited: no answer yet
    ap.awaits_setpoints = False                    # e.g. the offboard-loss failsafe lands
    for k in range(1, 4):
        assert sim.tick().t_ns == k * 20_000_000   # frame after frame, no wall-clock wait
    assert sim.lockstep.timeouts == 0


def test_lockstep_stops_waiting_for_a_silent_answerer_until_it_answers_again(configs):
    """Two full time-outs in a row (a bridge that died): the next frames go without a wait,
    frame after frame, until a new answer comes; then each frame waits for its answer again.
    A time-out between answered frames (a frame the graph skipped) never makes it silent."""
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.LOCKSTEP, lockstep_timeout_s=1.0)
    assert sim.tick().t_ns == 0
    ap.last_setpoint_time_boot_ms = 0
    assert sim.tick().t_ns == 20_000_000
    for k in (2, 3):                               # the bridge died: two full time-outs
        assert sim.tick() is None
        clock.now += 1.0
        assert sim.tick().t_ns == k * 20_000_000
    assert sim.lockstep.timeouts == 2 and sim.lockstep.silent and sim.lockstep.silences == 1
    for k in (4, 5, 6):                            # silent: no wall-clock wait
        assert sim.tick().t_ns == k * 20_000_000
    assert sim.lockstep.timeouts == 2
    ap.last_setpoint_time_boot_ms = 120            # an answer again (a bridge restarted)
    assert sim.tick().t_ns == 7 * 20_000_000 and not sim.lockstep.silent
    assert sim.tick() is None                      # the answer to 140 ms is waited for
    # alternating: a skipped frame's time-out, then an answered frame, never silent
    ap2, clock2 = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap2, clock2, pacing=Pacing.LOCKSTEP, lockstep_timeout_s=1.0)
    assert sim.tick().t_ns == 0
    for k in range(1, 7):
        if k % 2:
            ap2.last_setpoint_time_boot_ms = (k - 1) * 20
        else:
            clock2.now += 1.0
        assert sim.tick().t_ns == k * 20_000_000
    assert sim.lockstep.timeouts == 3 and not sim.lockstep.silent


@pytest.mark.parametrize('pacing, receiving_substeps', [(Pacing.LOCKSTEP, 0),
                                                        (Pacing.REALTIME, 'all')])
def test_lockstep_reads_mavlink_only_between_frames(configs, pacing, receiving_substeps):
    # A datagram landing while a frame's substeps are computed must not take effect at a
    # wall-clock-dependent substep in lockstep; in realtime it arrives whenever it arrives.
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=pacing)
    sim.tick()
    polls, receiving = ap.polls, ap.receiving_polls
    sim.step_frame()
    n_polls = ap.polls - polls
    assert n_polls == sim.substeps + 1            # each substep, then the frame-time telemetry
    expected = n_polls if receiving_substeps == 'all' else receiving_substeps
    assert ap.receiving_polls - receiving == expected
    ap.last_setpoint_time_boot_ms = 20
    polls, receiving = ap.polls, ap.receiving_polls
    if pacing is Pacing.LOCKSTEP:
        sim.tick()                                 # waiting between frames: reads
        assert ap.receiving_polls - receiving >= 1


def test_lockstep_moves_the_clock_before_the_autopilot_sends_anything_of_the_new_time(configs):
    # On a vehicle no autopilot message of time t reaches the companion before its clock reads
    # t. A /clock published only with the images lagged the autopilot's frame-time telemetry
    # (and its TIMESYNC) by a frame: the bridge's clock sync took 5 such samples in a row as a
    # time jump (ROS - boot = -20 ms) and the lockstep run stalled (2026-11-27).
    ap, clock = FakeAutopilot(), FakeClock()
    events = []
    ap_poll = ap.poll

    def poll(state, receive=True, telemetry=True):
        events.append(('poll', round(state.t * 1e9), receive))
        ap_poll(state, receive, telemetry)

    ap.poll = poll
    sim = _sim(configs, ap, clock, pacing=Pacing.LOCKSTEP,
               clock_sink=lambda t_ns: events.append(('clock', t_ns)))
    assert sim.tick().t_ns == 0
    for k in range(1, 4):
        ap.last_setpoint_time_boot_ms = 20 * (k - 1)
        assert sim.tick().t_ns == 20_000_000 * k
    clock_times = [e[1] for e in events if e[0] == 'clock']
    assert clock_times == [0, 20_000_000, 40_000_000, 60_000_000]
    period_ns, published, frame_polls = sim.period_ns, -1, 0
    for e in events:
        if e[0] == 'clock':
            published = e[1]
            continue
        _, t, receive = e
        if t % period_ns == 0 or receive:
            # the frame-time telemetry, and every poll that reads (answers TIMESYNC): the
            # clock already reads their time
            assert t <= published, events
            frame_polls += t % period_ns == 0
        else:
            # a substep's telemetry (the 100 Hz IMU between frames): within the frame period
            # that the clock moves through next (one /clock per frame in lockstep)
            assert published < t < published + period_ns, events
    assert frame_polls >= 4


def test_free_running_sim_leaves_its_clock_to_the_node(configs):
    # realtime: the node publishes /clock at every tick as sim time runs; no per-frame sink
    calls, clock = [], FakeClock()
    sim = _sim(configs, FakeAutopilot(), clock, pacing=Pacing.REALTIME, clock_sink=calls.append)
    sim.tick()
    clock.now += 0.1
    sim.tick()
    assert calls == []


def test_realtime_paces_by_the_wall_clock(configs):
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.REALTIME)
    sim.tick()
    assert sim.tick() is None
    clock.now += 0.021
    assert sim.tick().t_ns == 20_000_000
    assert sim.tick() is None
    clock.now += 5.0                               # the sim process stalled: re-phased
    assert sim.tick() is None and sim.realtime.stalls == 1 and sim.realtime.frames_dropped == 0
    clock.now += 0.02
    assert sim.tick().t_ns == 40_000_000


def test_free_running_sim_drops_the_frames_it_cannot_render_on_time(configs):
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.REALTIME, real_time_factor=0.5)
    assert sim.tick().t_ns == 0
    clock.now += 0.02                              # 10 ms of sim time: nothing due yet
    assert sim.tick() is None and sim.t_ns == 10_000_000
    clock.now += 0.08                              # sim time 50 ms: frame 20 ms is 30 ms late
    out = sim.tick()                               # -> dropped; frame 40 ms (10 ms late) goes
    assert out.t_ns == 40_000_000 and sim.realtime.frames_dropped == 1
    assert sim.tick() is None and sim.t_ns == 50_000_000     # physics caught up with the clock
    assert sim.realtime.sim_ns_at(clock.now + 1.0) == 550_000_000      # /clock runs at 0.5 x wall
    with pytest.raises(ValueError):
        _sim(configs, ap, clock, pacing=Pacing.REALTIME, real_time_factor=0.0)


def test_hover_reference_keeps_the_initial_condition(configs):
    sim = _sim(configs, FakeAutopilot(thrust=configs[2].hover_thrust))
    for _ in range(51):
        out = sim.step_frame()
    assert out.t == pytest.approx(1.0)
    assert out.state.xi_I == pytest.approx(configs[0].initial_position_I, abs=1e-6)


def test_the_autopilot_flies_its_attitude_estimate_not_the_truth(configs):
    """An estimate rolled by +d (R_err = rot_x(d)) holding level: the truth rolls by -d.

    The autopilot's loop drives its estimate R_IB R_err to the level reference, so the truth
    settles at R_IB = rot_x(-d), and the hover thrust (m g) along the tilted body axis pushes
    the vehicle sideways at a_y = -g sin d ({I}, NED: towards -y for a truth rolled left;
    less the plant's rotor drag),
    the horizontal disturbance of g * tilt error that an estimate error is to a controller.
    """
    d = np.radians(2.0)
    sim = _sim(configs, FakeAutopilot(thrust=configs[2].hover_thrust, R_err=rot_x(d)))
    for _ in range(51):
        out = sim.step_frame()                      # 1 s: the inner loop has settled
    roll, pitch, _ = euler_zyx_from_rot(out.state.R_IB)
    assert roll == pytest.approx(-d, abs=np.radians(0.01)) and abs(pitch) < 1e-6
    # v_y' = -g sin d - (k_D / m) v_y (the plant's rotor drag): closed form over 1 s
    k = PlantParams.from_vehicle(configs[2]).drag_coefficient / configs[2].mass
    v_inf = -GRAVITY * np.sin(d) / k
    v0 = out.state.v_I.copy()
    for _ in range(50):
        out = sim.step_frame()                      # one more second
    assert out.state.v_I[1] == pytest.approx(v_inf + (v0[1] - v_inf) * np.exp(-k), rel=0.01)
    assert v0[1] < -0.2 and abs(out.state.v_I[0]) < 1e-6


def test_two_runs_are_identical(configs):
    wind = WindConfig(steady_force_I=(0.2, 0.3, 0.0), gust_amplitude_N=0.4, seed=3)
    finals = []
    for _ in range(2):
        sim = _sim(configs, FakeAutopilot(thrust=0.52, q=(0.999, 0.02, -0.03, 0.01)), wind=wind)
        for _ in range(30):
            out = sim.step_frame()
        finals.append(out.state)
    assert np.array_equal(finals[0].xi_I, finals[1].xi_I)
    assert np.array_equal(finals[0].R_IB, finals[1].R_IB)


def test_touchdown_event_reports_vertical_speed(configs):
    # thrust 0.4 of a 2 m g maximum: a = g (1 - 0.8) downwards from rest
    sim = _sim(configs, FakeAutopilot(thrust=0.4), initial_position_I=(0.0, 0.0, -0.6))
    events = []
    for _ in range(100):
        events += sim.step_frame().events
    assert len(events) == 1 and events[0].type is EventType.TOUCHDOWN
    drop = 0.6 - configs[2].envelope_height / 2
    a = 0.2 * GRAVITY      # ignoring the thrust lag: the body starts at hover thrust
    assert events[0].speed_mps == pytest.approx(np.sqrt(2 * a * drop), rel=0.05)
    assert events[0].surface == 'floor'
    assert not sim.ended
    d = events[0].to_dict()
    assert d['type'] == 'touchdown' and len(d['position_map']) == 3
    assert d['position_map'][2] == pytest.approx(configs[2].envelope_height / 2, abs=1e-6)


def test_wall_collision_ends_the_run(configs):
    wind = WindConfig(steady_force_I=(3.0, 0.0, 0.0))
    sim = _sim(configs, FakeAutopilot(), wind=wind, initial_position_I=(-1.2, 0.0, -0.6))
    events = []
    for _ in range(200):
        out = sim.step_frame()
        if out is None:
            break
        events += out.events
    assert sim.ended and sim.step_frame() is None and sim.tick() is None
    assert [e.type for e in events] == [EventType.COLLISION]
    e = events[0]
    assert e.surface == 'wall'
    assert e.position_I[0] == pytest.approx(configs[0].wall_x - configs[2].envelope_radius,
                                            abs=0.01)


def test_first_frame_hold_waits_for_subscribers_then_settles():
    hold = FirstFrameHold({'front': 3, 'down': 3}, settle_s=0.5, timeout_s=30.0, now=0.0)
    assert not hold.ready({'front': 2, 'down': 3}, now=1.0)
    assert not hold.ready({'front': 3, 'down': 3}, now=2.0)      # matched: settling
    assert not hold.ready({'front': 2, 'down': 3}, now=2.3)      # lost one: settle restarts
    assert not hold.ready({'front': 3, 'down': 3}, now=2.4)
    assert hold.ready({'front': 3, 'down': 3}, now=2.9) and not hold.timed_out
    assert hold.ready({'front': 0, 'down': 0}, now=3.0)          # released for good


def test_first_frame_hold_counts_each_topic_against_its_own_minimum():
    hold = FirstFrameHold({'front': 2, 'down': 2, 'imu/data': 4}, settle_s=0.0, timeout_s=30.0,
                          now=0.0)
    assert not hold.ready({'front': 2, 'down': 2, 'imu/data': 3}, now=1.0)
    assert not hold.ready({'front': 2, 'down': 2}, now=1.0)      # a topic not counted: 0
    assert hold.ready({'front': 2, 'down': 2, 'imu/data': 5}, now=1.0)


def test_first_frame_hold_times_out_and_zero_never_holds():
    hold = FirstFrameHold({'front': 3, 'down': 3}, settle_s=0.5, timeout_s=30.0, now=0.0)
    assert not hold.ready({'front': 1, 'down': 1}, now=29.9)
    assert hold.ready({'front': 1, 'down': 1}, now=30.1) and hold.timed_out
    assert FirstFrameHold({'front': 0, 'down': 0}, 0.5, 30.0, now=0.0).ready(
        {'front': 0, 'down': 0}, now=0.0)
    with pytest.raises(ValueError):
        FirstFrameHold({'front': -1}, 0.5, 30.0, now=0.0)


def test_first_frame_hold_can_also_wait_for_the_setpoint_stream():
    hold = FirstFrameHold({}, settle_s=0.5, timeout_s=30.0, now=0.0, need_setpoints=True)
    counts = {'front': 0, 'down': 0}
    assert not hold.ready(counts, now=0.0)                       # no subscribers needed, but
    assert not hold.ready(counts, now=5.0, setpoints=False)      # no companion stream yet
    assert not hold.ready(counts, now=6.0, setpoints=True)       # streaming: settling
    assert hold.ready(counts, now=6.5, setpoints=True) and not hold.timed_out
    late = FirstFrameHold({'front': 2}, 0.5, 30.0, now=0.0, need_setpoints=True)
    assert not late.ready({'front': 2}, now=29.0)
    assert late.ready({'front': 2}, now=30.5) and late.timed_out


def test_before_frame_0_the_link_is_served_without_telemetry_then_t0_telemetry_leaves(configs):
    ap, clock = FakeAutopilot(), FakeClock()
    sim = _sim(configs, ap, clock, pacing=Pacing.LOCKSTEP)
    assert sim.poll_before_start() is False        # no setpoint stream yet
    ap.last_setpoint_time_boot_ms = 0
    assert sim.poll_before_start() is True
    assert ap.receiving_polls == 2 and ap.telemetry_times == []
    assert sim.tick().t_ns == 0
    assert ap.telemetry_times == [0.0]             # the IMU at t = 0 goes with frame 0


def test_lockstep_harness_holds_a_frame_until_imu_data_reached_its_time():
    from ibvs_sim.core.graph_sync import ImuBeforeImages
    from ibvs_sim.core.sim_core import FrameOutput
    frame = FrameOutput(40_000_000, {}, None, [])
    hold = ImuBeforeImages(timeout_s=1.0)
    assert hold.hold(frame, now=0.0) is frame           # no IMU seen yet: nothing to wait for
    hold.note_imu(30_000_000)
    assert hold.hold(frame, now=0.0) is None and hold.holding
    assert hold.release(now=0.5) is None                 # 30 ms < 40 ms, within the wait
    hold.note_imu(40_000_000)
    assert hold.release(now=0.6) is frame and not hold.timed_out and not hold.holding
    later = FrameOutput(60_000_000, {}, None, [])
    assert hold.hold(later, now=1.0) is None
    assert hold.release(now=2.0) is later and hold.timed_out and hold.timeouts == 1
    free = ImuBeforeImages(timeout_s=1.0, enabled=False)  # realtime pacing: pass-through
    free.note_imu(0)
    assert free.hold(later, now=0.0) is later


def test_answer_latency_pairs_each_setpoint_with_the_frame_of_its_time():
    lat = AnswerLatency()
    for k in range(5):                                   # frames at 0, 20, ..., 80 ms
        lat.published(k * 20_000_000, wall=10.0 + 0.08 * k)
    lat.answered(0, 10.005)                              # 5 ms
    lat.answered(0, 10.050)                              # a repeat: not a new answer
    lat.answered(20, 10.080 + 0.012)                     # 12 ms
    lat.answered(60, 10.240 + 0.007)                     # 7 ms; 40 ms never answered
    lat.answered(1234, 11.0)                             # no such frame: ignored
    st = lat.stats()
    assert st['frames_published'] == 5 and st['frames_answered'] == 3
    assert st['answered_fraction'] == pytest.approx(0.6)
    assert st['latency_median_ms'] == pytest.approx(7.0)
    assert st['latency_max_ms'] == pytest.approx(12.0)


def test_answer_latency_takes_the_nearest_frame_within_the_clock_sync_error():
    """A running TIMESYNC maps an image stamp to time_boot_ms within a few ms, not exactly."""
    lat = AnswerLatency(tolerance_ms=9)
    for k in range(3):                                   # frames at 0, 20, 40 ms
        lat.published(k * 20_000_000, wall=1.0 + 0.02 * k)
    lat.answered(1, 1.005)                               # frame 0, mapped 1 ms late: 5 ms
    lat.answered(38, 1.050)                              # frame 40, 2 ms early: 10 ms
    lat.answered(30, 1.070)                              # 10 ms from both: no frame
    st = lat.stats()
    assert st['frames_answered'] == 2
    assert st['latency_median_ms'] == pytest.approx(7.5)
    assert st['answer_stamp_error_max_ms'] == 2 and st['answer_stamp_exact_fraction'] == 0.0


def test_answer_latency_counts_the_grid_frames_answered_apart():
    """At a frame stride of 2 the graph answers every other frame by design: of the frames
    published on its grid, the fraction answered is its own; of all, it is half at best."""
    lat = AnswerLatency()
    for k in range(8):                                   # frames at 0 ... 140 ms, stride 2
        lat.published(k * 20_000_000, wall=1.0 + 0.02 * k, on_grid=k % 2 == 0)
    for k in (0, 2, 4):                                  # grid frames 0, 40, 80 ms; not 120
        lat.answered(k * 20, 1.005 + 0.02 * k)
    lat.answered(140, 1.30)                              # an off-grid frame answered
    st = lat.stats()
    assert st['frames_published'] == 8 and st['frames_on_grid'] == 4
    assert st['frames_answered'] == 4 and st['answered_fraction'] == pytest.approx(0.5)
    assert st['answered_grid_fraction'] == pytest.approx(3 / 4)


def test_lockstep_also_waits_for_every_product_of_the_frame_then_gives_up_a_dead_one(configs):
    """The clock stands still until the graph made all it makes of a frame, not only the answer.

    A product without a publisher, or of a camera whose image did not go out, is not waited
    for; one that does not come within the lockstep timeout is given up until it comes again.
    """
    ap, clock = FakeAutopilot(), FakeClock()
    products = GraphProducts({'window/corners': 'front', 'pad/landmarks': 'down',
                              'pad/groups': 'down'})
    sim = _sim(configs, ap, clock, products=products, pacing=Pacing.LOCKSTEP,
               lockstep_timeout_s=1.0)
    live = {'window/corners': 1, 'pad/landmarks': 1, 'pad/groups': 1}
    assert sim.tick().t_ns == 0
    products.expect(0, ['front', 'down'], live)
    ap.last_setpoint_time_boot_ms = 0                    # answered, but the pad still computes
    products.note('window/corners', 0)
    assert sim.tick() is None
    products.note('pad/groups', -20_000_000)             # an older frame's: not this one's
    products.note('pad/landmarks', 0)
    assert products.missing() == ['pad/groups'] and sim.tick() is None
    products.note('pad/groups', 0)
    out = sim.tick()
    assert out.t_ns == 20_000_000 and sim.lockstep.timeouts == 0
    # the pad detector dies: the next frame waits one timeout, then never again for it
    products.expect(out.t_ns, ['front', 'down'], live)
    ap.last_setpoint_time_boot_ms = 20
    products.note('window/corners', out.t_ns)
    assert sim.tick() is None
    clock.now += 1.0
    out = sim.tick()
    assert out.t_ns == 40_000_000 and sim.lockstep.given_up == ['pad/groups', 'pad/landmarks']
    assert sim.lockstep.timeouts == 0                    # the answer itself was there
    products.expect(out.t_ns, ['front', 'down'], live)
    ap.last_setpoint_time_boot_ms = 40
    products.note('window/corners', out.t_ns)
    assert sim.tick().t_ns == 60_000_000
    # it restarts and publishes again: waited for again (note says it was given up, once);
    # no publisher or camera off: not
    assert products.note('pad/landmarks', 60_000_000) is True
    assert products.note('pad/landmarks', 60_000_000) is False
    products.expect(60_000_000, ['front', 'down'], live)
    assert products.missing() == ['window/corners']
    products.expect(60_000_000, ['front'], live)
    assert products.missing() == ['window/corners']
    products.expect(60_000_000, ['front', 'down'], {**live, 'window/corners': 0})
    assert products.missing() == []


def test_a_free_running_collision_is_kept_as_an_event(configs):
    """Free-running, a collision between two frames ends the run and is still reported."""
    clock = FakeClock()
    wind = WindConfig(steady_force_I=(3.0, 0.0, 0.0))
    sim = _sim(configs, FakeAutopilot(), clock, pacing=Pacing.REALTIME, wind=wind,
               initial_position_I=(-1.2, 0.0, -0.6))
    for _ in range(2000):
        sim.tick()
        clock.now += 0.005
        if sim.ended:
            break
    assert sim.ended and [e.type for e in sim.events] == [EventType.COLLISION]


def test_lockstep_waits_for_the_frame_status_and_only_the_products_its_mode_uses():
    """Mode gating: a perception node computes its product only in the modes that use it.

    The harness waits for the supervisor's status of the frame, then for the products of the
    frame's mode; before any status, for all (the nodes compute all). A status that does not
    come (a dead supervisor) is given up with what its mode would have needed.
    """
    used_in = {'window/corners': {Mode.IDLE, Mode.WINDOW},
               'down_camera/translational_flow': {Mode.CROSSING, Mode.LANDING}}
    products = GraphProducts({'window/corners': 'front',
                              'down_camera/translational_flow': 'down'}, used_in=used_in)
    live = {'window/corners': 1, 'down_camera/translational_flow': 1, STATUS_TOPIC: 1}
    both = ['front', 'down']
    products.expect(0, both, live)
    assert products.missing() == [STATUS_TOPIC]
    products.note_status(0, Mode.WINDOW)
    assert products.missing() == ['window/corners']           # the floor flow is not made
    products.note('window/corners', 0)
    assert products.missing() == []
    # the switch to CROSSING at 20 ms: the floor flow of that frame is made, not the window
    products.expect(20_000_000, both, live)
    products.note_status(20_000_000, Mode.CROSSING)
    assert products.missing() == ['down_camera/translational_flow']
    products.note('down_camera/translational_flow', 20_000_000)
    assert products.missing() == []
    # cameras that are not synchronised: the switch frame's answer comes with the down
    # camera's next frame (no image of its stamp in the delivery); synchronised: owed
    assert products.handed_over(20_000_000, {'front': 20_000_000, 'down': 17_000_000})
    assert not products.handed_over(20_000_000, {'front': 20_000_000, 'down': 20_000_000})
    assert not products.handed_over(0, {'front': 0, 'down': 3_000_000})   # WINDOW: front
    assert not products.handed_over(40_000_000, {'front': 40_000_000})    # no status yet
    # no status at all (no supervisor publishing): every product, as the nodes make them all
    fresh = GraphProducts({'window/corners': 'front'}, used_in=used_in)
    fresh.expect(0, both, {'window/corners': 1, STATUS_TOPIC: 0})
    assert fresh.missing() == ['window/corners']
    # the supervisor dies: the status and the products its last mode uses are given up
    products.expect(40_000_000, both, live)
    assert products.give_up() == [STATUS_TOPIC, 'down_camera/translational_flow']
    products.expect(60_000_000, both, live)
    assert products.missing() == []
    products.note_status(60_000_000, Mode.CROSSING)       # it comes back: waited for again
    products.expect(80_000_000, both, live)
    assert products.missing() == [STATUS_TOPIC]


def test_lockstep_owes_no_wait_to_a_frame_off_the_graphs_grid(configs):
    """The rate governor computes every 2nd frame (ibvs/frame_grid): a frame off the grid gets
    no answer, status or product, so the clock moves on at once (it waited the whole time-out
    per frame: a 0.2 s camera dropout cost a CI test 49 of them); on the grid it waits."""
    ap, clock = FakeAutopilot(), FakeClock()
    products = GraphProducts({'window/corners': 'front'})
    sim = _sim(configs, ap, clock, products=products, pacing=Pacing.LOCKSTEP,
               lockstep_timeout_s=1.0)
    live = {'window/corners': 1}
    assert sim.tick().t_ns == 0
    products.note_grid('front', 20_000_000, 2, 0)       # every 2nd frame from t = 0
    products.expect(0, ['front'], live)
    ap.last_setpoint_time_boot_ms = 0
    products.note('window/corners', 0)
    out = sim.tick()
    assert out.t_ns == 20_000_000                       # frame 1: off the grid
    products.expect(out.t_ns, ['front'], live)
    assert products.missing() == [] and products.off_grid(20_000_000)
    out = sim.tick()
    assert out.t_ns == 40_000_000 and sim.lockstep.timeouts == 0
    products.expect(out.t_ns, ['front'], live)          # frame 2: on the grid, waited for
    assert products.missing() == ['window/corners'] and sim.tick() is None
    products.note('window/corners', 40_000_000)
    assert sim.tick() is None                           # the answer too
    ap.last_setpoint_time_boot_ms = 40
    assert sim.tick().t_ns == 60_000_000


def test_lockstep_owes_no_flow_to_a_frame_off_the_flow_grid():
    """The governor sheds the flows (ibvs/frame_grid's flow grid: every 2nd frame): a frame
    between two flow frames is owed its window, not its flow; a flow frame is owed both."""
    flow = 'front_camera/translational_flow'
    products = GraphProducts({'window/corners': 'front', flow: 'front'}, flow_topics={flow})
    live = {'window/corners': 1, flow: 1}
    products.note_grid('front', 20_000_000, 1, 0)
    products.note_grid('front', 20_000_000, 2, 20_000_000, flow=True)
    products.expect(20_000_000, ['front'], live)
    assert sorted(products.expected) == sorted(['window/corners', flow])
    products.expect(40_000_000, ['front'], live)
    assert products.expected == {'window/corners'}
    # without a flow grid the frame grid rules the flows too
    fresh = GraphProducts({'window/corners': 'front', flow: 'front'}, flow_topics={flow})
    fresh.note_grid('front', 20_000_000, 2, 0)
    fresh.expect(20_000_000, ['front'], live)
    assert fresh.expected == set()
