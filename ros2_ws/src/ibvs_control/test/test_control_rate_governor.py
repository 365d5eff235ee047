"""The rate governor: a larger stride when frames are skipped, a smaller one tried later."""
import numpy as np
import pytest

from ibvs_control.core import rate_governor
from ibvs_control.core.rate_governor import (Level, ladder, RateGovernor, SupersededFrames,
                                             SupervisorGrids)

MS = 1_000_000


def GovernorConfig(**kw):   # noqa: N802  the stride rules alone (the flow step: its own tests)
    return rate_governor.GovernorConfig(**{'flow_shed_stride': 1, **kw})


# the try rules, judged from the try's decision (the lead has a test of its own)
NO_LEAD = {'stride_down_lead_s': 0.0}


def run(gov, t0, n, complete, period=0.02):
    """Feed n frames (complete: bool or callable of the index); return the changes (t, stride)."""
    out = []
    for k in range(n):
        t = t0 + k * period * gov.stride
        ok = complete(k) if callable(complete) else complete
        s = gov.observe(t, ok)
        if s is not None:
            out.append((round(t, 6), s.stride if s.flow_stride == 1 else s))
    return out


def test_complete_frames_keep_every_frame():
    gov = RateGovernor(GovernorConfig())
    assert run(gov, 0.0, 500, True) == [] and gov.stride == 1


def test_a_lone_skipped_frame_now_and_then_keeps_every_frame():
    # 1 in 5 skipped (2 among any 10, never 2 in a row): the rate held is 80 %, more than
    # half of it at a doubled stride
    gov = RateGovernor(GovernorConfig())
    assert run(gov, 0.0, 500, lambda k: k % 5 != 0) == [] and gov.stride == 1


def test_four_skipped_in_ten_double_the_stride_up_to_the_largest():
    gov = RateGovernor(GovernorConfig(max_frame_stride=4))
    changes = run(gov, 0.0, 40, lambda k: k % 3 != 0)    # 1 in 3: 4 among 10, none in a row
    assert [s for _, s in changes] == [2, 4] and gov.stride == 4
    assert [k for k in range(10) if k % 3 == 0] == [0, 3, 6, 9]
    assert changes[0][0] == pytest.approx(9 * 0.02)      # at the 4th skipped frame
    assert run(gov, 1.0, 40, False) == []            # never above max_frame_stride


def test_three_skipped_in_a_row_double_the_stride_at_once():
    gov = RateGovernor(GovernorConfig())
    run(gov, 0.0, 20, True)
    assert run(gov, 0.4, 2, False) == [] and gov.stride == 1
    assert run(gov, 0.44, 1, False) == [(0.44, 2)]


def test_a_smaller_stride_is_tried_after_the_hold_and_kept_if_it_holds():
    cfg = GovernorConfig(stride_down_hold_s=2.0)
    gov = RateGovernor(cfg)
    run(gov, 0.0, 3, False)                          # 3 skipped: stride 2 at t = 0.04
    assert gov.stride == 2
    changes = run(gov, 0.08, 100, True)              # 40 ms frames: 4 s of complete ones
    assert changes and changes[0][1] == 1
    assert changes[0][0] == pytest.approx(0.04 + 2.0, abs=0.05)
    assert len(changes) == 1 and gov.stride == 1     # and kept


def test_a_failed_try_doubles_the_wait_before_the_next():
    cfg = GovernorConfig(stride_down_hold_s=1.0, stride_down_hold_max_s=8.0, **NO_LEAD)
    gov = RateGovernor(cfg)
    run(gov, 0.0, 3, False)                          # stride 2
    t = 0.04
    waits = []
    for _ in range(4):
        # complete frames at stride 2 until the governor tries stride 1 ...
        k = 0
        while gov.stride == 2:
            t += 0.04
            gov.observe(t, True)
            k += 1
        waits.append(round(k * 0.04, 2))
        # ... where frames are skipped at once: back to 2
        for _ in range(3):
            t += 0.02
            gov.observe(t, False)
        assert gov.stride == 2
    assert waits[1] == pytest.approx(2 * waits[0], abs=0.05)
    assert waits[2] == pytest.approx(4 * waits[0], abs=0.05)
    assert waits[3] == pytest.approx(8.0, abs=0.05)   # capped


