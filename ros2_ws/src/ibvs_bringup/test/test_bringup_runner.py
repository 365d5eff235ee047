"""The runner starts processes, stops them all (even stubborn ones) and reports a dead one."""
import os
import subprocess
import sys
import time

from ibvs_bringup import parent_death, ros2run
from ibvs_bringup.runner import ProcessRunner
import pytest

PY = sys.executable


def _wait(pred, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:   # a zombie counts as gone
        with open(f'/proc/{pid}/stat') as f:
            return f.read().split()[2] != 'Z'
    except OSError:
        return False


def test_dead_process_is_reported_with_code_and_stderr(tmp_path):
    with ProcessRunner(log_dir=str(tmp_path)) as runner:
        runner.start('sleeper', [PY, '-c', 'import time; time.sleep(60)'])
        runner.start('crasher', [PY, '-c',
                                 'import sys; print("bad camera_info", file=sys.stderr); '
                                 'sys.exit(3)'])
        assert _wait(lambda: runner.dead())
    # reported once, by name, with the exit code and the last stderr line
    runner2 = ProcessRunner()
    runner2.start('crasher', [PY, '-c', 'import sys; sys.stderr.write("boom\\n"); sys.exit(3)'])
    try:
        dead = []
        assert _wait(lambda: dead.extend(runner2.dead()) or dead)
        assert dead[0].name == 'crasher' and dead[0].returncode == 3
        assert dead[0].stderr_tail[-1] == 'boom' and 'boom' in dead[0].report()
        assert runner2.dead() == []
    finally:
        runner2.stop()
    assert 'bad camera_info' in (tmp_path / 'crasher.log').read_text()


def test_stop_escalates_to_sigkill_and_kills_grandchildren(tmp_path):
    pid_file = tmp_path / 'grandchild.pid'
    stubborn = ('import signal, subprocess, sys, time\n'
                'signal.signal(signal.SIGINT, signal.SIG_IGN)\n'
                'signal.signal(signal.SIGTERM, signal.SIG_IGN)\n'
                f'p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])\n'
                f'open({str(pid_file)!r}, "w").write(str(p.pid))\n'
                'time.sleep(60)\n')
    ready_file = tmp_path / 'polite.ready'
    # 'polite' says when it is in its sleep: a SIGINT during the interpreter's start-up (a CI
    # run under load) ends it with 1 (a KeyboardInterrupt in site's imports), not -SIGINT
    polite = f'import pathlib, time\npathlib.Path({str(ready_file)!r}).write_text("1")\n' \
        'time.sleep(60)\n'
    runner = ProcessRunner(stop_timeouts=(0.5, 0.5, 2.0))
    runner.start('stubborn', [PY, '-c', stubborn])
    runner.start('polite', [PY, '-c', polite])
    try:
        assert _wait(lambda: pid_file.exists() and pid_file.read_text())
        assert _wait(ready_file.exists)
        assert sorted(runner.running()) == ['polite', 'stubborn']
    finally:
        t0 = time.monotonic()
        codes = runner.stop()
    assert time.monotonic() - t0 < 5.0
    assert codes['stubborn'] == -9 and codes['polite'] == -2
    assert _wait(lambda: not _alive(int(pid_file.read_text())), 3.0)


def test_runner_passes_the_environment_through():
    env = dict(os.environ, ROS_DOMAIN_ID='77')
    runner = ProcessRunner(env=env)
    runner.start('env', [PY, '-c', 'import os, sys; sys.exit(int(os.environ["ROS_DOMAIN_ID"]))'])
    try:
        assert _wait(lambda: runner.running() == [])
    finally:
        codes = runner.stop()
    assert codes['env'] == 77


def test_runner_cli_stops_its_nodes_on_sigterm(tmp_path):
    """The runner process itself: SIGTERM -> every child stopped, exit code 0."""
    code = ('import sys, time\n'
            'from ibvs_bringup import runner\n'
            'r = runner.ProcessRunner()\n'
            'runner.raise_on_sigterm()\n'
            'try:\n'
            f'    r.start("child", [sys.executable, "-c", "import time; time.sleep(60)"])\n'
            f'    open({str(tmp_path / "pid")!r}, "w").write(str(r.children[0].proc.pid))\n'
            '    time.sleep(60)\n'
            'except runner.Terminated:\n'
            '    pass\n'
            'finally:\n'
            '    r.stop()\n')
    proc = subprocess.Popen([PY, '-c', code])
    try:
        assert _wait(lambda: (tmp_path / 'pid').exists() and (tmp_path / 'pid').read_text())
        child = int((tmp_path / 'pid').read_text())
        proc.terminate()
        assert proc.wait(timeout=10) == 0
        assert _wait(lambda: not _alive(child), 3.0)
    finally:
        proc.kill()
        proc.wait(timeout=5)


@pytest.mark.skipif(not parent_death.supported(), reason='PR_SET_PDEATHSIG is Linux only')
def test_a_killed_runner_takes_its_nodes_with_it(tmp_path):
    """SIGKILL of the runner (no chance to stop anything): the kernel sends its nodes SIGTERM.

    Without the parent death signal the child, in a process group of its own, runs on.
    """
    code = ('import time\n'
            'from ibvs_bringup import runner\n'
            'r = runner.ProcessRunner()\n'
            'r.start("child", [__import__("sys").executable, "-c", '
            '"import time; time.sleep(60)"])\n'
            f'open({str(tmp_path / "pid")!r}, "w").write(str(r.children[0].proc.pid))\n'
            'time.sleep(60)\n')
    proc = subprocess.Popen([PY, '-c', code])
    child = None
    try:
        assert _wait(lambda: (tmp_path / 'pid').exists() and (tmp_path / 'pid').read_text())
        child = int((tmp_path / 'pid').read_text())
        # the child is the command itself (exec'd), not a wrapper around it
        assert _wait(lambda: 'time.sleep(60)' in open(f'/proc/{child}/cmdline').read(), 5.0)
        assert _alive(child)
        proc.kill()
        proc.wait(timeout=5)
        assert _wait(lambda: not _alive(child), 3.0), 'the node outlived its killed runner'
    finally:
        proc.kill()
        proc.wait(timeout=5)
        if child is not None and _alive(child):
            os.kill(child, 9)


def test_parent_death_refuses_to_start_when_its_parent_is_already_gone():
    # a parent pid that is not ours: as if the runner died before the child's prctl
    out = subprocess.run([PY, '-m', 'ibvs_bringup.parent_death', '1', '--', PY, '-c',
                          'print("ran")'], capture_output=True, text=True, timeout=30)
    assert out.returncode == parent_death.EXIT_PARENT_GONE
    assert 'ran' not in out.stdout and 'parent 1 is gone' in out.stderr
    bad = subprocess.run([PY, '-m', 'ibvs_bringup.parent_death', 'x', PY],
                         capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and 'usage' in bad.stderr
    assert parent_death.wrap(['a', 'b'], 7)[-4:] == ['7', '--', 'a', 'b']


def test_resolver_finds_console_scripts_and_reports_unknown_ones(monkeypatch, tmp_path):
    res = ros2run.resolve('ibvs_bringup', 'runner')          # make install: lib/<pkg>/<exe>
    assert res.module == 'ibvs_bringup.runner' or res.source.endswith('lib/ibvs_bringup/runner')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))   # no colcon layout: entry point
    res = ros2run.resolve('ibvs_bringup', 'runner')
    assert res.module == 'ibvs_bringup.runner'
    assert ros2run.unavailable_reason('ibvs_bringup', 'runner') is None
    with pytest.raises(ros2run.ResolveError):
        ros2run.resolve('ibvs_bringup', 'no_such_executable')
    assert 'no_such_package' in ros2run.unavailable_reason('no_such_package', 'x')


