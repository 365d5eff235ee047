"""Every benchmark and the README's run commands, run briefly, so that drift fails CI.

The figures of these short runs mean nothing (a few frames, a loaded machine); the point is
that each command still starts, runs its whole path and exits 0. The real figures come from
the full runs documented in docs/performance.md.
"""
import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

# the benchmarks run graphs of their own: with the whole-graph runs on one pytest-xdist worker,
# not beside them (CI: the latency smoke run answered 0 of 35 frames at load average 4)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group('whole_graph')]
ROOT = Path(__file__).resolve().parents[2]
BENCH_ARGS = {'bench_perception.py': ['--frames', '5'], 'bench_sim.py': ['--frames', '10'],
              'bench_log_throttle.py': ['--calls', '50'], 'bench_gc_pause.py': ['--repeats', '3'],
              'bench_latency.py': ['--smoke', '--grouped'],
              'bench_window_robustness.py': ['--smoke'], 'bench_idle_cpu.py': ['--smoke'],
              'bench_pad_groups.py': ['--poses', '2'], 'bench_lockstep.py': ['--smoke'],
              'bench_mavlink_receive.py': ['--smoke'],
              'bench_onboard.py': ['--smoke', '--callback-cpu', '--share', '0.5',
                                   '--at-speed', '0.095'],
              'bench_instructions.py': ['--smoke']}


def run(args, cwd, timeout=600):
    proc = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ))
    assert proc.returncode == 0, f'{args} exited {proc.returncode}:\n{proc.stdout[-2000:]}\n' \
                                 f'{proc.stderr[-3000:]}'
    return proc.stdout


def test_every_benchmark_has_a_smoke_run():
    assert sorted(p.name for p in (ROOT / 'benchmarks').glob('bench_*.py')) == sorted(BENCH_ARGS)


@pytest.mark.parametrize('name', sorted(BENCH_ARGS))
def test_benchmark_smoke_run(name, tmp_path):
    out = run([str(ROOT / 'benchmarks' / name), *BENCH_ARGS[name]], cwd=tmp_path)
    print(out)
    # bench_latency's smoke run reports every run's answered frames, a median only when one
    # was answered (a loaded CI machine may make its graph fail safe first)
    expected = {'bench_latency.py': 'answered', 'bench_onboard.py': 'answered',
                'bench_instructions.py': 'processed natively'}.get(name, 'median')
    assert expected in out


def test_readme_feature_level_run(tmp_path):
    """``make run RUN_ARGS="--feature-level"`` (README): the feature-level closed loop."""
    run(['-m', 'ibvs_harness.run_scenario', '--feature-level', '--no-plots',
         '--results-root', str(tmp_path), '--run-name', 'feature'], cwd=tmp_path)
    summary = json.loads((tmp_path / 'feature' / 'summary.json').read_text())
    assert summary['success'] is True, summary


def test_readme_run_help_lists_the_options(tmp_path):
    out = run(['-m', 'ibvs_harness.run_scenario', '--help'], cwd=tmp_path)
    for option in ('--feature-level', '--random-ic', '--wind', '--real-time-factor'):
        assert option in out


def test_attitude_response_script_smoke(tmp_path):
    """scripts/attitude_response.py (docs/sim.md): the sim's fit, short and coarse.

    Its line per axis must name a fitted loop near vehicle.yaml's (the coarse grid's step).
    """
    out = run([str(ROOT / 'scripts' / 'attitude_response.py'), '--smoke'], cwd=tmp_path)
    print(out)
    lines = [ln.split() for ln in out.splitlines() if ln.startswith('sim')]
    assert [ln[1] for ln in lines] == ['roll', 'pitch', 'yaw']
    wn = {ln[1]: float(ln[ln.index('wn') + 1]) for ln in lines}
    assert 10.0 <= wn['roll'] <= 15.0 and 2.5 <= wn['yaw'] <= 4.0, out