@pytest.mark.parametrize('try_skipped', [1, 3])
def test_a_try_of_a_smaller_stride_ends_at_its_first_skipped_frame(try_skipped):
    # at the larger stride a lone skipped frame changes nothing; in a try it ends the try,
    # before the overload rules (3 in a row, 4 in 10) would
    cfg = GovernorConfig(stride_down_hold_s=1.0, stride_try_skipped=try_skipped, **NO_LEAD)
    gov = RateGovernor(cfg)
    run(gov, 0.0, 3, False)                          # stride 2 at 0.04
    assert run(gov, 0.08, 10, lambda k: k != 4) == [] and gov.stride == 2
    changes = run(gov, 0.48, 40, True)               # the try of stride 1 after 1 s
    assert [s for _, s in changes] == [1]
    t = changes[0][0]
    out = run(gov, t + 0.02, try_skipped, False)
    assert out == [(round(t + 0.02 * try_skipped, 6), 2)] and gov.stride == 2
    # the try failed: the next one waits twice the hold
    again = run(gov, t + 0.1, 60, True)
    assert again[0][0] - (t + 0.02 * try_skipped) == pytest.approx(2.0, abs=0.05)


def test_a_try_is_judged_from_its_lead_on_not_on_the_old_strides_frames_before_it():
    # the try's decision reaches the nodes stride_down_lead_s later: a frame of the old stride
    # skipped before then (a slow computer: now and then one) says nothing of the try. It
    # ended such tries at once, and the next waited twice as long
    gov = RateGovernor(GovernorConfig(stride_down_hold_s=1.0, stride_down_lead_s=0.1))
    run(gov, 0.0, 3, False)                          # stride 2 at 0.04
    changes = run(gov, 0.08, 40, True)
    assert [s for _, s in changes] == [1]
    t = changes[0][0]
    assert gov.observe(t + 0.08, False) is None and gov.stride == 1     # before the lead
    assert gov.observe(t + 0.12, True) is None and gov.stride == 1      # the try's first
    assert gov.observe(t + 0.14, False) == Level(2) and gov.reason == 'frames were skipped'


def test_bad_governor_thresholds_are_refused():
    with pytest.raises(ValueError):
        GovernorConfig(stride_window_frames=3, stride_up_skipped=4)
    with pytest.raises(ValueError):
        GovernorConfig(stride_window_frames=3, stride_up_skipped=2, stride_up_in_a_row=4)
    with pytest.raises(ValueError):
        GovernorConfig(stride_down_hold_s=5.0, stride_down_hold_max_s=1.0)


def test_supervisor_grids_expect_a_larger_stride_at_once_and_a_smaller_one_after_the_lead():
    grids = SupervisorGrids({'front': 20 * MS})
    assert all(grids.on_grid('front', k * 20 * MS) for k in range(10))
    grids.set_stride('front', 2, 100 * MS, lead_ns=100 * MS)
    assert not grids.on_grid('front', 120 * MS) and grids.on_grid('front', 140 * MS)
    grids.set_stride('front', 1, 200 * MS, lead_ns=100 * MS)
    # frames before 300 ms still on the stride-2 grid (the nodes may not compute the others)
    assert grids.on_grid('front', 220 * MS) and not grids.on_grid('front', 240 * MS)
    assert grids.on_grid('front', 300 * MS) and grids.on_grid('front', 320 * MS)
    assert grids.stride('front') == 1
    grids.set_stride('front', 4, 400 * MS, lead_ns=100 * MS)
    grids.reset()
    assert grids.stride('front') == 1 and grids.on_grid('front', 420 * MS)


def _at_stride_2_until_a_try(gov, lag_s, period=0.02):
    """Skip 3 frames (stride 2), then complete ones of lag ``lag_s`` until the try of 1."""
    run(gov, 0.0, 3, False)
    t = 0.04
    while gov.stride == 2:
        t += 2 * period
        gov.observe(t, True, lag_s, period)
    return t


