"""Fly the reference scenario through the whole graph and report like the paper (`make run`).

sim (lockstep) <-> MAVLink <-> bridge <-> controller <-> supervisor <-> perception, started
with the runner (graph.sim_graph), gated by the preflight checks, started by the supervisor
itself at sim t = 1 s (``auto_start_at_s``: the same frame in every run) and stopped on
touchdown + mode 4 (disarm), collision, failsafe, 60 s of sim time or the wall timeout.
Writes ``results/<run>/``: summary.json (docs/spec.md section 5, ibvs_sim's evaluation of the
ground truth, plus a ``run`` block), the paper's figures (PNG), ``bag/`` (MCAP rosbag2) and
``logs/<node>.log``. ``--feature-level`` flies ibvs_sim's feature-level closed loop
instead (no images, no ROS) and reports the same way.

Exit code: 0 success, 1 the flight failed docs/spec.md's criteria, 2 the run could not be flown.
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import time
from typing import TYPE_CHECKING

from ibvs_bringup import graph
from ibvs_bringup.runner import (DEFAULT_LAYOUT, LAYOUTS, ProcessRunner, raise_on_sigterm,
                                 Terminated)
from ibvs_common.core.config import load_pad_layout, load_vehicle, PadLayout
from ibvs_harness import plots, report
from ibvs_common.core.mavlink_connection import free_udp_port
from ibvs_common.core.modes import mode_name
from ibvs_control.core.pilot_input import PilotInput
from ibvs_control.mavlink.sequencer.common import EngageState
from ibvs_harness.scenario import (AUTOPILOTS, DEFAULT_IMAGE_EVERY, FAILSAFE_MODE, finish,
                                   IDLE_MODE, MAX_SIM_TIME_S, missing_executables,
                                   prepare_out_dir, random_initial_position, run_block,
                                   RunOptions, SHUTDOWN_GRACE_S, SHUTDOWN_MODE,
                                   supervisor_log, supervisor_transitions)
from ibvs_sim.core.world import load_world, WorldConfig
import numpy as np

CAMERA_NAMES = ('front', 'down')        # the order of the sim's camera_rate_hz
CAMERA_RATE = 'camera_rate_hz'

if TYPE_CHECKING:
    from ibvs_harness.monitor_node import ScenarioMonitor
    from ibvs_harness.feature_sim import FeatureSimLog
    from rclpy.executors import Executor


# --- feature-level run ----------------------------------------------------------------------

def run_feature_level(opts: RunOptions) -> int:
    """Fly ibvs_sim's feature-level closed loop and report it like a graph run."""
    try:
        from ibvs_harness import feature_sim
        from ibvs_harness.core_configs import controller_config, supervisor_config
        from ibvs_control.core.control_laws import CrossingLaw
    except ImportError as exc:
        print(f'--feature-level: the feature-level simulation is not available ({exc})',
              file=sys.stderr)
        return 2
    import yaml
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    with open(opts.params_file or graph.default_params_file(), encoding='utf-8') as f:
        params = yaml.safe_load(f) or {}

    ctrl, sup = controller_config(params), supervisor_config(params)   # as the nodes build them
    xi0 = opts.initial_position or tuple(world.initial_position_I)
    law = CrossingLaw(opts.crossing_law) if opts.crossing_law else ctrl.crossing_law
    wind = np.asarray(opts.wind or (0.0, 0.0, 0.0), dtype=float) / vehicle.mass
    cfg = feature_sim.FeatureSimConfig(initial_position_I=np.asarray(xi0, dtype=float),
                                       initial_yaw=world.initial_yaw, wind_accel_I=wind,
                                       crossing_law=law, max_time_s=MAX_SIM_TIME_S)
    t0 = time.monotonic()
    summary, flog = feature_sim.run_feature_scenario(world, pad, vehicle, ctrl, sup, cfg)
    summary = dict(summary, run=run_block(opts, xi0, wall_time_s=time.monotonic() - t0,
                                          stop_reason='feature-level run ended'))
    return finish(opts, summary, feature_run_data(flog, world, pad))


def feature_run_data(flog: FeatureSimLog, world: WorldConfig, pad: PadLayout
                     ) -> plots.RunData:
    """Convert ibvs_sim's FeatureSimLog into the plots' RunData."""
    log = report.RunLog()
    t, xi, v = flog.truth.arrays()
    for i in range(len(t)):
        log.add_truth(t[i], xi[i], v[i], np.full(3, np.nan), np.full(3, np.nan))
    for i, tc in enumerate(flog.t_ctrl):
        log.add_mode(tc, flog.mode[i])
        for name, seq in (('force', flog.F_I), ('q_w_bar', flog.q_w_bar), ('q_t', flog.q_t),
                          ('flow_down', flog.phi_t), ('flow_front', flog.phi_w)):
            value = seq[i]
            log.add_vector(name, tc, np.full(3, np.nan) if value is None else value)
    return report.run_data(log, world, pad)


# --- whole-graph run ------------------------------------------------------------------------

def onboard_vehicle_file(opts: RunOptions) -> str | None:
    """Return the onboard nodes' vehicle.yaml of a run (None: the installed file).

    ``--onboard-vehicle FILE``: that file (the calibration the graph flies with). With
    ``--camera-rate`` that file (or the installed one) with each camera's ``rate_hz`` set to
    the rate its camera runs at, written to ``results/<run>/vehicle_onboard.yaml``: the
    onboard configuration knows the rate the camera driver was configured with.
    """
    rates = opts.camera_model.get(CAMERA_RATE)
    if rates is None:
        return os.path.abspath(opts.onboard_vehicle) if opts.onboard_vehicle else None
    return write_vehicle_at_rates(opts.onboard_vehicle, rates,
                                  os.path.join(opts.out_dir, 'vehicle_onboard.yaml'),
                                  'run_scenario --camera-rate')


