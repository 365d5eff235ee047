#!/usr/bin/env python3
"""The onboard graph on a vehicle's sensors and computer: late cameras, 30 Hz, a slower CPU.

Replays a whole flight's camera frames to the onboard graph (``ibvs_bringup.composed`` with
the installed params.yaml, system time, as on the vehicle) against the sim's PX4-like
autopilot stand-in serving that flight's attitude at 100 Hz, and prints per case:

- frames answered: camera frames of the mode's camera after the start that got a
  SET_ATTITUDE_TARGET (a frame stride of 2 answers half of them by design);
- the control rate held (answered frames per second), the largest frame stride used and the
  share of the supervisor's 1 Hz reports with the flows shed (computed on every 2nd frame);
- the latency added after the image arrived: setpoint on the wire minus the image's delivery
  (median, p99), as the targets of late cameras and a slower computer are stated;
- the modes reached (time after the start) and the CPU of the graph (% of one core);
- where the frames went: the supervisor's frames complete and skipped (by missing product)
  and each perception node's images computed, superseded (skipped by a node behind for the
  newer one), grid frames missed, images without an attitude and median processing time
  (their /diagnostics);
- a machine-speed reference taken in the same run on the graph's core, before and after: a
  pure-Python loop of 3 M iterations (~0.1-0.2 s at this machine's fastest) and an image
  operation that moves with memory traffic as the perception does, so that a figure can be
  judged at any hour.

The flight: the feature-level reference run (deterministic, ibvs_harness.feature_sim), its
true pose at each frame rendered by the sim's renderer for both cameras (with the sim's read
noise), after 1 s of hover at its start; ``ibvs/start`` at 1 s. The graph flies open loop
(its setpoints do not move the replayed vehicle), which is enough to measure what it answers
and the modes its images lead it through.

Cases (``--case``, repeatable; default: all): camera delivery ``--latency-ms`` after the
stamp (with ``--jitter-ms``), ``--rate-hz`` 50 or 30, the graph ``--cpu`` full (both cores),
one (pinned to one core), half (one core shared with one busy process), third (two busy
processes), sixth (five: below what the graph needs, to see how it fails) or shared (both
cores, one busy process on each: ``--layout grouped`` (a container per camera and one
for control) or ``processes`` spread the nodes over them), and the autopilot link over UDP
or a serial cable (two pseudo-terminals at 921600 baud, ibvs_common.testing.SerialCable).

``--share F`` adds a case with the graph on F of a core: pinned beside one or two busy
processes, at the nice levels whose CFS weights split the core F : 1 - F. With ``--at-speed S`` the
share is of a core whose speed reference loop takes S s: before each run the loop is timed
and F scaled by it (``--share 0.5 --at-speed 0.095``: half a core of this machine at an
ordinary hour, whatever the hour; a core 2-4 x slower, as a Raspberry Pi 5's, is
``--share 1 / k`` of this one at its fastest).

``--callback-cpu`` runs the composed graph under callback_cpu.py and prints, for each mode,
the thread CPU per camera frame of every node's callbacks (its largest ones named): where a
frame's CPU goes, without the GIL waits that a sampling profiler counts as busy.

Run: ``make bench``, or ``AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python
benchmarks/bench_onboard.py [--case NAME] [--share F [--at-speed S]] [--repeats N]
[--callback-cpu] [--smoke]``. Needs a
quiet machine for meaningful figures (the load average and the speed reference are printed).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import select
import sys
import time

import numpy as np

from ibvs_common.core.modes import mode_name

HOVER_S = 1.0                    # s of hover at the start pose before the flight
START_AT_S = 1.0                 # ibvs/start at this replay time
WARMUP_S = 1.0                   # s after the start not counted (engage, first flows)
# a setpoint's time_boot_ms (ms-rounded, through the bridge's TIMESYNC estimate) is matched to
# the nearest frame within a quarter of the frame period; its error is reported apart (beyond
# SYNC_NS: the estimate is off), for an autopilot flies the setpoint whatever its time field says
MATCH_PERIODS = 0.25
SYNC_NS = 1_500_000
LINK_TIMEOUT_S = 60.0
CLK_TCK = os.sysconf('SC_CLK_TCK')
SERIAL_BAUD = 921600
GRAPH_CORE, HARNESS_CORE = 1, 0
ALL_CORES = os.sched_getaffinity(0)
CACHE_DIR = os.path.join('results', 'bench_onboard')
HERE = os.path.dirname(os.path.abspath(__file__))
CALLBACKS_SHOWN = 4                 # --callback-cpu: the largest callbacks printed per node
# (name, keyword arguments of run_once)
CASES = (
    ('punctual 50 Hz', {}),
    ('late 30 ms', {'latency_ms': 30.0, 'jitter_ms': 5.0}),
    ('late 30 ms, serial', {'latency_ms': 30.0, 'jitter_ms': 5.0, 'link': 'serial'}),
    ('late 30 ms, 30 Hz', {'latency_ms': 30.0, 'jitter_ms': 5.0, 'rate_hz': 30.0}),
    ('one core', {'latency_ms': 30.0, 'cpu': 'one'}),
    ('half a core', {'latency_ms': 30.0, 'cpu': 'half'}),
    ('a third of a core', {'latency_ms': 30.0, 'cpu': 'third'}),
    ('a sixth of a core', {'latency_ms': 30.0, 'cpu': 'sixth'}),
    ('two cores shared', {'latency_ms': 30.0, 'cpu': 'shared'}),
)
# --share F: the graph on F of a core, late cameras as the other CPU cases
SHARE_CASE = {'latency_ms': 30.0, 'cpu': 'share'}
# the cores of the competing busy processes, per CPU case ('shared': one on each core, the
# graph and the harness on both: a 2-core companion computer that also runs other work)
BUSY = {'full': (), 'one': (), 'half': (GRAPH_CORE,), 'third': (GRAPH_CORE,) * 2,
        'sixth': (GRAPH_CORE,) * 5, 'share': (),
        'shared': (HARNESS_CORE, GRAPH_CORE)}
# the graph on GRAPH_CORE, the harness on HARNESS_CORE
PINNED = ('one', 'half', 'third', 'sixth', 'share')
# CFS's weight of each nice level 0..19 (the kernel's sched_prio_to_weight: ~1.25 x a level)
NICE_WEIGHT = (1024, 820, 655, 526, 423, 335, 272, 215, 172, 137, 110, 87, 70, 56, 45, 36, 29,
               23, 18, 15)
MAX_NICE = 19                    # --share: the highest nice level used
SHARE_OVER, SHARE_UNDER = 0.005, 0.01   # --share: the split's tolerance above and below


# --- the flight ------------------------------------------------------------------------------

def reference_run_args() -> tuple:
    """Return the arguments of ``feature_sim.run_feature_scenario`` for the reference run.

    (world, pad, vehicle, controller config, supervisor config, feature-sim config): the
    installed configuration, no wind, the reference start.
    """
    from ibvs_common.core.config import load_pad_layout, load_vehicle
    from ibvs_control.config import ForceControllerNodeConfig, ModeSupervisorNodeConfig
    from ibvs_harness import feature_sim
    from ibvs_harness.scenario import MAX_SIM_TIME_S
    from ibvs_sim.core.world import load_world
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    ctrl = ForceControllerNodeConfig().controller_config(vehicle, world.window.width, pad)
    sup = ModeSupervisorNodeConfig().supervisor_config(world.window.width, pad)
    cfg = feature_sim.FeatureSimConfig(
        initial_position_I=np.asarray(world.initial_position_I, float),
        initial_yaw=world.initial_yaw, wind_accel_I=np.zeros(3),
        crossing_law=ctrl.crossing_law, max_time_s=MAX_SIM_TIME_S)
    return world, pad, vehicle, ctrl, sup, cfg


def reference_flight(rate_hz: float, max_s: float | None = None) -> dict:
    """Return the feature-level reference flight at the camera rate: times, poses, rates.

    Returns ``r`` (replay time of each frame, s), ``xi`` (N, 3), ``R`` (N, 3, 3), ``omega``
    (N, 3), with HOVER_S of the start pose first.
    """
    from ibvs_common.core.frames import quat_from_rot, rot_from_quat
    from ibvs_harness import feature_sim
    _, log = feature_sim.run_feature_scenario(*reference_run_args())
    t_ctrl = np.asarray(log.t_ctrl)
    q = np.array([quat_from_rot(R) for R in log.R_IB])
    t_end = t_ctrl[-1] + HOVER_S
    if max_s is not None:
        t_end = min(t_end, max_s)
    r = np.arange(0.0, t_end, 1.0 / rate_hz)
    t_flight = np.clip(r - HOVER_S, 0.0, t_ctrl[-1])
    xi_t, xi = log.truth.arrays()[:2]
    xi_f = np.stack([np.interp(t_flight, xi_t, xi[:, i]) for i in range(3)], axis=1)
    # attitude: the nearest logged frames' quaternions interpolated and renormalised
    qi = np.stack([np.interp(t_flight, t_ctrl, q[:, i]) for i in range(4)], axis=1)
    qi /= np.linalg.norm(qi, axis=1, keepdims=True)
    omega = np.stack([np.interp(t_flight, t_ctrl, np.asarray(log.Omega_B)[:, i])
                      for i in range(3)], axis=1)
    omega[r < HOVER_S] = 0.0
    return {'r': r, 'xi': xi_f, 'R': np.array([rot_from_quat(x) for x in qi]),
            'omega': omega, 'transitions': log.transitions}


def render(flight: dict, rate_hz: float, smoke: bool) -> dict:
    """Both cameras' mono8 frames of the flight (cached under results/bench_onboard/)."""
    from ibvs_common.core.config import load_pad_layout, load_vehicle
    from ibvs_sim.core.render import SceneRenderer
    from ibvs_sim.core.sensor_noise import ReadNoise
    from ibvs_sim.core.world import load_world
    path = os.path.join(CACHE_DIR, f'frames_{int(rate_hz)}hz{"_smoke" if smoke else ""}.npz')
    n = len(flight['r'])
    if os.path.exists(path):
        with np.load(path) as cached:
            if cached['front'].shape[0] == n:
                return {'front': cached['front'], 'down': cached['down']}
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    out = {}
    for cam in ('front', 'down'):
        model = vehicle.cameras[cam].model
        renderer = SceneRenderer(world, pad, vehicle.cameras[cam])
        noise = ReadNoise(2.0, (model.height, model.width), 0, cam)
        out[cam] = np.stack([noise.apply(renderer.render(flight['R'][k], flight['xi'][k]), k)
                             for k in range(n)])
    os.makedirs(CACHE_DIR, exist_ok=True)
    np.savez(path, **out)
    return out


