"""The TIMESYNC clock-offset estimator (ibvs_control.mavlink.time_sync) on synthetic round trips.

A synthetic link: the autopilot's boot clock is the ROS clock minus a known offset; a request
sent at ROS time t reaches the autopilot after ``up`` ns (it answers with its boot time then)
and the answer comes back ``down`` ns later. Expected offsets are written out from that model
(a symmetric link measures the offset exactly, an asymmetric one is off by half the
difference of the two legs; a drifting boot clock is a straight line; a least-squares line fit
by numpy is the reference of the first tracking steps), never recomputed with the estimator's
formula.
"""
import numpy as np
import pytest

from ibvs_control.mavlink.time_sync import TimeSync, TimeSyncConfig

MS = 1_000_000                                  # ns
OFFSET = 1_700_000_000_123_456_789              # ns: ROS (system time) - boot, a real-looking one


class Link:
    """Drives a TimeSync with round trips of a simulated link (ROS clock ns, steady s)."""

    def __init__(self, ts: TimeSync, offset: int, ros_ns: int = 5_000 * MS + OFFSET) -> None:
        self.ts = ts
        self.offset = offset          # the true ROS - boot (at ros_ns, with drift)
        self.drift = 0.0              # ns of offset per ns of ROS time (boot clock slow: > 0)
        self.ros = ros_ns             # ROS time now
        self.t_start = ros_ns
        self.steady = 100.0

    def true_offset(self, t: int) -> int:
        """ROS - boot (ns) at ROS time t (integers: 1.7e18 ns does not fit a float exactly)."""
        return self.offset + int(round(self.drift * (t - self.t_start)))

    def trip(self, up: int = 0, down: int = 0, offset: int | None = None,
             ts1_override: int | None = None) -> list:
        """One request/answer; the clocks then move on 0.1 s (ROS) / 0.05 s (steady)."""
        self.ros += 100 * MS
        self.steady += 0.05
        ts1 = self.ts.next_request(self.ros, self.steady)
        assert ts1 == self.ros, 'a request was due'
        arrival = self.ros + up
        true_offset = self.true_offset(arrival) if offset is None else offset
        tc1 = arrival - true_offset                # the autopilot's boot time when it answers
        return self.ts.on_reply(tc1, ts1 if ts1_override is None else ts1_override,
                                self.ros + up + down)


def synced(offset=OFFSET, **config) -> tuple[TimeSync, Link]:
    ts = TimeSync(TimeSyncConfig(**config))
    link = Link(ts, offset)
    for _ in range(ts.config.init_samples):
        link.trip()
    assert ts.synced
    return ts, link


def test_unknown_until_five_samples_then_their_median():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    # legs (up, down) in us -> sample error (down - up) / 2: +1, -0.5, 0, +2, -1.5 (ms)
    legs = [(1000, 3000), (2000, 1000), (500, 500), (0, 4000), (3000, 0)]
    for i, (up, down) in enumerate(legs):
        assert not ts.synced and ts.offset_ns is None
        assert ts.boot_ms_to_ros_ns(1234) is None and ts.ros_ns_to_boot_ms(OFFSET) is None
        events = link.trip(up * 1000, down * 1000)
        assert ts.accepted == i + 1
    assert ts.synced
    assert ts.offset_ns == OFFSET                 # the median sample: the symmetric one
    assert any('synced' in text for _, text in events)


def test_symmetric_link_gives_the_exact_offset_and_the_mappings():
    ts, _ = synced()
    assert ts.offset_ns == OFFSET
    assert ts.boot_ms_to_ros_ns(1234) == 1_700_000_001_357_456_789   # 1.234 s after boot
    # ROS -> boot ms, nearest ms, halves up
    assert ts.ros_ns_to_boot_ms(OFFSET + 1_234_499_999) == 1234
    assert ts.ros_ns_to_boot_ms(OFFSET + 1_234_500_000) == 1235
    assert ts.ros_ns_to_boot_ms(OFFSET + 1_233_500_000) == 1234


def test_asymmetric_link_is_off_by_half_the_difference_of_the_legs():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    for _ in range(5):
        link.trip(up=1 * MS, down=3 * MS)          # back leg 2 ms longer
    assert ts.offset_ns == OFFSET + 1 * MS         # ROS of the answer's middle taken 1 ms late
    assert ts.last_rtt_ns == 4 * MS


