"""bench_onboard's ``--share``: the nice levels that give the graph a share of a core.

Checked against the kernel's rule of thumb, not its table: each nice level weighs ~1.25 x
less than the one before (sched_prio_to_weight's "10 % effect"), so a task at nice g beside
tasks at nices b_i gets ~1 / (1 + sum 1.25 ** (g - b_i)) of the core.
"""
from pathlib import Path

import pytest

from script_module import load_script

BENCH = Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_onboard.py'


@pytest.fixture(scope='module')
def bench():
    return load_script(BENCH, 'bench_onboard')


def rule_of_thumb(g: int, busy: tuple) -> float:
    return 1.0 / (1.0 + sum(1.25 ** (g - b) for b in busy))


@pytest.mark.parametrize('share', [0.05, 0.2, 1 / 3, 0.387, 0.419, 0.5, 0.66, 0.9])
def test_the_levels_give_the_share(bench, share):
    g, busy, got = bench.nice_levels(share)
    assert 0 <= g <= 19 and 1 <= len(busy) <= 2 and all(0 <= b <= 19 for b in busy)
    assert share - 0.01 <= got <= share + 0.005       # never much more than asked
    assert rule_of_thumb(g, busy) == pytest.approx(got, abs=0.02)


def test_half_a_core_is_one_busy_process_at_the_graphs_level(bench):
    assert bench.nice_levels(0.5) == (0, (0,), 0.5)


def test_a_third_is_the_third_case_or_as_near(bench):
    g, busy, got = bench.nice_levels(1 / 3)
    assert got == pytest.approx(1 / 3, abs=0.005)


@pytest.mark.parametrize('share', [0.0, 1.0, -0.1, 1.5])
def test_a_share_outside_the_core_is_refused(bench, share):
    with pytest.raises(ValueError, match='share of a core'):
        bench.nice_levels(share)


def test_a_share_at_a_speed_scales_with_the_loop(bench):
    # half a core of a computer whose loop takes 0.1 s is 0.35 of a core that takes 0.07 s,
    # and 0.75 of one that takes 0.15 s
    assert bench.emulated_share(0.5, 0.1, 0.07) == pytest.approx(0.35)
    assert bench.emulated_share(0.5, 0.1, 0.15) == pytest.approx(0.75)
    assert bench.emulated_share(0.5, None, 0.07) == 0.5