def test_a_try_ends_at_its_first_frame_that_falls_half_a_period_behind():
    # a slow computer at stride 2 holds each frame 45 ms after its stamp; at stride 1 every
    # frame costs more than its 20 ms, so each completes 8 ms later than the one before: the
    # try ends when one is 10 ms (half the try's period) behind, before any frame is skipped
    gov = RateGovernor(GovernorConfig(stride_down_hold_s=1.0, **NO_LEAD))
    t = _at_stride_2_until_a_try(gov, 0.045)
    assert gov.stride == 1
    lags = [0.045 + 0.008 * k for k in range(1, 6)]
    out = [gov.observe(t + 0.02 * k, True, lag, 0.02) for k, lag in enumerate(lags, 1)]
    assert out == [None, None, Level(2), None, None]     # 0.069 - 0.053 (the first) >= 0.010
    assert gov.stride == 2 and gov.reason == 'the try fell behind'
    # a failed try: the next waits twice as long
    t2 = t + 0.04
    while gov.stride == 2:
        t2 += 0.04
        gov.observe(t2, True, 0.045, 0.02)
    assert t2 - (t + 0.04) == pytest.approx(2.0, abs=0.05)


def test_a_try_that_keeps_the_lag_of_the_frames_before_it_holds():
    gov = RateGovernor(GovernorConfig(stride_down_hold_s=1.0, **NO_LEAD))
    t = _at_stride_2_until_a_try(gov, 0.045)
    lags = 0.045 + 0.009 * np.sin(np.arange(200))         # noise below half a period (10 ms)
    out = [gov.observe(t + 0.02 * k, True, lag, 0.02) for k, lag in enumerate(lags, 1)]
    assert all(s is None for s in out) and gov.stride == 1


def _at_stride_4_until_a_try_of_2(gov):
    """Skip frames up to stride 4, then complete ones until the try of 2: its stamp."""
    run(gov, 0.0, 3, False)
    run(gov, 0.08, 3, False)
    assert gov.stride == 4
    t = 0.4
    while gov.stride == 4:
        t += 0.08
        gov.observe(t, True)
    assert gov.stride == 2
    return t


def test_a_sporadic_skip_after_the_probation_keeps_the_try():
    # stride 2 held with a skip now and then (a third of a core); the try of 4 -> 2 passes
    # its 0.5 s probation, and the overload rules (3 in a row, 4 in 10) ignore a lone skip
    cfg = GovernorConfig(stride_down_hold_s=1.0, stride_try_s=0.5, **NO_LEAD)
    gov = RateGovernor(cfg)
    t = _at_stride_4_until_a_try_of_2(gov)
    out = [gov.observe(t + 0.04 * k, k != 15) for k in range(1, 24)]   # a skip at 0.6 s
    assert all(s is None for s in out) and gov.stride == 2
    # within the probation the same skip ends the try
    gov = RateGovernor(cfg)
    t = _at_stride_4_until_a_try_of_2(gov)
    assert [gov.observe(t + 0.04 * k, k != 5) for k in range(1, 6)] == [None] * 4 + [Level(4)]


def test_a_try_whose_frames_keep_a_constant_extra_lag_holds():
    # from stride 4 to 2 on a third of a core: each frame of the busier stride completes ~20 ms
    # later than at stride 4, but no later frame after frame: no backlog, the try holds
    gov = RateGovernor(GovernorConfig(stride_down_hold_s=1.0, max_frame_stride=4, **NO_LEAD))
    run(gov, 0.0, 3, False)
    run(gov, 0.08, 3, False)                             # stride 4
    assert gov.stride == 4
    t = 0.4
    while gov.stride == 4:
        t += 0.08
        gov.observe(t, True, 0.045, 0.02)
    assert gov.stride == 2
    lags = 0.070 + 0.004 * np.sin(np.arange(24))         # +25 ms, steady, until the hold
    out = [gov.observe(t + 0.04 * k, True, lag, 0.02) for k, lag in enumerate(lags, 1)]
    assert all(s is None for s in out) and gov.stride == 2


def test_a_handover_waits_for_the_new_cameras_first_complete_frame_within_the_grace():
    cfg = GovernorConfig(stride_handover_grace_s=0.2)
    gov = RateGovernor(cfg)
    run(gov, 0.0, 20, True)
    gov.handover(0.5)
    assert run(gov, 0.5, 5, False) == [] and gov.stride == 1   # 0.5-0.58: starting
    assert gov.observe(0.6, True) is None                      # its first complete frame
    assert run(gov, 0.62, 3, False) == [(0.66, 2)]              # now they count
    # without a complete frame the grace ends after stride_handover_grace_s
    gov = RateGovernor(cfg)
    run(gov, 0.0, 20, True)
    gov.handover(0.5)
    assert run(gov, 0.5, 13, False) == [(0.74, 2)]   # 0.70, 0.72, 0.74: 3 in a row past it