def test_rtt_gate_rejects_long_round_trips_and_counts_them():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    link.trip(up=5 * MS, down=5 * MS + 1)          # 10 ms + 1 ns: rejected
    assert ts.rejected_rtt == 1 and ts.accepted == 0
    link.trip(up=5 * MS, down=5 * MS)              # exactly 10 ms: accepted
    assert ts.accepted == 1
    # our clock went back during the round trip (rtt < 0): rejected
    ts1 = ts.next_request(link.ros + 100 * MS, link.steady + 1.0)
    ts.on_reply(ts1 - OFFSET, ts1, ts1 - 1 * MS)
    assert ts.rejected_rtt == 2 and ts.last_rtt_ns == -1 * MS
    # max_rtt_s is a parameter
    ts2 = TimeSync(TimeSyncConfig(max_rtt_s=0.002))
    Link(ts2, OFFSET).trip(up=1 * MS, down=1 * MS + 1)
    assert ts2.rejected_rtt == 1


def test_answers_to_no_request_of_ours_are_ignored():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    link.trip(ts1_override=123)
    assert ts.unmatched == 1 and ts.accepted == 0
    ts.on_reply(5, 999, 1000)                      # never requested
    assert ts.unmatched == 2


def test_first_tracking_steps_are_the_least_squares_line_through_all_samples():
    ts, link = synced()                            # 5 samples of OFFSET, 0.1 s apart
    extra = [1_000_000, -400_000, 700_000, 0, 2_500_000, -1_200_000]     # ns, within the gate
    values = [0] * 5
    for e in extra:
        link.trip(offset=OFFSET + e)
        values.append(e)
        x = np.arange(len(values)) * 0.1           # s, equally spaced samples
        line = np.polyfit(x, np.array(values, dtype=float), 1)
        assert ts.offset_ns - OFFSET == pytest.approx(np.polyval(line, x[-1]), abs=1.0)
        assert ts.skew * 1e9 == pytest.approx(line[0], rel=1e-9, abs=1e-3)   # ns/s


def test_tracking_smooths_with_alpha_and_beta_once_the_line_has_enough_samples():
    ts, link = synced()
    for _ in range(200):
        link.trip()                                # exact samples: nothing moves
    assert ts.offset_ns == OFFSET and ts.skew == 0.0
    link.trip(offset=OFFSET + 1 * MS)              # 1 ms more: 5 % of the way (alpha)
    assert ts.offset_ns == OFFSET + 50_000
    # skew now beta * 1 ms / 0.1 s = 2e-5: predicted 50 us + 2 us, then 5 % of the rest
    assert ts.skew == pytest.approx(2e-5, rel=1e-12)
    link.trip(offset=OFFSET + 1 * MS)
    assert ts.offset_ns == OFFSET + 52_000 + 47_400
    ts2, link2 = synced(alpha=0.5, beta=0.1)
    for _ in range(200):
        link2.trip()
    link2.trip(offset=OFFSET + 2 * MS)
    assert ts2.offset_ns == OFFSET + 1 * MS


def test_a_drifting_boot_clock_is_tracked_with_its_skew():
    # PX4 SITL (SIH) measured: boot clock 0.77 % slow (7700 ppm), round trips 0.2-1 ms.
    rng = np.random.default_rng(3)
    ts = TimeSync()
    link = Link(ts, OFFSET)
    link.drift = 7700e-6
    errors = []
    for i in range(300):
        up, down = (int(x) for x in rng.uniform(0, 500_000, 2))    # asymmetry up to 0.25 ms
        link.trip(up, down)
        if ts.synced:
            errors.append(ts.offset_at(link.ros) - link.true_offset(link.ros))
    assert ts.resets == 0 and ts.rejected_outliers == 0
    # the start: the median of 5 samples 0.1 s apart is the middle one's, 0.2 s old (1.5 ms)
    assert max(abs(e) for e in errors) < 2 * MS
    assert max(abs(e) for e in errors[10:]) < 0.5 * MS
    assert max(abs(e) for e in errors[-100:]) < 0.3 * MS
    assert ts.skew * 1e6 == pytest.approx(7700, abs=30)            # ppm
    # boot -> ROS mapping on the drifting line: a sample 1 s after the last request
    boot_ms = (link.ros + 1_000 * MS - int(link.true_offset(link.ros + 1_000 * MS))) // MS
    ros_of_sample = link.ros + 1_000 * MS          # within a us: what the boot time was taken at
    truth = boot_ms * MS + link.true_offset(ros_of_sample)
    assert abs(ts.boot_ms_to_ros_ns(boot_ms) - truth) < 0.5 * MS
    # a plain exponential smoothing (no skew) lags 7.7 ms/s * 0.1 s / 0.05 = 15 ms: outliers


