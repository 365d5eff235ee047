"""``run_scenario --autopilot px4-sih``: the whole graph flies the scenario on the real PX4.

PX4 v1.16 SITL with SIH is the plant and the autopilot (docs/px4_sih.md). Sequence, all on
the system clock (PX4 runs in real time; every node has use_sim_time false):

1. PX4 SIH starts with the Pelican's parameters (vehicle.yaml), the home ``px4_sim`` maps from
   and MIS_TAKEOFF_ALT = the start height above the take-off point
   (:mod:`ibvs_harness.px4_sih`);
2. the graph starts: ``px4_sim`` (cameras rendered from PX4's ground truth) and the onboard
   nodes with the shipped params.yaml, the bridge on PX4's companion port (udpin 14540 + i);
3. the harness, as the pilot's GCS, arms PX4 and commands its take-off; PX4 climbs and holds
   (AUTO.LOITER); the harness waits until the ground truth is still (``SETTLE_S``);
4. the preflight checks pass (window in view), the harness calls ``ibvs/start``; the
   supervisor leaves IDLE and the bridge engages OFFBOARD (the vehicle is already armed: the
   bridge never arms, nothing asked it to);
5. stop on touchdown + mode 4 (disarm), collision, failsafe, ``MAX_FLIGHT_S`` after the start
   or the wall timeout; PX4 is stopped whatever happens.

summary.json and the plots are written as for a sim run, from the start on (times in s since
ibvs/start); ``timing`` holds px4_sim's frames published / dropped and the image stamp ->
force setpoint latency, ``run`` the PX4 instance, its SIH parameters and the start pose
reached.
"""
from __future__ import annotations

import math
import os
import sys
import time
from typing import TYPE_CHECKING

import numpy as np

from ibvs_bringup import graph
from ibvs_harness import report
from ibvs_common.core.modes import mode_name
from ibvs_harness.scenario import (finish, missing_executables, run_block,
                                   supervisor_log, supervisor_transitions)
from ibvs_harness.px4_sih import (free_instance, MAV_CMD_DO_REPOSITION, Pilot,
                                  px4_boot_parameters, Px4Sitl, SITL_NICE)
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.px4_plant import find_px4_sitl, NedToI, sih_parameters
from ibvs_sim.core.world import load_world

if TYPE_CHECKING:
    from ibvs_harness.scenario import RunOptions

TAKEOFF_TIMEOUT_S = 60.0      # s (steady), PX4's take-off until it holds (AUTO.LOITER)
TAKEOFF_REACHED = 0.8          # PX4's altitude estimate at this fraction of MIS_TAKEOFF_ALT
GRAPH_UP_TIMEOUT_S = 60.0     # s (steady), ground truth must flow from px4_sim by then
START_WAIT_S = 20.0           # s (steady), ibvs/start retried (1 s apart) until accepted
MAX_FLIGHT_S = 60.0           # s (system clock) after ibvs/start
SHUTDOWN_GRACE_S = 8.0        # s after touchdown in mode 4 to wait for the disarm (PX4: ramp
#                               2 s, then its land detector)
FAILSAFE_MODE, SHUTDOWN_MODE, IDLE_MODE = 5, 4, 0
START_TOLERANCE_M = 0.5       # m, ground truth vs the scenario's start at ibvs/start
START_YAW_TOL_RAD = 0.05      # rad, true heading vs world.yaml's initial yaw
START_SPEED_TOL_MPS = 0.1     # m/s, true speed at ibvs/start (the scenario starts at rest)
REPOSITION_WAIT_S = 3.0       # s (steady), at least this long between DO_REPOSITION corrections
REPOSITION_STILL_S = 1.0      # s (steady) the truth must have been slower than
#                               START_SPEED_TOL_MPS before the next correction: one sent while
#                               PX4 still swings to the last hold point re-excites its loop
#                               (s17px4e2: +-1 m swings for 120 s, 33 repositions)
REPOSITION_MAX_WAIT_S = 10.0  # s (steady), a correction anyway after this long in motion