# --- the autopilot stand-in ------------------------------------------------------------------

def stand_in(url: str, flight: dict, start_mono, stop, results) -> None:
    """Serve the sim's PX4-like autopilot on the wall clock; put (time_boot_ms, rx ns) pairs."""
    os.sched_setaffinity(0, {HARNESS_CORE})
    from ibvs_common.core.frames import GRAVITY
    from ibvs_sim.core.autopilot import Autopilot, AutopilotConfig, VehicleStateView
    from ibvs_sim.core.autopilot.stand_in import wait_s
    ap = Autopilot(AutopilotConfig(url=url, telemetry_default_hz=100.0))
    mono0 = time.monotonic()
    sys_minus_mono_ns = time.time_ns() - time.monotonic_ns()
    got = []
    fd = ap.fileno()
    r_frames = flight['r']
    while not stop.is_set():
        select.select([fd] if fd is not None else [], [], [], wait_s(ap, time.monotonic() - mono0))
        now = time.monotonic()
        r = max(now - start_mono.value, 0.0) if start_mono.value > 0 else 0.0
        k = min(int(np.searchsorted(r_frames, r)), len(r_frames) - 1)
        R = flight['R'][k]
        ap.poll(VehicleStateView(now - mono0, flight['xi'][k], np.zeros(3), R,
                                 flight['omega'][k], R.T @ np.array([0.0, 0.0, -GRAVITY])))
        while ap.new_setpoints:
            ms, wall = ap.new_setpoints.popleft()
            got.append((ms, int(wall * 1e9) + sys_minus_mono_ns))
    ap.close()
    results.put((got, sys_minus_mono_ns + int(mono0 * 1e9)))