def test_outliers_are_not_used_and_five_in_a_row_re_initialise_from_them():
    ts, link = synced()
    accepted = ts.accepted
    for _ in range(4):
        link.trip(offset=OFFSET - 20 * MS)         # -20 ms with rtt 0: a lagging /clock
    assert ts.offset_ns == OFFSET and ts.rejected_outliers == 4 and ts.accepted == accepted
    link.trip()                                    # a good one ends the streak
    # a real time jump: our system clock is set back by 3 s (the boot clock runs on)
    jumped = OFFSET - 3_000 * MS
    link.ros -= 3_000 * MS
    link.offset = jumped
    for _ in range(4):
        link.trip()
    assert ts.synced and ts.offset_ns == OFFSET
    events = link.trip()                           # the 5th in a row: the new offset at once
    assert ts.synced and ts.resets == 1 and ts.offset_ns == jumped
    assert ts.reboots == 0 and ts.status().reboots == 0            # a jump is no reboot
    assert any('time jump' in text and 're-initialised' in text for _, text in events)
    for _ in range(20):
        link.trip()                                # tracked from there, no further reset
    assert ts.offset_ns == jumped and ts.resets == 1 and ts.skew == 0.0


def test_deviation_gate_is_a_parameter():
    ts, link = synced(max_deviation_s=0.002, max_consecutive_outliers=2)
    link.trip(offset=OFFSET + 1_900_000)           # within 2 ms: used
    assert ts.rejected_outliers == 0
    link.trip(offset=OFFSET + 5 * MS)
    assert ts.synced
    link.trip(offset=OFFSET + 5 * MS)              # 2 in a row: reset, 2 of 5 initial samples
    assert not ts.synced and ts.resets == 1
    for _ in range(3):
        link.trip(offset=OFFSET + 5 * MS)
    assert ts.synced and ts.offset_ns == OFFSET + 5 * MS


def test_reboot_resets_on_time_boot_ms_or_tc1_going_back():
    ts, link = synced()
    ts.on_boot_time('time_boot_ms', 100_000 * MS)
    assert ts.on_boot_time('time_boot_ms', 99_500 * MS) == []    # 0.5 s back: reordering
    assert ts.synced
    events = ts.on_boot_time('time_boot_ms', 2_000 * MS)         # 98 s back: reboot
    assert not ts.synced and ts.resets == 1 and ts.reboots == 1
    assert any('reboot' in text for _, text in events)
    # re-sync on the new boot clock (booted 150 s after the old one)
    link.offset = OFFSET + 150_000 * MS
    for _ in range(5):
        link.trip()
    assert ts.synced and ts.offset_ns == OFFSET + 150_000 * MS
    # tc1 going back by more than 1 s resets as well
    link.offset = OFFSET + 300_000 * MS
    link.trip()
    assert not ts.synced and ts.resets == 2 and ts.status().reboots == 2


def test_requests_never_at_ros_time_zero_and_paced_by_the_right_clock():
    ts = TimeSync()
    assert ts.next_request(0, 1.0) is None         # no /clock yet under use_sim_time
    assert ts.next_request(None, 1.0) is None
    # unsynced: every call, at most every 0.05 s of the steady clock (ROS time may stand)
    assert ts.next_request(20 * MS, 1.0) == 20 * MS
    assert ts.next_request(20 * MS, 1.03) is None
    assert ts.next_request(20 * MS, 1.05) == 20 * MS
    ts2 = TimeSync()
    steady = 0.0
    while not ts2.synced:                          # lockstep: ROS = boot = 20 ms, frozen
        steady += 0.05
        ts1 = ts2.next_request(20 * MS, steady)
        ts2.on_reply(20 * MS, ts1, 20 * MS)
    assert ts2.offset_ns == 0
    # synced: every 0.1 s of ROS time, whatever the steady clock does
    assert ts2.next_request(20 * MS, steady + 10.0) is None
    assert ts2.next_request(100 * MS, steady + 10.0) is None
    assert ts2.next_request(120 * MS, steady) == 120 * MS
    assert ts2.next_request(200 * MS, steady + 10.0) is None
    assert ts2.next_request(220 * MS, steady) == 220 * MS


