"""The launch files under real launch_ros, as ``ros2 launch`` runs them (not the runner).

Runs where ``launch`` and ``launch_ros`` are installed (a Jazzy install: apt, the Docker image,
colcon); SKIPPED in the project venv, where they are not (they are not on PyPI; README
"Facts"). The launch files are started as ros2launch's ``launch_a_launch_file`` does
(``LaunchService`` + ``IncludeLaunchDescription`` of the installed file, ``name:=value``
arguments), so the ``ros2`` CLI itself is not needed:

- ``onboard.launch.py layout:=processes`` against the sim's PX4-like autopilot on UDP: the
  bridge links; a perception node killed is respawned alone (launch_ros ``respawn``), the
  other nodes keep their pids; the launch killed with SIGKILL takes every node with it (the
  parent death signal of ``parent_death.launch_prefix()``, docs/bringup.md);
- ``sim.launch.py``: the whole graph against the sim starts on ``ibvs/start`` and lands on the
  pad within docs/spec.md section 5 (touchdown from the sim's ``sim/events``); Ctrl-C (SIGINT) to
  the launch stops every node cleanly, without a traceback. The start is called as soon as
  it is accepted, and the lockstep sim must never have waited out its 5 s wall-clock
  time-out: before ``ibvs/start`` was applied at a frame (``ModeSupervisor.request_start``),
  the first WINDOW frame's front flow was held back by mode gating until that frame's own
  status, and the sim stalled twice, or for every frame of the first 0.5 s of sim time
  (docs/bringup.md).

Checked by hand on 2026-11-27 with launch 3.4.3 and launch_ros 0.26.6 (their jazzy branches)
installed into a throwaway ``--target`` directory on PYTHONPATH (docs/bringup.md).
"""
import importlib.util
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(importlib.util.find_spec('launch_ros') is None,
                                 reason='launch_ros is not installed (not on PyPI): these '
                                        'tests run on a Jazzy install, where ros2 launch is')]

# ros2launch's launch_a_launch_file, without the ros2 CLI: PKG FILE [name:=value ...]
LAUNCHER = '''
import os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)   # a background runner may ignore it
from ament_index_python.packages import get_package_share_directory
import launch
from launch.launch_description_sources import AnyLaunchDescriptionSource
pkg, name, *args = sys.argv[1:]
path = os.path.join(get_package_share_directory(pkg), 'launch', name)
service = launch.LaunchService(argv=args, noninteractive=True)
service.include_launch_description(launch.LaunchDescription([
    launch.actions.IncludeLaunchDescription(
        AnyLaunchDescriptionSource(path),
        launch_arguments=[tuple(a.split(':=', 1)) for a in args])]))
sys.exit(service.run())
'''
ONBOARD_NODES = 7
SIM_NODES = 8                 # the sim and the onboard nodes
UP_TIMEOUT_S = 60.0           # s (wall): nodes up, the bridge linked
RESPAWN_TIMEOUT_S = 15.0      # s (wall): graph.RESPAWN_DELAY_S (1 s) and a node's start-up
GONE_TIMEOUT_S = 10.0         # s (wall): nodes gone after the launch's death or its Ctrl-C
FLIGHT_TIMEOUT_S = 120.0      # s (wall): start to touchdown in lockstep on this 2-core machine


def _launch(file_name: str, args: list, log: Path) -> subprocess.Popen:
    with open(log, 'w') as out:
        return subprocess.Popen([sys.executable, '-c', LAUNCHER, 'ibvs_bringup', file_name,
                                 *args], stdout=out, stderr=subprocess.STDOUT)


def _children(pid: int) -> dict:
    """{pid: command line} of the processes whose parent is ``pid`` (Linux /proc)."""
    found = {}
    for entry in os.listdir('/proc'):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f'/proc/{entry}/stat').read_text()
            cmd = Path(f'/proc/{entry}/cmdline').read_bytes().replace(b'\0', b' ').decode()
        except OSError:
            continue
        if int(stat.rsplit(')', 1)[1].split()[1]) == pid:
            found[int(entry)] = cmd
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def _wait(condition, timeout_s: float, what: str, log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f'{what} within {timeout_s:.0f} s; launch output:\n'
                                 + log.read_text()[-3000:])
        time.sleep(0.2)


