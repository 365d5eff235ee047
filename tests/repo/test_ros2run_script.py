"""scripts/ros2run: `ros2 run` without the ros2 CLI, on the console scripts make install made."""
import os
import subprocess
import sys

PY = sys.executable


def test_ros2run_script_runs_a_console_script_with_ros_args():
    script = os.path.join(os.path.dirname(__file__), '..', '..', 'scripts', 'ros2run')
    out = subprocess.run([script, 'ibvs_bringup', 'runner', '--help'], capture_output=True,
                         text=True, timeout=60, env=dict(os.environ, PYTHON=PY))
    assert out.returncode == 0 and 'graph' in out.stdout
    bad = subprocess.run([script, 'ibvs_bringup', 'nope'], capture_output=True, text=True,
                         timeout=60, env=dict(os.environ, PYTHON=PY))
    assert bad.returncode == 1 and 'no executable' in bad.stderr