def lockstep_run() -> tuple[list, TimeSync]:
    """A lockstep sim: ROS time = sim time = boot time, 20 ms frames, answers in the frame.

    One request in seven is read by the autopilot a frame late while our /clock still shows
    the old frame (a sample of -20 ms with rtt 0), one in eleven comes back after our /clock
    moved on (rtt 20 ms). Returns the mapped stamps of every frame's IMU sample.
    """
    ts = TimeSync()
    stamps = []
    steady = 0.0
    for frame in range(1, 400):
        t = frame * 20 * MS
        steady += 0.02
        ts1 = ts.next_request(t, steady)
        if ts1 is not None:
            if frame % 7 == 3:
                ts.on_reply(t + 20 * MS, ts1, t)           # answered in the next frame
            elif frame % 11 == 5:
                ts.on_reply(t, ts1, t + 20 * MS)           # read after /clock moved on
            else:
                ts.on_reply(t, ts1, t)
        stamps.append(ts.boot_ms_to_ros_ns(frame * 20))
    return stamps, ts


def test_lockstep_pattern_keeps_the_offset_exactly_zero_and_stamps_repeat():
    stamps, ts = lockstep_run()
    assert ts.synced and ts.offset_ns == 0
    assert ts.rejected_outliers > 0 and ts.rejected_rtt > 0       # the pattern happened
    assert ts.resets == 0
    first = next(i for i, s in enumerate(stamps) if s is not None)
    assert all(s == (i + 1) * 20 * MS for i, s in enumerate(stamps) if i >= first)
    again, _ = lockstep_run()
    assert again == stamps                                         # bit for bit


def test_config_is_validated():
    for bad in ({'period_s': 0.0}, {'max_rtt_s': -1.0}, {'alpha': 0.0}, {'alpha': 1.5},
                {'init_samples': 0}, {'max_consecutive_outliers': 2.5},
                {'max_deviation_s': float('nan')}):
        with pytest.raises(ValueError):
            TimeSyncConfig(**bad)


class StarvedSitl:
    """A SITL boot clock on a starved machine, polled as the bridge polls (every 4 ms).

    The boot clock runs ``slow`` (a fraction) behind ROS time, is read on a ``grid_ns`` grid
    (SIH: 4 ms steps) and stands still for ``stall_ns`` at each ROS time of ``stalls`` (the
    simulated clock stalls, the offset grows by that much at once). Requests reach it after
    2 ms, answers come back 2 ms later (round trip 4 ms, as measured against SIH).
    """

    POLL_NS = 4 * MS
    LEG_NS = 2 * MS

    def __init__(self, ts: TimeSync, slow: float, stalls: tuple = (), stall_ns: int = 0,
                 grid_ns: int = 4 * MS) -> None:
        self.ts, self.slow, self.stalls = ts, slow, stalls
        self.stall_ns, self.grid = stall_ns, grid_ns
        self.t0 = OFFSET + 10_000 * MS

    def true_offset(self, t: int) -> int:
        """ROS - boot (ns) at ROS time t, off the grid."""
        stalled = sum(self.stall_ns for s in self.stalls if t >= s)
        return OFFSET + int(round(self.slow * (t - self.t0))) + stalled

    def boot_ns(self, t: int) -> int:
        return (t - self.true_offset(t)) // self.grid * self.grid

    def run(self, seconds: float) -> list:
        """Poll for ``seconds``; return (ROS ns, mapped - true offset ns) once synced."""
        errors, in_flight = [], []
        t = self.t0
        while t < self.t0 + int(seconds * 1e9):
            t += self.POLL_NS
            for answer in [a for a in in_flight if a[0] <= t]:
                in_flight.remove(answer)
                self.ts.on_reply(answer[1], answer[2], t)
            ts1 = self.ts.next_request(t, (t - self.t0) / 1e9)
            if ts1 is not None:
                tc1 = self.boot_ns(t + self.LEG_NS)
                in_flight.append((t + 2 * self.LEG_NS, tc1, ts1))
            if self.ts.synced:
                errors.append((t, self.ts.offset_at(t) - self.true_offset(t)))
        return errors