def test_a_frame_of_another_camera_is_a_handover():
    """The supervisor passes each frame's camera: the first camera is no handover, a change
    of camera is one at the new camera's first stamp, the same camera again is none."""
    cfg = GovernorConfig(stride_handover_grace_s=0.2)
    gov = RateGovernor(cfg)
    for k in range(20):
        gov.observe(0.02 * k, True, camera='front')
    out = [gov.observe(0.5 + 0.02 * k, False, camera='down') for k in range(5)]
    assert out == [None] * 5 and gov.stride == 1            # the grace: not counted
    assert gov.observe(0.6, True, camera='down') is None
    out = [gov.observe(0.62 + 0.02 * k, False, camera='down') for k in range(3)]
    assert out == [None, None, Level(2)]                            # the same camera: they count
    # the first camera seen is no handover: its skips count at once
    gov = RateGovernor(cfg)
    out = [gov.observe(0.02 * k, False, camera='front') for k in range(3)]
    assert out == [None, None, Level(2)]


def test_the_lag_rule_can_be_switched_off_and_needs_the_lag():
    for cfg, lag in ((GovernorConfig(stride_down_hold_s=1.0, stride_try_lag_periods=0.0,
                                     **NO_LEAD), 0.5),
                     (GovernorConfig(stride_down_hold_s=1.0, **NO_LEAD), None)):
        gov = RateGovernor(cfg)
        t = _at_stride_2_until_a_try(gov, None if lag is None else 0.045)
        assert gov.observe(t + 0.02, True, lag, 0.02) is None and gov.stride == 1


def test_superseded_frames_match_a_gap_within_the_tolerance_per_camera():
    """Reports match the gap's frames within the tolerance, per camera; a clock step clears."""
    seen = SupersededFrames(keep=4)
    base, step, tol = 1_000_000_000, 20_000_000, 10_000_000
    seen.note('front', base + step + 3_000_000)       # frame 1, jittered 3 ms
    seen.note('front', base + 3 * step)               # frame 3
    seen.note('down', base + 2 * step)                # the other camera's frame 2
    assert seen.reported('front', base + step, tol)
    assert not seen.reported('front', base + 2 * step, tol)
    assert seen.count_in_gap('front', base, step, 3, tol) == 2
    assert seen.count_in_gap('front', base, step, 2, tol) == 1     # frame 3 is past the gap
    assert seen.count_in_gap('down', base, step, 3, tol) == 1
    assert seen.count_in_gap('front', base, step, 3, 2_000_000) == 1   # 3 ms off: not frame 1
    for k in range(4):                                # only the newest `keep` are kept
        seen.note('front', base + (10 + k) * step)
    assert seen.count_in_gap('front', base, step, 3, tol) == 0
    seen.clear()
    assert not seen.reported('front', base + 10 * step, tol)


# --- the flow step: flows at half rate before the control rate is halved --------------------

def test_the_ladder_sheds_the_flows_before_it_doubles_the_stride():
    cfg = rate_governor.GovernorConfig
    assert ladder(cfg()) == (Level(1), Level(1, 2), Level(2), Level(4))
    assert ladder(cfg(flow_shed_stride=1)) == (Level(1), Level(2), Level(4))
    assert ladder(cfg(max_frame_stride=1)) == (Level(1), Level(1, 2))
    assert ladder(cfg(max_frame_stride=8, flow_shed_stride=3))[:3] == (
        Level(1), Level(1, 3), Level(2))


def test_an_overload_sheds_the_flows_first_and_a_lasting_one_then_doubles_the_stride():
    gov = RateGovernor(rate_governor.GovernorConfig(stride_down_hold_s=1.0, **NO_LEAD))
    changes = run(gov, 0.0, 3, False)                      # 3 in a row: the flows first
    assert changes == [(0.04, Level(1, 2))] and (gov.stride, gov.flow_stride) == (1, 2)
    assert run(gov, 0.06, 3, False) == [(0.1, 2)]          # still behind: every 2nd frame
    # it holds: after the hold, the flows shed again (not every frame at once), then all
    t = 0.1
    while gov.stride == 2:
        t += 0.04
        gov.observe(t, True)
    assert (gov.stride, gov.flow_stride) == (1, 2) and gov.reason == 'none skipped: a try'
    while gov.flow_stride == 2:
        t += 0.02
        gov.observe(t, True)
    assert (gov.stride, gov.flow_stride) == (1, 1) and t - 0.1 > 2.0