def nice_levels(share: float) -> tuple[int, tuple, float]:
    """Return (graph's nice, busy processes' nices, the graph's share) for ``share`` of a core.

    Always-runnable tasks on one core get CPU in proportion to their CFS weights (one per
    nice level, ``NICE_WEIGHT``): the graph at nice g beside busy processes at nices b_i gets
    w(g) / (w(g) + sum w(b_i)). One or two busy processes split a core in steps of about
    0.01. Returns, of the splits within [share - 0.01, share + 0.005], the one with the
    lowest nice levels, then the fewest busy processes (the nearest split if none is). Levels
    are only raised (no privileges needed). As in the half and third cases, the graph counts
    as one task: its threads mostly run one at a time under the GIL.
    """
    if not 0.0 < share < 1.0:
        raise ValueError(f'a share of a core is in (0, 1), not {share}')
    levels = range(MAX_NICE + 1)
    splits = [(g, (b,)) for g in levels for b in levels] \
        + [(g, (b1, b2)) for g in levels for b1 in levels for b2 in levels if b1 <= b2]
    shares = [(NICE_WEIGHT[g] / (NICE_WEIGHT[g] + sum(NICE_WEIGHT[b] for b in busy)), g, busy)
              for g, busy in splits]
    close = [(max(g, *busy), len(busy), got, g, busy) for got, g, busy in shares
             if share - SHARE_UNDER <= got <= share + SHARE_OVER]
    if close:
        _, _, got, g, busy = min(close)
    else:
        got, g, busy = min(shares, key=lambda x: abs(x[0] - share))
    return g, busy, got


def emulated_share(share: float, at_speed_s: float | None, loop_s: float) -> float:
    """Return the share of this core now that stands for ``share`` of a core at ``at_speed_s``.

    ``at_speed_s``: the speed reference's Python loop time (s) of the core to emulate, e.g.
    0.095 for this machine at an ordinary hour; ``loop_s``: the loop time measured now. A
    core k x slower than this one now is 1/k of it. ``None``: ``share`` as it is.
    """
    return share if at_speed_s is None else share * loop_s / at_speed_s


def busy_loop(core: int, stop, nice: int = 0) -> None:
    """Spin on ``core`` until told to stop: a competing process (a camera driver, a recorder)."""
    os.sched_setaffinity(0, {core})
    os.nice(nice)
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def speed_reference(core: int) -> tuple[float, float]:
    """Return this machine's speed on ``core``: (Python loop s, image op ms).

    The Python loop: 3 M iterations. The image op (median of 30: a 5x5 Gaussian blur, a Sobel
    and a 3-level pyramid of a 752x480 frame, OpenCV on one thread) moves with memory
    traffic, as the perception does; the Python loop stays in the cache and can read fast
    while the image work is slow.
    """
    ctx = mp.get_context('spawn')
    q = ctx.Queue()
    p = ctx.Process(target=_timed_loop, args=(core, q))
    p.start()
    p.join(60.0)
    return q.get(timeout=5.0)