def test_runner_restarts_a_respawn_node_with_backoff_and_leaves_the_others(tmp_path):
    """As on a vehicle: the graph keeps running; perception nodes come back, doubling waits."""
    import time as _time
    from ibvs_bringup import graph
    from ibvs_bringup.runner import ProcessRunner
    runner = ProcessRunner(log_dir=str(tmp_path), stop_timeouts=(1.0, 1.0, 1.0))
    try:
        runner.start('flaky', [sys.executable, '-c', 'import sys; sys.exit(3)'], respawn=True)
        runner.start('steady', [sys.executable, '-c', 'import time; time.sleep(60)'])
        runner.start('fatal', [sys.executable, '-c', 'import sys; sys.exit(4)'])
        _time.sleep(0.5)
        t0 = _time.monotonic()
        events = runner.supervise(t0)
        assert any("'flaky' died with exit code 3" in e for e in events)
        assert any("'fatal' died with exit code 4" in e and 'not restarted' in e for e in events)
        assert any('restarts in 1.0 s' in e for e in events)
        assert runner.supervise(t0 + 0.5) == []                        # backoff not over
        assert "restarted (1 so far)" in runner.supervise(t0 + graph.RESPAWN_DELAY_S)[0]
        _time.sleep(0.5)                                               # dies again at once
        events = runner.supervise(t0 + 2.0)
        assert any('restarts in 2.0 s' in e for e in events)          # doubled
        assert 'steady' in runner.running() and 'fatal' not in runner.running()
    finally:
        runner.stop()