def test_a_starved_sitl_clock_resets_once_per_jump_and_keeps_its_skew():
    # PX4 SIH measured on this machine while starved (2026-11-27): boot clock 2.4-4 % slow on
    # a 4 ms grid, stalls of 12-30 ms. CI 21 failed with 8 resets in 6 s for 2 such jumps:
    # after a jump the skew went back to 0 and the next request left at once, so the sample
    # 5 ms later made a 2 ms grid residual a skew step of 8 %, and then outliers again.
    stalls = (OFFSET + 13_000 * MS, OFFSET + 16_000 * MS)
    ts = TimeSync()
    sitl = StarvedSitl(ts, slow=0.03, stalls=stalls, stall_ns=30 * MS)
    errors = sitl.run(8.0)
    assert ts.resets == len(stalls)
    assert ts.skew * 1e6 == pytest.approx(30_000, abs=1_500)      # ppm: the rate, kept
    # 0.6 s (5 outliers, 0.1 s apart, and a margin) after a stall the estimate is back within
    # the grid; before the first stall, once the skew is learnt (2 s), as well
    settled = [e for t, e in errors
               if t > sitl.t0 + 2_000 * MS
               and not any(s <= t < s + 600 * MS for s in stalls)]
    assert len(settled) > 1000
    assert max(abs(e) for e in settled) < 4 * MS


def test_after_a_time_jump_requests_go_on_at_their_period_and_the_skew_is_kept():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    link.drift = 0.02                                  # boot clock 2 % slow
    for _ in range(60):
        link.trip()
    skew = ts.skew
    assert skew == pytest.approx(0.02, rel=0.01)
    link.offset += 50 * MS                             # the boot clock stalls 50 ms
    for _ in range(5):
        link.trip()
    assert ts.resets == 1 and ts.synced
    assert ts.skew == skew                             # the rate did not change
    # the base: the streak's median brought to its latest sample's time with that skew
    assert abs(ts.offset_at(link.ros) - link.true_offset(link.ros)) < 0.1 * MS
    assert ts.next_request(link.ros + 50 * MS, link.steady + 1.0) is None     # not at once
    assert ts.next_request(link.ros + 100 * MS, link.steady + 1.0) == link.ros + 100 * MS


def test_a_clock_too_slow_for_the_gate_is_learnt_from_the_first_streak():
    # PX4 SIH after a 3 s freeze on a starved machine (2026-11-27): its clock ran 13 % slow
    # for 6 s, 13 ms per request period, beyond the 10 ms gate: the tracker, started with
    # skew 0, never got a sample to learn the rate from and reset every 0.5 s (15 resets).
    ts = TimeSync()
    sitl = StarvedSitl(ts, slow=0.13)
    errors = sitl.run(6.0)
    assert ts.resets == 1                              # the first streak, then tracked
    assert ts.skew * 1e6 == pytest.approx(130_000, abs=2_000)     # ppm
    settled = [e for t, e in errors if t > sitl.t0 + 1_500 * MS]
    assert len(settled) > 1000 and max(abs(e) for e in settled) < 4 * MS


def test_a_streak_off_the_learnt_rate_takes_its_own_robust_slope():
    ts = TimeSync()
    link = Link(ts, OFFSET)
    for _ in range(30):
        link.trip()                                    # learnt: skew 0
    # the boot clock slows to 20 % (20 ms per 0.1 s) and one of the 5 outliers is 30 ms off:
    # the slope is the median of the pairwise slopes, which that one cannot move far
    link.drift, link.t_start, link.offset = 0.2, link.ros, OFFSET
    for i in range(5):
        link.trip(offset=link.true_offset(link.ros + 100 * MS) + (30 * MS if i == 2 else 0))
    assert ts.resets == 1 and ts.synced
    assert ts.skew == pytest.approx(0.2, abs=0.03)
    for _ in range(10):
        link.trip()
    assert ts.resets == 1
    assert abs(ts.offset_at(link.ros) - link.true_offset(link.ros)) < 1 * MS
