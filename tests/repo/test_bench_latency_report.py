"""bench_latency: the dead-input report (differences within a round) and its case selection."""
from pathlib import Path

import numpy as np
from script_module import load_script

BENCH = Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_latency.py'


def load_bench():
    return load_script(BENCH, 'bench_latency')


def test_dead_input_differences_are_paired_by_round(capsys):
    bench = load_bench()

    def run(median_ms: float) -> dict:
        return {'latency_ms': np.array([median_ms - 1.0, median_ms, median_ms + 1.0])}

    # the machine drifts by 5 ms between the rounds; the pad-killed run is 0.5 ms slower
    # than its own round's baseline each time, the down-stopped one 0.2 ms faster
    rounds = [{'all inputs': run(10.0 + d), 'pad detector killed': run(10.5 + d),
               'down camera stopped': run(9.8 + d)} for d in (0.0, 5.0, -3.0)]
    bench.dead_input_report(rounds)
    out = capsys.readouterr().out
    assert 'pad detector killed: median latency +0.50 ms against all inputs (median of 3 ' \
           'round(s); range +0.50 ... +0.50 ms)' in out
    assert 'down camera stopped: median latency -0.20 ms' in out
    assert 'composed' not in out                 # no composed runs: nothing said about them


def test_case_selection():
    bench = load_bench()
    every = [name for name, _, _ in bench.CASES]
    assert [n for n, _ in bench.select_cases([])] == every
    assert bench.select_cases(['composed, all inputs']) == [('composed, all inputs',
                                                             {'composed': True})]
    assert all(not kw.get('composed') for _, kw in bench.select_cases([], no_composed=True))
    assert bench.select_cases(['composed, all inputs'], no_composed=True) == []