def test_onboard_launch_respawns_a_dead_perception_node_and_dies_with_its_launch(tmp_path):
    from ibvs_sim.core.autopilot import AutopilotConfig
    from ibvs_sim.core.autopilot.stand_in import HoverStandIn
    autopilot = HoverStandIn(AutopilotConfig(url='udpin:127.0.0.1:0'))
    log = tmp_path / 'launch.log'
    proc = _launch('onboard.launch.py', [f'mavlink_url:=udpout:127.0.0.1:{autopilot.local_port}',
                                         'layout:=processes'], log)
    try:
        _wait(lambda: len(_children(proc.pid)) == ONBOARD_NODES
              and 'engage: preflight -> standby' in log.read_text(),
              UP_TIMEOUT_S, f'{ONBOARD_NODES} nodes up and the bridge linked', log)
        before = _children(proc.pid)
        window = [pid for pid, cmd in before.items() if 'window_detector' in cmd]
        assert len(window) == 1, before
        os.kill(window[0], signal.SIGKILL)

        def respawned():
            now = _children(proc.pid)
            return len(now) == ONBOARD_NODES and any(
                'window_detector' in cmd and pid not in before for pid, cmd in now.items())
        _wait(respawned, RESPAWN_TIMEOUT_S, 'the window detector respawned', log)
        now = _children(proc.pid)
        # the other six nodes ran on undisturbed
        assert {p for p in before if p != window[0]} <= set(now), (before, now)
        proc.kill()                                 # the launch dies without a word
        proc.wait(timeout=10)
        _wait(lambda: not any(_alive(pid) for pid in now), GONE_TIMEOUT_S,
              'every node gone after its launch was killed', log)
    finally:
        if proc.poll() is None:
            proc.kill()
        autopilot.close()


def test_sim_launch_flies_to_the_pad_on_ibvs_start_and_stops_on_ctrl_c(tmp_path):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String
    from std_srvs.srv import Trigger
    from ibvs_common.core.mavlink_connection import free_udp_port
    from ibvs_sim.core.evaluation import MAX_LANDING_ERROR_M, MAX_TOUCHDOWN_SPEED_MPS

    log = tmp_path / 'launch.log'
    proc = _launch('sim.launch.py', [f'mavlink_port:={free_udp_port()}'], log)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('launch_test', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    modes, touchdown = [], []

    def on_status(msg):
        for status in msg.status:
            for kv in status.values:
                if kv.key == 'mode' and (not modes or modes[-1] != int(kv.value)):
                    modes.append(int(kv.value))

    def on_event(msg):
        event = json.loads(msg.data)
        if event.get('type') == 'touchdown':
            touchdown.append(event)

    node.create_subscription(DiagnosticArray, 'ibvs/supervisor_status', on_status, 10)
    node.create_subscription(String, 'sim/events', on_event, QoSProfile(
        depth=50, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    start = node.create_client(Trigger, 'ibvs/start')
    try:
        _wait(lambda: len(_children(proc.pid)) == SIM_NODES, UP_TIMEOUT_S,
              f'{SIM_NODES} nodes up', log)
        deadline, answer = time.monotonic() + UP_TIMEOUT_S, None
        while answer is None or not answer.success:     # 1 s apart until accepted
            assert time.monotonic() < deadline, (answer, log.read_text()[-3000:])
            if start.wait_for_service(timeout_sec=1.0):
                future = start.call_async(Trigger.Request())
                executor.spin_until_future_complete(future, timeout_sec=5.0)
                answer = future.result()
                if answer is None or not answer.success:
                    time.sleep(1.0)
        deadline = time.monotonic() + FLIGHT_TIMEOUT_S
        while not (touchdown and 4 in modes):
            assert time.monotonic() < deadline, (modes, log.read_text()[-3000:])
            executor.spin_once(timeout_sec=0.2)
        stalls = log.read_text().count('lockstep: no setpoint answered a frame')
        print(f'modes {modes}, touchdown {touchdown[0]}, lockstep time-outs {stalls}')
        assert stalls == 0, log.read_text()[-3000:]
        assert modes[-4:] == [1, 2, 3, 4], modes            # WINDOW CROSSING LANDING SHUTDOWN
        x, y = touchdown[0]['position_map'][:2]             # the pad at the origin of map
        assert np.hypot(x, y) <= MAX_LANDING_ERROR_M, touchdown
        assert touchdown[0]['speed_mps'] <= MAX_TOUCHDOWN_SPEED_MPS, touchdown
        nodes = _children(proc.pid)
        proc.send_signal(signal.SIGINT)                     # Ctrl-C
        proc.wait(timeout=30)
        _wait(lambda: not any(_alive(pid) for pid in nodes), GONE_TIMEOUT_S,
              'every node gone after Ctrl-C', log)
        text = log.read_text()
        assert text.count('process has finished cleanly') == SIM_NODES, text[-3000:]
        assert 'Traceback' not in text, text
    finally:
        if proc.poll() is None:
            proc.kill()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