def write_vehicle_at_rates(source: str | None, rates, path: str, why: str) -> str:
    """Write ``source`` (None: the installed vehicle.yaml) with the cameras' ``rate_hz``.

    ``rates``: (front, down) in Hz. Returns the absolute path written.
    """
    import yaml
    from ibvs_common.core.config import default_config_path
    source = source or default_config_path('vehicle.yaml')
    with open(source, encoding='utf-8') as f:
        data = yaml.safe_load(f)
    for name, rate in zip(CAMERA_NAMES, rates):
        data['cameras'][name]['rate_hz'] = float(rate)
    path = os.path.abspath(path)
    with open(path, 'w', encoding='utf-8') as f:
        f.write(f'# {os.path.basename(source)} with the cameras at {list(rates)} Hz ({why})\n')
        yaml.safe_dump(data, f, sort_keys=False)
    return path


def camera_block(opts: RunOptions, onboard_vehicle: str | None) -> dict:
    """Return the camera model of a run as summary.json's ``run.camera`` reports it."""
    from dataclasses import asdict
    from ibvs_sim.config import SimNodeConfig
    c = asdict(SimNodeConfig()) | opts.camera_model          # the sim's defaults, the options
    return {'latency_ms': 1e3 * c['camera_latency_s'], 'jitter_ms': 1e3 * c['camera_jitter_s'],
            'jitter_distribution': c['camera_jitter_distribution'],
            'drop_probability': c['camera_drop_probability'],
            'rate_hz': (list(opts.camera_model[CAMERA_RATE]) if CAMERA_RATE in opts.camera_model
                        else 'vehicle.yaml'),
            'exposure_ms': 1e3 * c['camera_exposure_s'],
            'exposure_samples': c['camera_exposure_samples'], 'stamp_at': c['camera_stamp_at'],
            'true_vehicle': opts.true_vehicle or 'as onboard',
            'onboard_vehicle': onboard_vehicle or 'vehicle.yaml'}


def graph_specs(opts: RunOptions, port: int, initial_position: tuple,
                onboard_vehicle: str | None = None, firmware_instance: int | None = None) -> list:
    """Return the node specs of a run: the sim graph plus the recorder.

    ``onboard_vehicle``: the onboard nodes' vehicle YAML (None: params.yaml's);
    ``firmware_instance``: a real firmware flies the sim's plant (``--autopilot px4`` or
    ``ardupilot``), this instance of it.
    """
    camera = [(k, list(v) if isinstance(v, tuple) else v) for k, v in opts.camera_model.items()]
    if firmware_instance is not None:
        camera += [('firmware', opts.autopilot), ('firmware_instance', int(firmware_instance))]
    bridge, start_at = (), START_AT_SIM_S
    if opts.pilot_switch:       # the simulated pilot flips the RC switch (fly(), below)
        camera += [('pilot_switch_channel', PILOT_SWITCH_CHANNEL),
                   ('pilot_switch_on_s', -1.0)]
        bridge, start_at = (('pilot_switch_channel', PILOT_SWITCH_CHANNEL),), -1.0
        if opts.pilot_switch_off_s is not None:
            camera.append(('pilot_switch_off_s', float(opts.pilot_switch_off_s)))
    if opts.true_vehicle:
        camera.append(('true_vehicle_file', os.path.abspath(opts.true_vehicle)))
    gopts = graph.GraphOptions(params_file=opts.params_file, use_sim_time=True,
                               mavlink_port=port, initial_position=initial_position,
                               wind=opts.wind, crossing_law=opts.crossing_law,
                               auto_start_at_s=start_at, bridge_overrides=bridge,
                               real_time_factor=opts.real_time_factor,
                               sim_overrides=tuple(
                                   [(f'fault_{cam}_camera_off_s', list(w))
                                    for cam, w in opts.camera_off.items()]
                                   + [(f'fault_{cam}_camera_freeze_s', list(w))
                                      for cam, w in opts.camera_freeze.items()]
                                   + [(f'fault_imu_{kind}_s', list(w)) for kind, w in (
                                       ('off', opts.imu_off), ('nan', opts.imu_nan)) if w]
                                   + camera),
                               vehicle_file=onboard_vehicle,
                               extra_image_subscribers=1 if opts.bag else 0,
                               extra_imu_subscribers=1 if opts.bag else 0)
    specs = graph.sim_graph(gopts)
    if opts.bag:
        specs.append(graph.tool_node('recorder', 'recorder', ({
            'use_sim_time': True, 'bag_path': os.path.abspath(os.path.join(opts.out_dir, 'bag')),
            'image_every': int(opts.image_every)},)))
    return specs


class _Stop(Exception):
    pass


#: s of sim time after a FAILSAFE that --follow-failsafe waits for the autopilot to land and
#: disarm (a land mode descends at 0.4-0.5 m/s from at most ~2 m, then its land detector)
FOLLOW_FAILSAFE_S = 20.0
START_WAIT_S = 20.0    # s of wall clock after START_AT_SIM_S for the supervisor to start
# The supervisor starts by itself at the first frame at or after this sim time (graph option
# auto_start_at_s), so that every run starts at the same frame: an ibvs/start call lands at
# a frame that depends on the machine's load, and lockstep runs would not repeat.
START_AT_SIM_S = 1.0
#: --pilot-switch: the RC channel of the mission switch (the sim's radio and the bridge)
PILOT_SWITCH_CHANNEL = 7