class _Stop(Exception):
    pass


def in_box(xi_I: np.ndarray, box: dict) -> bool:
    """Whether ``xi_I`` ({I}, m) lies in ``box`` ({'x': (lo, hi), 'y': ..., 'z': ...})."""
    return all(lo <= float(v) <= hi for v, (lo, hi) in zip(xi_I, (box[k] for k in 'xyz')))


def at_start(xi_I: np.ndarray, start_I: np.ndarray, yaw_err_rad: float, box: dict) -> bool:
    """Whether the ground truth ``xi_I`` ({I}, m) may start the scenario from ``start_I``.

    Within START_TOLERANCE_M of the start and START_YAW_TOL_RAD of its heading, and inside
    SPEC's box of random starts (world.yaml ``random_initial_box``: where the graph's success
    is measured) when the start itself is in it: 0.5 m around the reference start reaches
    y = +0.6, and a PX4 SIH mission started at y = +0.50 hit the window frame (s30px4b,
    docs/px4_sih.md).
    """
    xi, start = np.asarray(xi_I, dtype=float), np.asarray(start_I, dtype=float)
    return bool(np.linalg.norm(xi - start) < START_TOLERANCE_M
                and abs(yaw_err_rad) < START_YAW_TOL_RAD
                and (in_box(xi, box) or not in_box(start, box)))


def px4_sim_section(params_file: str | None) -> dict:
    """Return the ``px4_sim`` parameters as the node reads the params file.

    Its code defaults, then the file's ``/**`` block and ``px4_sim`` section (ValueError for a
    value the node would refuse).
    """
    import yaml
    from ibvs_common.core.params import node_values
    from ibvs_sim.config import Px4SimNodeConfig
    with open(params_file or graph.default_params_file(), encoding='utf-8') as f:
        data = yaml.safe_load(f) or {}
    return node_values(Px4SimNodeConfig, data, graph.PX4_SIM_NAME)


def _error_summary(opts, world, xi0, error: str) -> dict:
    summary = report.summarize(report.RunLog(), world, 0.0, 0.0)
    summary['run'] = run_block(opts, xi0, autopilot='px4-sih', error=error)
    return summary


def run_px4_sih(opts: RunOptions) -> int:
    """Fly the whole graph against PX4 SIH once; write results/<run>/ (exit code as run_graph)."""
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    xi0 = opts.initial_position or tuple(float(x) for x in world.initial_position_I)
    try:
        sitl_dir = find_px4_sitl()
    except FileNotFoundError as exc:
        print(f'--autopilot px4-sih: {exc}', file=sys.stderr)
        return finish(opts, _error_summary(opts, world, xi0, str(exc)), None)
    p = px4_sim_section(opts.params_file)
    home = (float(p['home_lat_deg']), float(p['home_lon_deg']), float(p['home_alt_m']))
    frame = NedToI.from_start(xi0, world.floor_z, float(p['rest_height_m']))
    sih = sih_parameters(vehicle)
    mocap_hz = 0.0 if opts.px4_no_mocap else float(p['mocap_rate_hz'])
    boot = px4_boot_parameters(sih, frame.takeoff_altitude(xi0), home, mocap=mocap_hz > 0.0)
    try:
        instance = opts.px4_instance if opts.px4_instance is not None else free_instance()
    except RuntimeError as exc:
        return finish(opts, _error_summary(opts, world, xi0, str(exc)), None)
    gopts = graph.GraphOptions(params_file=opts.params_file, use_sim_time=False,
                               initial_position=opts.initial_position,
                               crossing_law=opts.crossing_law,
                               extra_image_subscribers=1 if opts.bag else 0,
                               extra_imu_subscribers=1 if opts.bag else 0)
    specs = graph.px4_sih_graph(gopts, instance, {'home_lat_deg': home[0],
                                                  'home_lon_deg': home[1],
                                                  'home_alt_m': home[2],
                                                  'mocap_rate_hz': mocap_hz})
    if opts.bag:
        specs.append(graph.tool_node('recorder', 'recorder', ({
            'use_sim_time': False,
            'bag_path': os.path.abspath(os.path.join(opts.out_dir, 'bag')),
            'image_every': int(opts.image_every)},)))
    missing = missing_executables(specs)
    if missing:
        return finish(opts, _error_summary(opts, world, xi0,
                                           'nodes missing: ' + '; '.join(missing)), None)
    return _fly_px4(opts, world, pad, vehicle, xi0, sitl_dir, instance, boot, specs,
                    finish, run_block, frame)