def _timed_loop(core: int, q) -> None:
    import cv2
    os.sched_setaffinity(0, {core})
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    x = 0
    for i in range(3_000_000):
        x += i
    loop_s = time.perf_counter() - t0
    img = np.random.default_rng(0).integers(0, 256, (480, 752), dtype=np.uint8)
    ms = []
    for _ in range(30):
        t0 = time.perf_counter()
        blurred = cv2.GaussianBlur(img, (5, 5), 0)
        cv2.Sobel(blurred, cv2.CV_16S, 1, 0)
        cv2.pyrDown(cv2.pyrDown(cv2.pyrDown(blurred)))
        ms.append(1e3 * (time.perf_counter() - t0))
    q.put((loop_s, float(np.median(ms))))


def speed_text(core: int) -> str:
    """Return the speed reference as printed."""
    loop_s, image_ms = speed_reference(core)
    return (f'3 M-iteration Python loop {loop_s:.3f} s, image op {image_ms:.2f} ms '
            f'(core {core})')


# --- the replay ------------------------------------------------------------------------------

class Replayer:
    """The benchmark's ROS node: camera publishers, the mode and diagnostics, ibvs/start."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image
        from std_msgs.msg import UInt8
        from std_srvs.srv import Trigger
        from ibvs_common.core.config import load_vehicle
        from ibvs_common.node_common import COMMAND_QOS, MODE_QOS
        from ibvs_sim.messages import camera_info_msg, image_msg
        self.rclpy = rclpy
        self.image_msg, self.info_msg = image_msg, camera_info_msg
        self.node = rclpy.create_node('bench_onboard_replayer')
        self.cameras = load_vehicle().cameras
        self.images = {c: self.node.create_publisher(Image, f'{c}_camera/image_raw',
                                                     qos_profile_sensor_data)
                       for c in ('front', 'down')}
        self.infos = {c: self.node.create_publisher(CameraInfo, f'{c}_camera/camera_info',
                                                    qos_profile_sensor_data)
                      for c in ('front', 'down')}
        self.modes: list = []                     # (system ns, mode)
        self.rates: list = []           # (system ns, control rate, stride, flow stride)
        self.diagnostics: dict = {}               # status name -> its newest values
        self.node.create_subscription(UInt8, 'ibvs/mode', self._on_mode, MODE_QOS)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag,
                                      COMMAND_QOS)
        self.start = self.node.create_client(Trigger, 'ibvs/start')
        self.start_request = Trigger.Request()
        self.start_future = None

    def _on_mode(self, msg) -> None:
        self.modes.append((time.time_ns(), int(msg.data)))

    def _on_diag(self, msg) -> None:
        from ibvs_control.mode_supervisor_node import DIAGNOSTICS_NAME as SUPERVISOR_STATUS
        from ibvs_perception.image_diagnostics import STATUS_SUFFIX
        for s in msg.status:
            v = {kv.key: kv.value for kv in s.values}
            if s.name == SUPERVISOR_STATUS:
                self.rates.append((time.time_ns(), float(v['control_rate_hz']),
                                   int(v['frame_stride']), int(v.get('flow_stride', '1'))))
            if s.name == SUPERVISOR_STATUS or s.name.endswith(STATUS_SUFFIX):
                self.diagnostics[s.name] = v          # the newest counts of each

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0.0:
            self.rclpy.spin_once(self.node, timeout_sec=min(0.01, left))

    def publish(self, frames: dict, k: int, stamp_ns: int) -> None:
        from builtin_interfaces.msg import Time
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        for c in ('front', 'down'):
            cam = self.cameras[c]
            self.infos[c].publish(self.info_msg(cam.model, stamp, cam.frame_id))
            self.images[c].publish(self.image_msg(frames[c][k], stamp, cam.frame_id))

    def close(self) -> None:
        self.node.destroy_node()


def cpu_ticks(pids: dict) -> dict:
    """Return utime + stime (clock ticks) of each named process and its children threads."""
    out = {}
    for name, pid in pids.items():
        try:
            with open(f'/proc/{pid}/stat') as f:
                fields = f.read().rsplit(')', 1)[1].split()
            out[name] = int(fields[11]) + int(fields[12])
        except (OSError, IndexError, ValueError):
            out[name] = None
    return out


def run_once(name: str, flight: dict, frames: dict, rate_hz: float = 50.0,
             latency_ms: float = 0.0, jitter_ms: float = 0.0, cpu: str = 'full',
             link: str = 'udp', layout: str = 'composed', seed: int = 0, run: int = 0,
             callback_cpu: bool = False, params: tuple = (), nices: tuple = (0, ())) -> dict:
    """One replay of the flight through a fresh onboard graph; return its figures.

    The nodes' logs go to ``results/bench_onboard/<case>_r<run>/``. ``callback_cpu``: the
    composed graph runs under callback_cpu.py (its callbacks' thread CPU, by mode).
    ``params``: 'name:=value' parameters for every node of the containers (an A/B).
    ``nices``: the graph's nice level and those of busy processes added on its core
    (``nice_levels``).
    """
    from ibvs_bringup.runner import ProcessRunner
    from ibvs_harness.run_scenario import write_vehicle_at_rates
    from ibvs_common.core.mavlink_connection import free_udp_port
    from ibvs_common.testing import SerialCable
    ctx = mp.get_context('spawn')
    stop, results, start_mono = ctx.Event(), ctx.Queue(), ctx.Value('d', 0.0)
    cable = None
    if link == 'serial':
        cable = SerialCable(SERIAL_BAUD)
        graph_url, ap_url = (f'{end},{SERIAL_BAUD}' for end in cable.ends)
    else:
        port = free_udp_port()
        graph_url, ap_url = f'udpout:127.0.0.1:{port}', f'udpin:127.0.0.1:{port}'
    ap = ctx.Process(target=stand_in, args=(ap_url, flight, start_mono, stop, results))
    ap.start()
    load_stop = ctx.Event()
    loads = [ctx.Process(target=busy_loop, args=(core, load_stop)) for core in BUSY[cpu]] \
        + [ctx.Process(target=busy_loop, args=(GRAPH_CORE, load_stop, b)) for b in nices[1]]
    for p in loads:
        p.start()
    pin = (['taskset', '-c', str(GRAPH_CORE)] if cpu in PINNED else []) \
        + (['nice', '-n', str(nices[0])] if nices[0] else [])
    case_dir = os.path.join(CACHE_DIR, f"{name.replace(' ', '_')}_r{run}")
    runner = ProcessRunner(log_dir=case_dir)
    os.sched_setaffinity(0, {HARNESS_CORE} if cpu in PINNED else ALL_CORES)
    rep = Replayer()
    rng = np.random.default_rng(seed)
    period_ns = int(round(1e9 / rate_hz))
    out = {'name': name, 'rate_hz': rate_hz, 'latency_ms': latency_ms, 'cpu': cpu, 'link': link,
           'nices': nices}
    delivered = {}
    try:
        # the graph configured for its cameras' rate, as a user sets vehicle.yaml's rate_hz
        os.makedirs(case_dir, exist_ok=True)
        vehicle = None if rate_hz == 50.0 else write_vehicle_at_rates(
            None, (rate_hz, rate_hz), os.path.join(case_dir, 'vehicle_onboard.yaml'),
            f'bench_onboard: cameras at {rate_hz:g} Hz')
        callbacks_json = os.path.join(case_dir, 'callback_cpu.json')
        if callback_cpu and os.path.exists(callbacks_json):
            os.remove(callbacks_json)
        launcher = [os.path.join(HERE, 'callback_cpu.py'), callbacks_json] if callback_cpu \
            else []
        argv = pin + [sys.executable, *launcher, '-m', 'ibvs_bringup.composed', '--mavlink-url',
                      graph_url]
        # the ROS arguments last: an option after --ros-args would be read as one of them
        ros_args = ([] if vehicle is None else ['-p', f'vehicle_file:={vehicle}']) \
            + [a for param in params for a in ('-p', param)]
        ros_args = ['--ros-args', *ros_args] if ros_args else []
        if layout in ('composed', 'composed-single'):
            runner.start('composed', argv + (['--single-executor']
                                             if layout == 'composed-single' else []) + ros_args)
        elif layout == 'grouped':            # a container per camera and one for control
            from ibvs_bringup.composed import GROUPS
            for group, names in GROUPS.items():
                runner.start(group, argv + ['--nodes', ','.join(names)] + ros_args)
        else:                                # a process per node, each pinned as the graph
            from ibvs_bringup import graph
            from ibvs_bringup.runner import command_for
            for spec in graph.onboard_graph(graph.GraphOptions(use_sim_time=False,
                                                               mavlink_url=graph_url,
                                                               vehicle_file=vehicle)):
                runner.start(spec.name, pin + command_for(spec.package, spec.executable,
                                                          spec.ros_args()))
        pids = {c.name: c.proc.pid for c in runner.children}
        deadline = time.monotonic() + LINK_TIMEOUT_S
        while not rep.start.service_is_ready() and time.monotonic() < deadline:
            rep.spin(0.1)
            if runner.dead():
                raise RuntimeError(f'a node died at start: {runner.dead()}')
        rep.spin(3.0)                        # the link, TIMESYNC and the telemetry settle
        t0_ns = time.time_ns() + 200_000_000
        t0_mono = time.monotonic() + 0.2
        start_mono.value = t0_mono
        a = cpu_ticks(pids)
        n = len(flight['r'])
        late = np.maximum(latency_ms + rng.uniform(-jitter_ms, jitter_ms, n), 0.0) * 1e-3
        stamps = []
        for k in range(n):
            send_at = t0_mono + k / rate_hz + late[k]
            while (wait := send_at - time.monotonic()) > 0.0:
                rep.rclpy.spin_once(rep.node, timeout_sec=wait)
            stamp_ns = t0_ns + k * period_ns
            rep.publish(frames, k, stamp_ns)
            delivered[stamp_ns] = time.time_ns()
            stamps.append(stamp_ns)
            if rep.start_future is None and flight['r'][k] >= START_AT_S:
                rep.start_future = rep.start.call_async(rep.start_request)
        seconds = time.monotonic() - t0_mono
        end_ns = time.time_ns()
        out['cpu_pct'] = {k: 100.0 * (b - a[k]) / CLK_TCK / seconds
                          for k, b in cpu_ticks(pids).items() if b is not None and a[k]}
        rep.spin(1.0)
        answer = rep.start_future.result() if rep.start_future and rep.start_future.done() \
            else None
        out['started'] = bool(answer and answer.success)
        out['start_answer'] = answer.message if answer else 'no answer to ibvs/start'
    finally:
        stop.set()
        load_stop.set()
        try:
            got, boot_to_sys_ns = results.get(timeout=20.0)
            ap.join(timeout=10.0)
        finally:
            runner.stop()
            rep.close()
            for p in loads:
                p.join(timeout=5.0)
            if cable is not None:
                out['serial_bytes'] = list(cable.moved)
                cable.close()
    out['failsafe'] = failsafe_reasons(case_dir)
    np.savez(os.path.join(case_dir, 'replay.npz'), stamps=np.array(stamps, dtype=np.int64),
             delivered=np.array([delivered[s] for s in stamps], dtype=np.int64),
             setpoints=np.array(got, dtype=np.int64).reshape(-1, 2),
             boot_to_sys_ns=boot_to_sys_ns, t0_ns=t0_ns)
    out = summarise(out, rep, got, boot_to_sys_ns, stamps, delivered, t0_ns)
    if callback_cpu and os.path.exists(callbacks_json):
        out['callbacks'] = callbacks_by_mode(callbacks_json, rep.modes, stamps, end_ns)
    return out


def callbacks_by_mode(path: str, modes: list, stamps: list, end_ns: int) -> dict:
    """callback_cpu.py's figures per mode: {mode: (frames published, {key: (calls, ns)})}."""
    from callback_cpu import per_mode
    with open(path) as f:
        snapshot = json.load(f)
    named = [(ns, mode_name(m)) for ns, m in modes]
    split = per_mode(snapshot, named, end_ns)
    starts = [ns for ns, _ in named] + [end_ns]
    stamps = np.array(stamps, dtype=np.int64)
    return {name: (int(np.count_nonzero((stamps >= starts[i]) & (stamps < starts[i + 1]))),
                   split[name])
            for i, (_, name) in enumerate(named)}


def print_callbacks(callbacks: dict) -> None:
    """Print each mode's callback CPU per camera frame: per node, and its largest callbacks."""
    for mode, (n_frames, keys) in callbacks.items():
        if n_frames < 10 or not keys:
            continue
        nodes: dict = {}
        for key, (calls, ns) in keys.items():
            nodes.setdefault(key.split(' ', 1)[0], []).append((ns, calls, key.split(' ', 1)[1]))
        total = sum(ns for _, ns in keys.values()) / 1e3 / n_frames
        print(f'    callbacks in {mode} ({n_frames} frames): {total:.0f} us of thread CPU a '
              'frame')
        for node, rows in sorted(nodes.items(), key=lambda kv: -sum(r[0] for r in kv[1])):
            rows.sort(reverse=True)
            top = ', '.join(f'{what} {ns / 1e3 / n_frames:.0f} ({ns / 1e3 / max(calls, 1):.0f} '
                            'a call)' for ns, calls, what in rows[:CALLBACKS_SHOWN])
            print(f'      {node} {sum(r[0] for r in rows) / 1e3 / n_frames:.0f} us: {top}')


def failsafe_reasons(log_dir: str) -> list:
    """Return the supervisor's reasons for FAILSAFE, from the nodes' logs in ``log_dir``."""
    reasons = []
    for log in sorted(os.listdir(log_dir)):
        if log.endswith('.log'):
            with open(os.path.join(log_dir, log), errors='replace') as f:
                reasons += [line.split(' s: ', 1)[-1].strip() for line in f
                            if '[mode_supervisor]: mode ' in line and '-> FAILSAFE at' in line]
    return reasons


def summarise(out: dict, rep: Replayer, got: list, boot_to_sys_ns: int, stamps: list,
              delivered: dict, t0_ns: int) -> dict:
    """Match setpoints to frames; figures over the frames after start + warm-up."""
    stamps = np.array(stamps, dtype=np.int64)
    start_ns = t0_ns + int((START_AT_S + WARMUP_S) * 1e9)
    modes = [(ns, m) for ns, m in rep.modes]
    end_ns = next((ns for ns, m in modes if m in (4, 5)), stamps[-1] + 1)
    counted = stamps[(stamps >= start_ns) & (stamps < end_ns)]
    match_ns = int(MATCH_PERIODS * 1e9 / out['rate_hz'])
    answered, lat = set(), []
    for ms, rx_ns in got:
        s = ms * 1_000_000 + boot_to_sys_ns
        i = int(np.searchsorted(counted, s))
        for j in (i - 1, i):
            if 0 <= j < len(counted) and abs(int(counted[j]) - s) <= match_ns \
                    and j not in answered:
                answered.add(j)
                lat.append((rx_ns - delivered[int(counted[j])]) / 1e6)
                break
    span_s = max((int(counted[-1]) - int(counted[0])) / 1e9, 1e-9) if len(counted) else 1e-9
    out.update(stamp_error_ms=stamp_errors_ms(got, boot_to_sys_ns, counted))
    out.update(frames=len(counted), answered=len(answered), latency_ms=np.array(lat),
               rate_held_hz=len(answered) / span_s,
               max_stride=max((r[2] for r in rep.rates), default=1),
               shed_pct=100.0 * sum(r[3] > 1 for r in rep.rates) / max(len(rep.rates), 1),
               diagnostics=dict(rep.diagnostics),
               modes=[(mode_name(m), (ns - t0_ns) / 1e9 - START_AT_S)
                      for ns, m in modes])
    return out


def stamp_errors_ms(got: list, boot_to_sys_ns: int, counted: np.ndarray) -> np.ndarray:
    """Return each setpoint's time minus the nearest counted frame stamp (ms).

    The bridge writes a frame's stamp in time_boot_ms through its TIMESYNC estimate of the
    autopilot's clock: an error beyond a quarter period leaves an answered frame unmatched.
    """
    if len(counted) < 2 or not got:
        return np.zeros(0)
    s = np.array([ms * 1_000_000 + boot_to_sys_ns for ms, _ in got], dtype=np.int64)
    s = s[(s >= counted[0]) & (s <= counted[-1])]
    i = np.clip(np.searchsorted(counted, s), 1, len(counted) - 1)
    before, after = s - counted[i - 1], s - counted[i]
    return np.where(np.abs(after) < np.abs(before), after, before) / 1e6


def report(r: dict) -> None:
    lat = r['latency_ms']
    frac = 100.0 * r['answered'] / max(r['frames'], 1)
    line = (f"{r['name']:22s} answered {r['answered']}/{r['frames']} ({frac:.1f} %), "
            f"rate held {r['rate_held_hz']:.1f} Hz, max stride {r['max_stride']}, "
            f"flows shed {r.get('shed_pct', 0.0):.0f} %")
    if len(lat):
        line += (f"; after arrival median {np.median(lat):.1f} ms, "
                 f"p99 {np.percentile(lat, 99):.1f} ms")
    print(line + ('' if r.get('started') else
                  f"  (the supervisor did not start: {r.get('start_answer', '?')})"))
    err = r.get('stamp_error_ms', np.zeros(0))
    if len(err):
        off = 100.0 * np.mean(np.abs(err) > SYNC_NS / 1e6)
        print(f'    setpoint time - frame stamp: median {np.median(err):+.2f} ms, {off:.0f} % '
              f'beyond {SYNC_NS / 1e6:g} ms (the bridge\'s TIMESYNC estimate)')
    print('    modes: ' + ' -> '.join(f'{m} {t:+.2f} s' for m, t in r['modes'])
          + ''.join(f' (FAILSAFE: {why})' for why in r.get('failsafe', ())))
    print_diagnostics(r.get('diagnostics', {}))
    cpu = r.get('cpu_pct', {})
    print('    CPU (% of one core): ' + ', '.join(f'{n} {v:.0f}' for n, v in cpu.items())
          + (f"; serial bytes {r['serial_bytes']}" if 'serial_bytes' in r else ''))
    if r.get('callbacks'):
        print_callbacks(r['callbacks'])


def print_diagnostics(diagnostics: dict) -> None:
    """Print where frames went: the supervisor's counts and each perception node's."""
    from ibvs_control.mode_supervisor_node import DIAGNOSTICS_NAME as SUPERVISOR_STATUS
    from ibvs_perception.image_diagnostics import STATUS_SUFFIX
    sup = diagnostics.get(SUPERVISOR_STATUS)
    if sup is not None:
        without = ', '.join(f"{k[len('frames_skipped_without_'):]} {v}" for k, v in sup.items()
                            if k.startswith('frames_skipped_without_'))
        print(f"    supervisor: frames complete {sup.get('frames_complete')}, skipped "
              f"{sup.get('frames_skipped')} ({without or 'none'}); late products dropped "
              f"{sup.get('late_products_dropped')}, off-grid "
              f"{sup.get('off_grid_products_dropped')}")
    nodes = [(name[:-len(STATUS_SUFFIX)], v) for name, v in sorted(diagnostics.items())
             if name.endswith(STATUS_SUFFIX)]
    if nodes:
        print('    nodes (computed / superseded / grid frames missed / without attitude / '
              'median ms): '
              + '; '.join(f"{n} {v.get('images_computed')}/{v.get('images_superseded')}/"
                          f"{v.get('grid_frames_missed')}/{v.get('images_without_attitude')}/"
                          f"{v.get('processing_median_ms')}" for n, v in nodes))


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--case', action='append', default=[], choices=[c[0] for c in CASES])
    p.add_argument('--repeats', type=int, default=1)
    p.add_argument('--layout', choices=('composed', 'composed-single', 'grouped', 'processes'),
                   default='composed',
                   help='composed-single: composed with --single-executor (every node on one '
                   'executor); grouped: a container per camera and one for control')
    p.add_argument('--callback-cpu', action='store_true',
                   help='the composed graph under callback_cpu.py: each mode\'s thread CPU per '
                   'frame, by node and callback')
    p.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                   help='a parameter for every node of the containers (composed and grouped '
                   'layouts), e.g. flow_shed_stride:=1 for the governor without its flow step')
    p.add_argument('--share', type=float, action='append', default=[], metavar='F',
                   help='a case with the graph on F of a core (0 < F < 1): pinned beside one '
                   'or two busy processes, their nice levels set for that share; runs only '
                   'these cases unless --case is given too')
    p.add_argument('--at-speed', type=float, metavar='S',
                   help='with --share: F of a core whose speed reference\'s Python loop takes '
                   'S s (e.g. 0.095, this machine at an ordinary hour), scaled by the loop '
                   'measured before each run, so that a run judges the same computer at any '
                   'hour')
    p.add_argument('--smoke', action='store_true',
                   help='4 s of the flight, the first case only (CI: the command still runs)')
    args = p.parse_args(argv)
    if any(not 0.0 < f < 1.0 for f in args.share):
        p.error('--share takes a fraction of a core in (0, 1)')
    if args.at_speed is not None and (not args.share or args.at_speed <= 0.0):
        p.error('--at-speed takes a positive loop time (s), with --share')
    if args.param and args.layout == 'processes':
        p.error('--param is for the containers (composed, composed-single, grouped)')
    if any(':=' not in a for a in args.param):
        p.error('--param takes NAME:=VALUE')
    if args.callback_cpu and args.layout not in ('composed', 'composed-single'):
        p.error('--callback-cpu measures one composed process (--layout composed or '
                'composed-single)')
    from ibvs_bringup.graph import ensure_ament_prefix_path
    from ibvs_common.dds_profile import use_dds_profile_here
    from ibvs_common.testing import isolate_dds
    ensure_ament_prefix_path()
    isolate_dds()                # a DDS domain of its own: no other graph on this machine
    use_dds_profile_here()                           # the graph's shared-memory profile
    import rclpy
    cases = [(n, kw) for n, kw in CASES if n in args.case or not (args.case or args.share)]
    cases += [(share_case_name(f, args.at_speed), dict(SHARE_CASE, share=f))
              for f in args.share]
    if args.smoke:
        cases = cases[:1]
    print(f'load average {os.getloadavg()[0]:.2f}; speed reference: {speed_text(GRAPH_CORE)}')
    flights, frames = {}, {}
    rclpy.init()
    try:
        run_cases(cases, args, flights, frames)
    finally:
        rclpy.try_shutdown()
    print(f'speed reference at the end: {speed_text(GRAPH_CORE)}')
    return 0