def flip_pilot_switch(monitor: ScenarioMonitor, spin, deadline: float) -> None:
    """Flip the mission switch ON as the pilot, after the preflight's go (``--pilot-switch``).

    As a pilot looks at the switch before flipping it, this waits until the bridge has read
    it OFF (``ibvs/pilot_input``): a switch ON that the graph never saw OFF starts nothing.
    """
    from std_msgs.msg import Bool
    while PilotInput.OFF not in monitor.pilot_inputs:
        if time.monotonic() > deadline:
            raise _Stop("the bridge never read the pilot's switch OFF (ibvs/pilot_input; see "
                        'logs/mavlink_bridge.log)')
        spin(0.02)
    monitor.pilot_switch.publish(Bool(data=True))
    print(f"the pilot's switch ON at sim t = {monitor.now_s():.2f} s", flush=True)


#: ``--autopilot`` values whose firmware flies the plant in lockstep (a pre-roll before frame 0)
LOCKSTEP_FIRMWARES = ('px4', 'ardupilot')
#: s (wall): the longest wait for a firmware's pre-roll (boot, take-off, hold at the start).
#: The sim itself fails the pre-roll after 120 s of plant time; this only bounds a lockstep
#: far slower than real time
PREROLL_WAIT_S = 600.0


def bridge_engaged(monitor: ScenarioMonitor) -> bool:
    """Whether the bridge's latest /diagnostics says the autopilot flies its setpoints.

    'engaged': the autopilot's HEARTBEAT showed the offboard mode (PX4 OFFBOARD, ArduCopter
    GUIDED_NOGPS) it was asked for; the firmware's offboard-loss failsafe applies from then on.
    """
    return bool(monitor.bridge_history) \
        and monitor.bridge_history[-1].get('engage_state') == EngageState.ENGAGED.value


def autopilot_disarmed(monitor: ScenarioMonitor) -> bool:
    """Whether the autopilot is disarmed, in the sim's word where it has one.

    The sim's: the vehicle's own HEARTBEAT or state (``sim/stats``); else the bridge's
    (/diagnostics, stale once the bridge died: ``--kill-node mavlink_bridge``).
    """
    armed = monitor.sim_stats.get('autopilot_armed')
    if armed is not None:
        return not armed
    return monitor.health.armed is False


def wait_for_preroll(monitor: ScenarioMonitor, spin) -> None:
    """Wait for the sim's first frame, which comes once the firmware holds at the start.

    The preflight's wall-clock limit counts from then: a pre-roll that took long (PX4 in
    gusts, not still enough for the start pilot: 137 s of plant time) is not a preflight
    that failed. A pre-roll that fails (the sim logs it: "firmware: pre-roll: ...") ends
    here after ``PREROLL_WAIT_S``, or at the run's own wall-clock limit (``spin``).
    """
    deadline = time.monotonic() + PREROLL_WAIT_S
    while monitor.first_truth_wall is None:
        if time.monotonic() > deadline:
            raise _Stop(f'the firmware did not hold at the start within {PREROLL_WAIT_S:.0f} '
                        's of wall time (logs/sim.log: "frame 0 waits for the firmware")')
        spin(0.05)