def _fly_px4(opts, world, pad, vehicle, xi0, sitl_dir, instance, boot, specs, finish,
             run_block, frame: NedToI) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions
    from ibvs_harness.monitor_node import close_monitor, ScenarioMonitor
    from ibvs_bringup.runner import ProcessRunner, Terminated

    t_wall0 = time.monotonic()
    px4 = Px4Sitl(instance, boot, sitl_dir)
    runner = ProcessRunner(log_dir=os.path.join(opts.out_dir, 'logs'))
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    monitor = pilot = None
    stop_reason = error = None
    info: dict = {'px4_instance': instance, 'px4_parameters': boot,
                  'px4_estimator': 'mocap' if boot.get('EKF2_EV_CTRL') else 'gps'}
    codes = {}
    try:
        # the graph first: with motion capture, px4_sim relays it to PX4, whose EKF2 (GPS off)
        # has no position, and px4-sih start no "Ready for takeoff", before it comes
        monitor = ScenarioMonitor(use_sim_time=False)
        runner.start_layout(specs, opts.layout)
        t = time.monotonic()
        px4.start()
        info['px4_start_s'] = round(time.monotonic() - t, 2)
        info['px4_nice'] = px4.renice(SITL_NICE)
        print(f'run {opts.run_name}: PX4 SIH instance {instance} up in '
              f'{info["px4_start_s"]} s ({px4.env.get("PX4_WORKDIR")}), its estimator on '
              f'{info["px4_estimator"]}',
              flush=True)
        pilot = Pilot(instance)
        stop_reason = _flight(opts, monitor, runner, pilot, xi0, t_wall0, info,
                              {s.name for s in specs if s.respawn},
                              float(boot['MIS_TAKEOFF_ALT']), frame, world)
    except _Stop as exc:
        error = str(exc)
    except RuntimeError as exc:               # PX4 did not start
        error = str(exc)
    except (KeyboardInterrupt, Terminated, ExternalShutdownException):
        error = 'interrupted'
    finally:
        codes = runner.stop()
        log, sim_stats, bridge = close_monitor(monitor)
        if pilot is not None:
            pilot.close()
        tail = px4.log_tail() if error else ''
        px4.stop()
        rclpy.try_shutdown()
    if not info.get('started'):   # nothing is evaluated before ibvs/start (the take-off is
        log = report.RunLog()     # the harness's, not the run)
    print(f'stopped: {stop_reason or error} (exit codes {codes})', flush=True)
    if tail:
        print('PX4 log tail:\n' + tail, flush=True)
    if log.xi:
        info['end_pose_I'] = [round(float(x), 3) for x in log.xi[-1]]
        info['max_x_I'] = round(float(max(x[0] for x in log.xi)), 3)   # nearest the wall / past
    summary = report.summarize(log, world, vehicle.envelope_radius, vehicle.envelope_height)
    summary['timing'] = sim_stats
    summary['bridge'] = bridge
    summary['run'] = run_block(opts, xi0, autopilot='px4-sih', stop_reason=stop_reason,
                               error=error, wall_time_s=time.monotonic() - t_wall0,
                               events=log.events, **info,
                               transitions=supervisor_transitions(
                                   supervisor_log(opts.out_dir)))
    return finish(opts, summary, report.run_data(log, world, pad) if log.t else None)