def run_cases(cases: list, args, flights: dict, frames: dict) -> None:
    """Each case once per repeat, rendering each camera rate's frames once."""
    for run in range(args.repeats):
        for name, kw in cases:
            rate = kw.get('rate_hz', 50.0)
            if rate not in flights:
                flights[rate] = reference_flight(rate, 4.0 if args.smoke else None)
                t0 = time.monotonic()
                frames[rate] = render(flights[rate], rate, args.smoke)
                print(f'{len(flights[rate]["r"])} frames at {rate:g} Hz ready '
                      f'({time.monotonic() - t0:.1f} s)')
            kw = dict(kw)
            if 'share' in kw:
                kw.update(share_settings(kw.pop('share'), args.at_speed))
            report(run_once(name, flights[rate], frames[rate], layout=args.layout, run=run,
                            callback_cpu=args.callback_cpu, params=tuple(args.param), **kw))


def share_case_name(share: float, at_speed_s: float | None) -> str:
    """Return a --share case's printed name."""
    return f'{share:g} of a core' + (f' at {at_speed_s:g} s' if at_speed_s else '')


def share_settings(share: float, at_speed_s: float | None) -> dict:
    """Return run_once's CPU arguments for ``share`` of a core (at a speed); print them.

    A core to emulate that is faster than this one now (a share above the whole core) gets
    the whole core, said so: the figures then stand for a slower computer than asked.
    """
    loop_s = speed_reference(GRAPH_CORE)[0] if at_speed_s else None
    here = emulated_share(share, at_speed_s, loop_s)
    told = f'{share:g} of a core' + (f' at {at_speed_s:g} s: this core runs the loop in '
                                     f'{loop_s:.3f} s now, so {here:.3f} of it' if at_speed_s
                                     else '')
    if here >= 1.0:
        print(f'{told}; more than this core: the graph gets all of it (a slower computer '
              'than asked)')
        return {'cpu': 'one'}
    g, busy, got = nice_levels(here)
    print(f'{told}; the graph at nice {g} beside busy processes at nice '
          f'{", ".join(map(str, busy))}: {got:.3f}')
    return {'cpu': 'share', 'nices': (g, busy)}


if __name__ == '__main__':
    sys.exit(main())