def fly(opts: RunOptions, monitor: ScenarioMonitor, runner: ProcessRunner, t_wall0: float,
        runner_specs: list, restarts: list, executor: Executor) -> str:
    """Preflight, start, watch; return the stop reason (raise _Stop on a run error).

    As on a vehicle, a perception node that dies is restarted (runner.supervise) and the run
    goes on (``restarts`` lists what happened); any other death stops the run. ``executor``:
    the one the monitor was added to.
    """
    killed: list = []
    from ibvs_bringup.preflight import format_checklist

    respawning = {s.name for s in runner_specs if s.respawn}

    def spin(dt: float) -> None:
        executor.spin_once(timeout_sec=dt)
        if opts.kill_node and not killed and monitor.now_s() >= opts.kill_at_s \
                and (bridge_engaged(monitor) or not opts.kill_once_engaged):
            killed.append(runner.kill(opts.kill_node))
            print(f'fault injected: {opts.kill_node} killed at sim t = {monitor.now_s():.2f} s',
                  flush=True)
        for event in runner.supervise():
            print(f'runner: {event}', flush=True)
            restarts.append(f't = {monitor.now_s():.2f} s: {event.splitlines()[0]}')
            expected = opts.follow_failsafe and any(f"'{n}'" in event for n in killed)
            if 'died' in event and not expected \
                    and not any(f"'{n}'" in event for n in respawning):
                raise _Stop(event)
        if time.monotonic() - t_wall0 > opts.timeout_s:
            raise _Stop(f'wall-clock timeout {opts.timeout_s:.0f} s')

    if opts.autopilot in LOCKSTEP_FIRMWARES:
        wait_for_preroll(monitor, spin)
    deadline = time.monotonic() + opts.preflight_timeout_s
    while not monitor.health.healthy() and time.monotonic() < deadline:
        spin(0.05)
    print('preflight:\n' + format_checklist(monitor.health.checklist()), flush=True)
    if not monitor.health.healthy():
        raise _Stop(f'preflight failed after {opts.preflight_timeout_s:.0f} s')
    monitor.health.stop_preflight_only()      # imu/data, camera_info, window: not needed now
    # The supervisor starts by itself at START_AT_SIM_S (it retries at each frame while its
    # inputs settle); a run that has not started START_WAIT_S of wall clock later is stopped.
    while monitor.now_s() < START_AT_SIM_S:
        spin(0.01)
    start_deadline = time.monotonic() + START_WAIT_S
    if opts.pilot_switch:
        flip_pilot_switch(monitor, spin, start_deadline)
    while monitor.log.mode in (None, IDLE_MODE):
        if time.monotonic() > start_deadline:
            raise _Stop(f'the supervisor did not start by itself at sim t = '
                        f'{START_AT_SIM_S:.2f} s (see logs/mode_supervisor.log)'
                        if not opts.pilot_switch else
                        "the pilot's switch ON did not start the supervisor (see "
                        'logs/mavlink_bridge.log and logs/mode_supervisor.log)')
        spin(0.02)
    t_start = monitor.now_s()
    how = ("by the pilot's switch" if opts.pilot_switch
           else f'by the supervisor at sim t = {START_AT_SIM_S:.2f} s')
    print(f'started {how} (seen at {t_start:.2f} s)', flush=True)
    next_print = time.monotonic()
    failsafe_at = None
    while True:
        spin(0.02)
        t_sim = monitor.now_s()
        mode = monitor.log.mode
        if time.monotonic() >= next_print:
            next_print += 1.0
            xi = monitor.log.xi[-1] if monitor.log.xi else np.full(3, np.nan)
            print(f'  t = {t_sim:6.2f} s  mode {mode_name(mode)}  xi_I = '
                  f'({xi[0]:+.2f}, {xi[1]:+.2f}, {xi[2]:+.2f})', flush=True)
        if monitor.collision is not None:
            return f"collision with {monitor.collision.get('surface')}"
        if mode == FAILSAFE_MODE:
            if not opts.follow_failsafe:
                return 'failsafe'
            failsafe_at = t_sim if failsafe_at is None else failsafe_at
            if monitor.touchdown is not None and autopilot_disarmed(monitor):
                return 'failsafe, then the autopilot landed and disarmed'
            if t_sim - failsafe_at > FOLLOW_FAILSAFE_S:
                return (f'failsafe, and the autopilot had not landed and disarmed '
                        f'{FOLLOW_FAILSAFE_S:g} s later')
            continue
        if monitor.touchdown is not None and mode == SHUTDOWN_MODE:
            if monitor.health.armed is False:
                return 'touchdown, mode 4, disarmed'
            td_t = float(monitor.touchdown.get('t', t_sim))
            if t_sim - td_t > SHUTDOWN_GRACE_S:
                return 'touchdown, mode 4 (no disarm report)'
        if t_sim - t_start > opts.max_sim_time_s:
            return f'{opts.max_sim_time_s:g} s of sim time'


def flight_timing(monitor: ScenarioMonitor | None, wall_end: float) -> dict:
    """Return the run's real-time factor: sim time over wall time since frame 0 (summary.json).

    ``wall_s``: steady clock from the first ground truth (frame 0, sim t = 0) reaching the
    monitor to ``wall_end`` (the end of the flight: the stop decision, before the graph is
    stopped), so process start-up and preflight discovery are not counted; ``flight_sim_s``:
    the monitor's sim time then; ``sim_over_wall``: their ratio. Empty before frame 0.
    """
    start = getattr(monitor, 'first_truth_wall', None)
    if start is None or wall_end <= start:
        return {}
    sim_s, wall_s = monitor.now_s(), wall_end - start
    return {'flight_sim_s': round(sim_s, 3), 'wall_s': round(wall_s, 3),
            'sim_over_wall': round(sim_s / wall_s, 4)}