def _follow(grids, follower, camera='front'):
    """The flow node's view of the flow grid, as it reads it on ibvs/frame_grid."""
    g = grids.flow_grid(camera)
    follower.update(g.stride, g.ref_ns)


def test_every_frame_s_flow_source_is_a_frame_the_flow_node_computes():
    # walk the whole ladder up and down; after each decision (and its lead) every frame the
    # supervisor expects takes its flow from a frame on the flow node's grid, at most one
    # frame of the grid older, and its own when the flows are not shed
    from ibvs_common.core.frame_grid import GridFollower
    P, lead = 20 * MS, 100 * MS
    grids = SupervisorGrids({'front': P})
    follower = GridFollower(P)
    t = 1000 * MS
    for level in (Level(1, 2), Level(2), Level(4), Level(2), Level(1, 2), Level(1),
                  Level(1, 2), Level(2), Level(1, 2), Level(1)):
        t += 17 * P                                         # a decision on some frame
        while not grids.on_grid('front', t):
            t += P
        grids.set_stride('front', level.stride, t, lead, level.flow_stride)
        _follow(grids, follower)
        assert (grids.stride('front'), grids.flow_stride('front')) == level
        for s in range(t + lead + P, t + lead + 20 * P, P):
            if not grids.on_grid('front', s):
                continue
            src = grids.flow_source_ns('front', s)
            assert follower.on_grid_at(src), (level, s, src)
            assert 0 <= s - src <= (level.flow_stride - 1) * level.stride * P
            if level.flow_stride == 1:
                assert src == s


def test_shedding_starts_at_the_next_frame_and_a_larger_stride_takes_the_flow_frames():
    P = 20 * MS
    grids = SupervisorGrids({'front': P})
    grids.set_stride('front', 1, 100 * MS, 100 * MS, flow_stride=2)
    assert grids.flow_grid('front').ref_ns == 120 * MS      # the grid frame after 100 ms
    assert [grids.flow_source_ns('front', s * MS) for s in (120, 140, 160, 180)] == [
        120 * MS, 120 * MS, 160 * MS, 160 * MS]
    grids.set_stride('front', 2, 180 * MS, 100 * MS)        # a decision at a held frame
    assert grids.ref_ns('front') == 160 * MS                # on the flow frames: own flows
    assert all(grids.flow_source_ns('front', s) == s for s in range(200 * MS, 400 * MS, 2 * P))
    grids.set_stride('front', 1, 400 * MS, 100 * MS, flow_stride=2)   # a try: flows stay
    g = grids.flow_grid('front')
    assert g.stride == 2 and g.on_grid(160 * MS) and grids.stride('front') == 1
    assert grids.flow_source_ns('front', 520 * MS) == 520 * MS
    assert grids.flow_source_ns('front', 540 * MS) == 520 * MS
    grids.set_stride('front', 1, 600 * MS, 100 * MS)        # flows on every frame: from 700
    assert grids.flow_source_ns('front', 680 * MS) == 680 * MS      # on the old flow grid
    assert grids.flow_source_ns('front', 660 * MS) == 640 * MS
    assert grids.flow_source_ns('front', 700 * MS) == 700 * MS
    assert grids.flow_source_ns('front', 720 * MS) == 720 * MS
    grids.reset()
    assert grids.flow_stride('front') == 1
    assert grids.flow_source_ns('front', 730 * MS) == 730 * MS


def test_at_a_handover_the_new_cameras_first_frame_is_a_flow_frame():
    # the flows shed when WINDOW hands over to the down camera: its first frame has no flow
    # frame before it (the floor flow was not published in WINDOW), so it computes its own
    P = 20 * MS
    grids = SupervisorGrids({'down': P})
    grids.set_stride('down', 1, 500 * MS, 100 * MS, flow_stride=2, first_frame=True)
    assert [grids.flow_source_ns('down', s * MS) for s in (500, 520, 540)] == [
        500 * MS, 500 * MS, 540 * MS]


def test_lone_skips_count_only_while_the_next_step_sheds_the_flows():
    gov = RateGovernor(rate_governor.GovernorConfig(**NO_LEAD))
    assert gov.counts_lone_skips                        # every frame: the next step sheds
    run(gov, 0.0, 3, False)
    assert gov.flow_stride == 2 and not gov.counts_lone_skips     # the next: stride 2
    assert not RateGovernor(GovernorConfig()).counts_lone_skips   # no flow step