def _flight(opts, monitor, runner, pilot, xi0, t_wall0, info, respawning: set,
            takeoff_alt_m: float, frame: NedToI, world) -> str:
    """Take off, settle, preflight, ibvs/start, watch; return the stop reason."""
    import rclpy
    from std_srvs.srv import Trigger
    from ibvs_bringup.preflight import format_checklist

    def spin(dt: float) -> None:
        rclpy.spin_once(monitor, timeout_sec=dt)
        pilot.poll()
        for event in runner.supervise():
            print(f'runner: {event}', flush=True)
            if 'died' in event and not any(f"'{n}'" in event for n in respawning):
                raise _Stop(event)
        if time.monotonic() - t_wall0 > opts.timeout_s:
            raise _Stop(f'wall-clock timeout {opts.timeout_s:.0f} s')

    deadline = time.monotonic() + GRAPH_UP_TIMEOUT_S
    while not monitor.log.t:
        if time.monotonic() > deadline:
            raise _Stop(f'no ground truth from px4_sim within {GRAPH_UP_TIMEOUT_S:.0f} s '
                        '(see logs/px4_sim.log)')
        spin(0.05)
    t = time.monotonic()
    why = pilot.take_off(TAKEOFF_TIMEOUT_S, TAKEOFF_REACHED * takeoff_alt_m, spin)
    if why:
        raise _Stop(why)
    info['takeoff_s'] = round(time.monotonic() - t, 2)
    xi = monitor.log.xi[-1]
    print(f'PX4 holds after its take-off ({info["takeoff_s"]} s) at xi_I = '
          f'({xi[0]:+.2f}, {xi[1]:+.2f}, {xi[2]:+.2f}); scenario start '
          f'{tuple(round(x, 2) for x in xi0)}', flush=True)
    # PX4 holds its own estimate, which is off the truth and wanders (measured: 0.3-0.5 m in
    # height after the take-off, up to 1 m and 0.3 rad of heading within a minute on the
    # loaded machine): the harness moves PX4's hold point by the ground-truth error
    # (DO_REPOSITION, PX4 stays in AUTO.LOITER), once it has settled after the last one
    # (REPOSITION_STILL_S, or REPOSITION_MAX_WAIT_S in motion), until the truth is
    # at the start while the preflight passes, then starts at once; the pose is reported.
    target, yaw0 = frame.to_ned(xi0), float(world.initial_yaw)
    deadline = time.monotonic() + opts.preflight_timeout_s
    moved_at, moving_at, info['repositions'] = -np.inf, time.monotonic(), 0
    while True:
        spin(0.05)
        err = target - frame.to_ned(monitor.log.xi[-1])
        yaw_err = math.remainder(yaw0 - float(monitor.log.euler[-1][2]), 2.0 * math.pi)
        there = at_start(monitor.log.xi[-1], xi0, yaw_err, world.random_box)
        # PX4 has flown to its last hold point (not merely passing through the tolerance on
        # its way: measured, runs then started at the tolerance's edge, y = +0.29)
        arrived = time.monotonic() - moved_at >= REPOSITION_WAIT_S
        # and is still: a start at 0.33 m/s sideways (measured) lost the window in WINDOW
        still = float(np.linalg.norm(monitor.log.v[-1])) < START_SPEED_TOL_MPS
        if not still:
            moving_at = time.monotonic()
        if there and arrived and still and monitor.health.healthy():
            break
        if time.monotonic() > deadline:
            print('preflight:\n' + format_checklist(monitor.health.checklist()), flush=True)
            raise _Stop(f'not at the start with the preflight passed within '
                        f'{opts.preflight_timeout_s:.0f} s (error {np.round(err, 2).tolist()} '
                        f'm NED, {yaw_err:+.3f} rad, in SPEC\'s start box: '
                        f'{in_box(monitor.log.xi[-1], world.random_box)}, '
                        f'{info["repositions"]} repositions)')
        since_move = time.monotonic() - moved_at
        settled = time.monotonic() - moving_at >= REPOSITION_STILL_S
        if not there and since_move > REPOSITION_WAIT_S \
                and (settled or since_move > REPOSITION_MAX_WAIT_S):
            # each correction in the run's output, so that a start hold that does not converge
            # can be read from it (docs/px4_sih.md)
            print(f'start hold: reposition {info["repositions"] + 1} by '
                  f'{np.round(err, 2).tolist()} m NED, {yaw_err:+.3f} rad '
                  f'({"settled" if settled else "in motion"}, true '
                  f'speed {float(np.linalg.norm(monitor.log.v[-1])):.2f} m/s; the last one\'s '
                  f'COMMAND_ACK {pilot.acks.get(MAV_CMD_DO_REPOSITION, "none")})', flush=True)
            moved_at = time.monotonic()
            info['repositions'] += pilot.reposition_by(err, yaw_err)
    print('preflight:\n' + format_checklist(monitor.health.checklist()), flush=True)
    xi, euler = monitor.log.xi[-1], monitor.log.euler[-1]
    info['start_pose_I'] = [round(float(x), 3) for x in xi]
    info['start_yaw_rad'] = round(float(euler[2]), 4)
    # PX4's own heading (its estimate: what imu/data and so the graph see) vs the truth
    info['px4_yaw_estimate_rad'] = None if pilot.yaw_est is None else round(pilot.yaw_est, 4)
    info['start_speed_mps'] = round(float(np.linalg.norm(monitor.log.v[-1])), 3)
    print(f'start pose (ground truth): xi_I = ({xi[0]:+.2f}, {xi[1]:+.2f}, {xi[2]:+.2f}), '
          f'yaw {euler[2]:+.3f} rad, speed {info["start_speed_mps"]:.2f} m/s', flush=True)
    client = monitor.create_client(Trigger, 'ibvs/start')
    deadline = time.monotonic() + START_WAIT_S
    answer = None
    while True:
        if time.monotonic() > deadline:
            raise _Stop(f'ibvs/start not accepted within {START_WAIT_S:.0f} s: '
                        f'{answer.message if answer else "no answer"}')
        if client.service_is_ready():
            t_call = monitor.get_clock().now().nanoseconds * 1e-9
            future = client.call_async(Trigger.Request())
            until = time.monotonic() + 1.0
            while not future.done() and time.monotonic() < until:
                spin(0.02)
            answer = future.result() if future.done() else None
            if answer is not None and answer.success:
                break
        spin(0.2)
    monitor.reset_log(t_call)
    info['started'] = True
    # px4_sim's counters run from its start (take-off and hold included): the flight's own
    # frames are the final ones minus these
    info['timing_at_start'] = {k: monitor.sim_stats.get(k) for k in (
        'frames_due', 'frames_published', 'frames_dropped', 'frames_stale')}
    print(f'ibvs/start: {answer.message}', flush=True)
    limit_s = opts.px4_flight_s if opts.px4_flight_s is not None else MAX_FLIGHT_S
    next_print = time.monotonic()
    while True:
        spin(0.02)
        t_run, mode = monitor.now_s(), monitor.log.mode
        if time.monotonic() >= next_print:
            next_print += 1.0
            xi = monitor.log.xi[-1] if monitor.log.xi else np.full(3, np.nan)
            st = monitor.sim_stats
            print(f'  t = {t_run:6.2f} s  mode {mode_name(mode)}  xi_I = ({xi[0]:+.2f}, '
                  f'{xi[1]:+.2f}, {xi[2]:+.2f})  PX4 main mode {pilot.main_mode}  frames '
                  f'{st.get("frames_published")} published / {st.get("frames_dropped")} '
                  'dropped', flush=True)
        if monitor.collision is not None:
            return f"collision with {monitor.collision.get('surface')}"
        if mode == FAILSAFE_MODE:
            return 'failsafe'
        if monitor.touchdown is not None and mode == SHUTDOWN_MODE:
            if monitor.health.armed is False or not pilot.armed:
                return 'touchdown, mode 4, disarmed'
            if t_run - float(monitor.touchdown.get('t', t_run)) > SHUTDOWN_GRACE_S:
                return 'touchdown, mode 4 (no disarm report)'
        if t_run > limit_s:
            return f'{limit_s:g} s after ibvs/start'