def run_graph(opts: RunOptions) -> int:
    """Fly the whole graph once; write results/<run>/."""
    import rclpy
    from ibvs_harness.monitor_node import close_monitor, ScenarioMonitor
    from ibvs_common.spin import make_executor
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    xi0 = opts.initial_position or tuple(float(x) for x in world.initial_position_I)
    port = opts.mavlink_port or free_udp_port()
    onboard_vehicle = onboard_vehicle_file(opts)
    px4 = lockstep_firmware(opts, world, vehicle, xi0)
    specs = graph_specs(opts, port, xi0, onboard_vehicle,
                        None if px4 is None else px4.instance)
    missing = missing_executables(specs)
    if missing:
        summary = report.summarize(report.RunLog(), world, 0.0, 0.0)
        summary['run'] = run_block(opts, xi0, error='nodes missing: ' + '; '.join(missing),
                                   camera=camera_block(opts, onboard_vehicle))
        print('cannot fly: ' + '; '.join(missing), file=sys.stderr)
        return finish(opts, summary, None)
    t_wall0 = time.monotonic()
    runner = ProcessRunner(log_dir=os.path.join(opts.out_dir, 'logs'))
    # our own SIGINT/SIGTERM handling (KeyboardInterrupt / Terminated): rclpy must not shut
    # its context down under us before the graph is stopped and the log drained
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    monitor = executor = None
    stop_reason, error = None, None
    restarts: list = []
    try:
        monitor = ScenarioMonitor()
        if onboard_vehicle is not None:     # the preflight's rate check: the rates configured
            monitor.health.rates_hz = {cam: c.rate_hz for cam, c in
                                       load_vehicle(onboard_vehicle).cameras.items()}
        # the graph's own executor (C++ events executor): the monitor takes ~550 messages/s,
        # and rclpy's Python wait set cost it 15-25 % of a core, taken from the graph
        executor = make_executor(monitor.context)
        executor.add_node(monitor)
        runner.start_layout(specs, opts.layout)
        print(f'run {opts.run_name}: started {len(specs)} nodes (MAVLink port {port}), '
              f'initial position {xi0}', flush=True)
        if px4 is not None:     # after the sim, whose port the firmware connects to
            wait_for_port(px4, runner)
            env = px4.start()
            print(f'run {opts.run_name}: {firmware_name(opts)} instance {px4.instance} flies '
                  f'the plant in lockstep ({env.get("PX4_WORKDIR") or env.get("AP_WORKDIR")})',
                  flush=True)
        stop_reason = fly(opts, monitor, runner, t_wall0, specs, restarts, executor)
    except _Stop as exc:
        error = str(exc)
    except RuntimeError as exc:           # the firmware did not start
        error = str(exc)
    except (KeyboardInterrupt, Terminated, ExternalShutdownException):
        error = 'interrupted'
    finally:
        flight = flight_timing(monitor, time.monotonic())
        codes = runner.stop()
        log, sim_stats, bridge = close_monitor(monitor, executor)
        rclpy.try_shutdown()
        if px4 is not None:
            if error:
                print('firmware log tail:\n' + px4.log_tail(), flush=True)
            px4.stop()
    print(f'stopped: {stop_reason or error} (exit codes {codes})', flush=True)
    summary = report.summarize(log, world, vehicle.envelope_radius, vehicle.envelope_height)
    summary['timing'] = {**sim_stats, **flight}
    summary['bridge'] = bridge        # the bridge's /diagnostics, once a second (sim time t)
    summary['run'] = run_block(opts, xi0, stop_reason=stop_reason, error=error,
                               wall_time_s=time.monotonic() - t_wall0, mavlink_port=port,
                               node_restarts=restarts,
                               camera=camera_block(opts, onboard_vehicle),
                               events=log.events,
                               transitions=supervisor_transitions(supervisor_log(opts.out_dir)),
                               **firmware_block(px4))
    return finish(opts, summary, report.run_data(log, world, pad) if log.t else None)


def firmware_block(px4) -> dict:
    """Return summary.json's firmware keys of a run on a real firmware (none for the sim's)."""
    if px4 is None:
        return {}
    from ibvs_harness.ardupilot_sitl import ARDUPILOT_FIRMWARE, ArduPilotSitl
    if isinstance(px4, ArduPilotSitl):
        return {'autopilot': 'ardupilot', 'firmware': ARDUPILOT_FIRMWARE,
                'ardupilot_instance': px4.instance, 'ardupilot_parameters': px4.params}
    return {'autopilot': 'px4', 'firmware': PX4_FIRMWARE, 'px4_instance': px4.instance,
            'px4_parameters': px4.params}


PX4_FIRMWARE = 'PX4 v1.16.0 SITL (px4-hil: simulator_mavlink, lockstep)'


def firmware_name(opts: RunOptions) -> str:
    """Return the firmware of ``--autopilot px4|ardupilot`` in words."""
    return ('ArduCopter 4.5.6 SITL (JSON backend)' if opts.autopilot == 'ardupilot'
            else 'PX4 v1.16 SITL (px4-hil)')


def lockstep_firmware(opts: RunOptions, world, vehicle, xi0: tuple):
    """Return the firmware (not started) of ``--autopilot px4|ardupilot``; None for the others."""
    if opts.autopilot == 'px4':
        return firmware_px4(opts, world, vehicle, xi0)
    if opts.autopilot == 'ardupilot':
        return firmware_ardupilot(opts, vehicle)
    return None


def firmware_ardupilot(opts: RunOptions, vehicle):
    """Return ArduCopter SITL (JSON backend, not started) with the Pelican's parameters.

    The plant starts on the floor below the start; the sim's start pilot takes off to it in
    GUIDED before frame 0. The dead-bridge failsafe (GCS failsafe on the bridge's system id:
    LAND) is set as docs/mavlink.md asks of a user.
    """
    from ibvs_common.core.params import node_values
    from ibvs_control.mavlink.config import MavlinkBridgeNodeConfig
    from ibvs_harness.ardupilot_sitl import (ardupilot_mission_parameters, ArduPilotSitl,
                                             free_instance)
    import yaml
    with open(opts.params_file or graph.default_params_file(), encoding='utf-8') as f:
        bridge = node_values(MavlinkBridgeNodeConfig, yaml.safe_load(f), 'mavlink_bridge')
    params = ardupilot_mission_parameters(vehicle, int(bridge['source_system']))
    instance = opts.px4_instance if opts.px4_instance is not None else free_instance()
    return ArduPilotSitl(instance, params)


#: s (steady): the sim node binds the firmware's port (ArduPilot's JSON port) within this
FIRMWARE_PORT_WAIT_S = 60.0


def wait_for_port(firmware, runner) -> None:
    """ArduPilot: wait until the sim bound its JSON port (its first packet must find it).

    PX4 connects to the sim's TCP server and retries by itself; ArduPilot sends its servo
    packets to a UDP port and re-sends a lost one only after 10 s.
    """
    from ibvs_harness.ardupilot_sitl import ArduPilotSitl
    from ibvs_sim.core.firmware.ardupilot_json import JSON_PORT_BASE
    if not isinstance(firmware, ArduPilotSitl):
        return
    port = JSON_PORT_BASE + 10 * int(firmware.instance)
    t0 = time.monotonic()
    while time.monotonic() - t0 < FIRMWARE_PORT_WAIT_S:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(('127.0.0.1', port))
            except OSError:
                return                  # the sim holds it
        time.sleep(0.2)
    raise RuntimeError(f'the sim did not bind the ArduPilot JSON port {port} within '
                       f'{FIRMWARE_PORT_WAIT_S:.0f} s')


def firmware_px4(opts: RunOptions, world, vehicle, xi0: tuple):
    """Return PX4 SITL (px4-hil, not started) with the Pelican's parameters for this start.

    The sim's plant starts on the floor below the start; PX4 takes off to it by itself
    (MIS_TAKEOFF_ALT) before frame 0. Its offboard-loss failsafe: land (COM_OBL_RC_ACT 4)
    after COM_OF_LOSS_T 1 s, as the bridge expects (docs/mavlink.md).
    """
    from ibvs_harness.px4_sih import free_instance, Px4Sitl
    from ibvs_sim.core.firmware.lockstep import takeoff_altitude
    from ibvs_sim.core.firmware.px4_hil import px4_hil_parameters
    params = {**px4_hil_parameters(vehicle),
              'MIS_TAKEOFF_ALT': round(takeoff_altitude(world, vehicle, xi0), 3),
              'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 4}
    instance = opts.px4_instance if opts.px4_instance is not None else free_instance()
    return Px4Sitl(instance, params, script='px4-hil')


def _flat(windows: list) -> tuple:
    """(start, end) pairs of a repeated option -> the flat start, end, start, end, ..."""
    return tuple(x for pair in windows for x in pair)


def camera_model(a: argparse.Namespace) -> dict:
    """Return the sim parameters of the camera options given (ms -> s); ValueError if bad."""
    out: dict = {}
    for option, key, scale in (('camera_latency', 'camera_latency_s', 1e-3),
                               ('camera_jitter', 'camera_jitter_s', 1e-3),
                               ('camera_exposure', 'camera_exposure_s', 1e-3)):
        value = getattr(a, option)
        if value is not None:
            if not (np.isfinite(value) and 0.0 <= value <= 1000.0):
                raise ValueError(f'--{option.replace("_", "-")} must be in [0, 1000] ms, got '
                                 f'{value}')
            out[key] = float(value) * scale
    if a.camera_drop is not None:
        if not 0.0 <= a.camera_drop < 1.0:
            raise ValueError(f'--camera-drop must be in [0, 1), got {a.camera_drop}')
        out['camera_drop_probability'] = float(a.camera_drop)
    if a.camera_rate is not None:
        rates = a.camera_rate * 2 if len(a.camera_rate) == 1 else a.camera_rate
        if len(rates) != 2 or not all(0.0 < r <= 1000.0 for r in rates):
            raise ValueError(f'--camera-rate takes one rate or FRONT DOWN, each in (0, 1000] '
                             f'Hz, got {a.camera_rate}')
        out[CAMERA_RATE] = tuple(float(r) for r in rates)
    if a.camera_exposure_samples is not None:
        if not 1 <= a.camera_exposure_samples <= 64:
            raise ValueError('--camera-exposure-samples must be in 1 ... 64')
        out['camera_exposure_samples'] = int(a.camera_exposure_samples)
    for option in ('camera_jitter_distribution', 'camera_stamp_at'):
        if getattr(a, option) is not None:
            out[option] = getattr(a, option)
    return out


def parse_args(argv: list | None = None) -> RunOptions:
    """Parse the command line into RunOptions."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--run-name', default=None, help='results/<run-name>/ (default: derived)')
    p.add_argument('--results-root', default='results')
    ic = p.add_mutually_exclusive_group()
    ic.add_argument('--initial-position', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                    help='paper frame {I}, m (default: world.yaml, the paper\'s)')
    ic.add_argument('--random-ic', type=int, metavar='SEED',
                    help='draw the initial position from the SPEC box with this seed')
    p.add_argument('--wind', type=float, nargs=3, metavar=('FX', 'FY', 'FZ'),
                   help='constant wind force in {I}, N')
    p.add_argument('--crossing-law', choices=graph.CROSSING_LAWS)
    p.add_argument('--no-bag', action='store_true', help='do not record a bag')
    p.add_argument('--bag-image-every', type=int, default=DEFAULT_IMAGE_EVERY,
                   help='record every N-th camera frame (1: all)')
    p.add_argument('--no-plots', action='store_true')
    p.add_argument('--max-sim-time', type=float, default=MAX_SIM_TIME_S, metavar='S',
                   help='stop S s of sim time after the start (default: docs/spec.md\'s 60; a '
                        'shorter flight fails the criteria: benchmarks, smoke runs)')
    p.add_argument('--feature-level', action='store_true',
                   help="fly ibvs_sim's feature-level closed loop (no images, no ROS)")
    p.add_argument('--timeout', type=float, default=900.0, help='wall-clock limit, s')
    p.add_argument('--preflight-timeout', type=float, default=120.0)
    p.add_argument('--mavlink-port', type=int, default=None,
                   help='default: a free UDP port in 6100-6899 (free_udp_port)')
    p.add_argument('--params-file', default=None)
    p.add_argument('--follow-failsafe', action='store_true',
                   help='after a FAILSAFE, go on until the autopilot (its land mode, to which '
                        'the bridge hands the vehicle) has put it down and disarmed, or '
                        f'{FOLLOW_FAILSAFE_S:g} s of sim time passed; the run still fails '
                        '(docs/firmware_lockstep.md "Fault tests")')
    p.add_argument('--kill-node', default=None, metavar='NAME',
                   help='fault injection: SIGKILL this node at --kill-at-s (sim time); '
                        'with --follow-failsafe its death does not stop the run (e.g. '
                        'mavlink_bridge: the autopilot\'s own failsafe lands the vehicle)')
    p.add_argument('--kill-at-s', type=float, default=2.0, metavar='T')
    p.add_argument('--kill-once-engaged', action='store_true',
                   help='with --kill-node: kill it at --kill-at-s or later, once the bridge '
                        'reports the autopilot flying its setpoints (engaged; its /diagnostics '
                        'come once a second of wall clock): a fault while the firmware flies '
                        'the graph, not in the switch to its offboard mode')
    for cam in ('front', 'down'):
        p.add_argument(f'--{cam}-camera-off', type=float, nargs=2, metavar=('START', 'END'),
                       action='append',
                       help=f'fault injection: no {cam} images in this sim-time window (s); '
                            'repeat the option for several windows')
        p.add_argument(f'--{cam}-camera-freeze', type=float, nargs=2, metavar=('START', 'END'),
                       action='append',
                       help=f'fault injection: in this sim-time window (s) the {cam} camera '
                            f're-publishes its image of START with new stamps (a hung driver); '
                            'repeat the option for several windows')
    p.add_argument('--imu-off', type=float, nargs=2, metavar=('START', 'END'),
                   help='fault injection: the autopilot sends no attitude/IMU in this sim-time '
                        'window (s)')
    p.add_argument('--imu-nan', type=float, nargs=2, metavar=('START', 'END'),
                   help='fault injection: the autopilot sends attitude/IMU full of NaN in this '
                        'sim-time window (s)')
    p.add_argument('--real-time-factor', type=float, default=None, metavar='RTF',
                   help='free-running sim (not lockstep): sim time runs at RTF x the wall '
                        'clock, frames it cannot render on time are dropped (e.g. 0.25)')
    cam = p.add_argument_group(
        'camera model', 'the sim\'s cameras like real ones (lockstep too: a late image is '
        'computed late in sim time; docs/sim.md "Camera model"); times in ms of sim time')
    cam.add_argument('--camera-latency', type=float, metavar='MS',
                     help='an image is published MS after the instant its stamp refers to')
    cam.add_argument('--camera-jitter', type=float, metavar='MS',
                     help='delivery jitter: uniform in +-MS (or the standard deviation, '
                          '--camera-jitter-distribution normal), seeded')
    cam.add_argument('--camera-jitter-distribution', choices=('uniform', 'normal'))
    cam.add_argument('--camera-drop', type=float, metavar='P',
                     help='each camera loses each frame with probability P (seeded)')
    cam.add_argument('--camera-rate', type=float, nargs='+', metavar='HZ',
                     help='frame rate of both cameras, or FRONT DOWN (e.g. 30); the onboard '
                          'nodes get a vehicle.yaml with these rates (results/<run>/'
                          'vehicle_onboard.yaml)')
    cam.add_argument('--camera-exposure', type=float, metavar='MS',
                     help='exposure time: motion blur, averaging renders over it')
    cam.add_argument('--camera-exposure-samples', type=int, metavar='N',
                     help='renders averaged over an exposure (the render cost, times N)')
    cam.add_argument('--camera-stamp-at', choices=('start', 'mid', 'end'),
                     help='the instant of the exposure a stamp refers to (default mid)')
    cam.add_argument('--true-vehicle', metavar='FILE',
                     help='the vehicle YAML the sim flies and renders (mounts, lever arms, '
                          'intrinsics, time offsets), the onboard nodes keep theirs: a '
                          'calibration error')
    cam.add_argument('--onboard-vehicle', metavar='FILE',
                     help='the vehicle YAML the onboard nodes are calibrated with (default: '
                          'the installed vehicle.yaml); the sim publishes its camera_info')
    p.add_argument('--autopilot', choices=AUTOPILOTS, default=AUTOPILOTS[0],
                   help="'sim': the simulator's plant and autopilot emulation (lockstep); "
                        "'px4-sih': PX4 SITL with SIH is plant and autopilot, real time on "
                        "the system clock, needs ../shared/px4-sitl (docs/px4_sih.md); 'px4': "
                        "PX4 v1.16 SITL (px4-hil) flies the sim's plant in lockstep, it takes "
                        "off to the start before frame 0; 'ardupilot': ArduCopter 4.5.6 SITL "
                        '(JSON backend) likewise, needs ../shared/ardupilot-sitl '
                        '(docs/firmware_lockstep.md)')
    p.add_argument('--layout', choices=LAYOUTS, default=None,
                   help="onboard nodes as one process per node ('processes', the default with "
                        "the sim), all in one process ('composed', ibvs_bringup.composed: the "
                        'onboard default, and the default with px4-sih, which runs in real '
                        "time), or a container per camera and one for control ('grouped'); "
                        'the sim, monitor and recorder run beside them in every layout')
    p.add_argument('--px4-instance', type=int, default=None, choices=range(10),
                   metavar='I', help='px4-sih, px4, ardupilot: the firmware instance 0-9 '
                   '(default: a free one, PX4 >= 5, ArduPilot 1-4)')
    p.add_argument('--px4-flight-s', type=float, default=None, metavar='S',
                   help='px4-sih: stop S s (system clock) after ibvs/start (default 60, as a '
                        'sim run)')
    p.add_argument('--pilot-switch', action='store_true',
                   help="the mission starts from the pilot's radio, not by itself: the "
                        'autopilot (the emulated one, or PX4 in lockstep) gets RC input from '
                        'the sim, whose pilot flips a mission switch ON once the preflight '
                        f'passed, from {START_AT_SIM_S:g} s of sim time on, and the bridge '
                        'read it OFF (sim/pilot_switch); the bridge reads it (RC_CHANNELS, '
                        f'pilot_switch_channel {PILOT_SWITCH_CHANNEL}) and the supervisor starts '
                        '(docs/onboard.md "Start and abort from the radio")')
    p.add_argument('--pilot-switch-off-at', type=float, default=None, metavar='S',
                   help='with --pilot-switch: the pilot flips the switch OFF at S s of sim '
                        'time, an abort (FAILSAFE: the autopilot lands)')
    p.add_argument('--px4-no-mocap', action='store_true',
                   help="px4-sih: PX4's estimator on SIH's GPS, baro and magnetometer instead "
                        'of the motion capture of params.yaml px4_sim mocap_rate_hz')
    a = p.parse_args(argv)
    try:
        model = camera_model(a)
    except ValueError as exc:
        p.error(str(exc))
    xi0 = tuple(a.initial_position) if a.initial_position else None
    extra = {}
    if a.random_ic is not None:
        xi0 = random_initial_position(a.random_ic)
        extra['random_ic_seed'] = a.random_ic
    name = a.run_name or ('feature-' if a.feature_level else '') + (
        f'random-{a.random_ic}' if a.random_ic is not None else
        'ic_' + '_'.join(f'{x:+.2f}' for x in xi0) if xi0 else 'reference')
    return RunOptions(run_name=name, results_root=a.results_root, initial_position=xi0,
                      camera_model=model, true_vehicle=a.true_vehicle,
                      onboard_vehicle=a.onboard_vehicle,
                      wind=tuple(a.wind) if a.wind else None, crossing_law=a.crossing_law,
                      bag=not a.no_bag, image_every=max(1, a.bag_image_every),
                      feature_level=a.feature_level, timeout_s=a.timeout,
                      preflight_timeout_s=a.preflight_timeout, mavlink_port=a.mavlink_port,
                      params_file=a.params_file, plots=not a.no_plots, extra=extra,
                      real_time_factor=a.real_time_factor, kill_node=a.kill_node,
                      kill_at_s=a.kill_at_s, kill_once_engaged=a.kill_once_engaged,
                      camera_off={cam: _flat(w) for cam, w in (
                          ('front', a.front_camera_off), ('down', a.down_camera_off)) if w},
                      camera_freeze={cam: _flat(w) for cam, w in (
                          ('front', a.front_camera_freeze), ('down', a.down_camera_freeze))
                          if w},
                      imu_off=tuple(a.imu_off) if a.imu_off else None,
                      imu_nan=tuple(a.imu_nan) if a.imu_nan else None,
                      max_sim_time_s=a.max_sim_time, follow_failsafe=a.follow_failsafe,
                      autopilot=a.autopilot, px4_instance=a.px4_instance,
                      px4_flight_s=a.px4_flight_s, px4_no_mocap=a.px4_no_mocap,
                      pilot_switch=a.pilot_switch, pilot_switch_off_s=a.pilot_switch_off_at,
                      layout=a.layout or DEFAULT_LAYOUT['onboard' if a.autopilot == 'px4-sih'
                                                        else 'sim'])


def main(argv: list | None = None) -> int:
    """Run one scenario from the command line; return the exit code."""
    opts = parse_args(argv)
    graph.ensure_ament_prefix_path()
    try:
        graph.checked_params_file(opts.params_file, graph.SIM_NODE_NAMES)
        if not opts.max_sim_time_s > 0.0:
            raise ValueError(f'--max-sim-time must be > 0, got {opts.max_sim_time_s}')
        if opts.kill_once_engaged and not opts.kill_node:
            raise ValueError('--kill-once-engaged needs --kill-node')
        if opts.kill_node and opts.layout != 'processes':
            raise ValueError('--kill-node kills one node process: it needs --layout processes')
        if opts.autopilot in ('px4', 'ardupilot') and opts.feature_level:
            raise ValueError(f'--autopilot {opts.autopilot} flies the graph: not with '
                             '--feature-level')
        if opts.pilot_switch_off_s is not None and not (
                opts.pilot_switch and opts.pilot_switch_off_s > START_AT_SIM_S):
            raise ValueError(f'--pilot-switch-off-at needs --pilot-switch and a time after the '
                             f'start ({START_AT_SIM_S:g} s)')
        if opts.pilot_switch and opts.autopilot not in ('sim', 'px4'):
            raise ValueError('--pilot-switch needs the sim: its radio is the RC input of the '
                             'emulated autopilot or of PX4 in lockstep')
        if (opts.camera_model or opts.true_vehicle or opts.onboard_vehicle) and (
                opts.feature_level or opts.autopilot == 'px4-sih'):
            raise ValueError('the camera model options are the sim node\'s: not with '
                             '--feature-level or --autopilot px4-sih')
        for option, path in (('--true-vehicle', opts.true_vehicle),
                             ('--onboard-vehicle', opts.onboard_vehicle)):
            if path and not os.path.isfile(path):
                raise ValueError(f'{option} {path}: no such file')
        prepare_out_dir(opts)
    except (ValueError, OSError) as exc:
        print(f'run_scenario: {exc}', file=sys.stderr)
        return 2
    raise_on_sigterm()
    if opts.autopilot == 'px4-sih' and not opts.feature_level:
        from ibvs_harness.px4_scenario import run_px4_sih
        return run_px4_sih(opts)
    return run_feature_level(opts) if opts.feature_level else run_graph(opts)


if __name__ == '__main__':
    sys.exit(main())
