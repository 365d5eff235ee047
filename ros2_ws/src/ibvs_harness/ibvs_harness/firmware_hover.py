"""Real firmware flies the sim's Pelican in lockstep: boot, arm, take off, hold; the figures.

``python -m ibvs_harness.firmware_hover [--autopilot px4|ardupilot] [--height M] [--hold-s S]
[--seed N] [--json]``

PX4 v1.16 SITL (``../shared/px4-sitl/px4-hil``) runs its own mixer, controllers and EKF2 on
the sim's plant (:class:`~ibvs_sim.core.firmware.lockstep.FirmwarePlant`): sensors from the
ground truth, motion capture for EKF2, the Pelican's rotor geometry and hover output from
vehicle.yaml (:func:`~ibvs_sim.core.firmware.px4_hil.px4_hil_parameters`). The harness is
the pilot's GCS (:class:`~ibvs_harness.px4_sih.Pilot`): it sets the EKF origin, arms and
commands PX4's own take-off, and PX4 holds in AUTO.LOITER. The figures: sim time to the
take-off, the hover output against the plant's (m g / 4 through the thrust curve), and the
hold's height and horizontal errors against PX4's take-off target. It checks that the
firmware, the plant, the sensors and the parameters agree before a flight of the graph uses
them (docs/firmware_lockstep.md). ``--autopilot ardupilot``: ArduCopter 4.5.6 SITL on its JSON
backend (``../shared/ardupilot-sitl start --json``), GUIDED take-off on its own GPS, barometer
and compass made from the plant's state (:func:`fly_hover_ardupilot`).
"""
from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field
import json
import math
import subprocess
import sys
import time

import numpy as np
from pymavlink import mavutil

from ibvs_common.core.config import load_vehicle
from ibvs_common.core.frames import GRAVITY
from ibvs_sim.core.dynamics import PlantParams
from ibvs_sim.core.events import EventType
from ibvs_sim.core.firmware.ardupilot_json import (ardupilot_motor_model, ardupilot_parameters,
                                                   ArduPilotJsonLink)
from ibvs_sim.core.firmware.lockstep import ArduPilotExchange, FirmwarePlant, Px4Exchange
from ibvs_sim.core.firmware.px4_hil import (FirmwareLinkError, px4_hil_parameters,
                                            px4_motor_model, Px4Sensors, Px4SimLink)
from ibvs_sim.core.px4_plant import find_px4_sitl, SIH_DEFAULT_HOME
from ibvs_sim.core.world import load_world
from ibvs_harness.ardupilot_sitl import ArduPilotSitl
from ibvs_harness.px4_sih import free_instance, Pilot, Px4Sitl

MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
ACCEPT_TIMEOUT_S = 60.0         # s (wall), PX4's connection to the simulator after its start
ARM_AFTER_S = 12.0              # s (sim), the pilot arms once EKF2 has had this long
COMMAND_PERIOD_S = 1.0          # s (sim), arm / take-off / origin retried this often
TAKEOFF_TIMEOUT_S = 30.0        # s (sim), from the first arm request to AUTO.LOITER
PX4_MAIN_AUTO, PX4_SUB_LOITER = 4, 3


@dataclass
class HoverReport:
    """What one lockstep hover measured (SI; times on the sim clock unless named wall)."""

    firmware: str = 'PX4 v1.16.0 SITL (simulator_mavlink, lockstep)'
    ok: bool = False
    error: str = ''
    armed_at_s: float | None = None
    loiter_at_s: float | None = None      # PX4 in AUTO.LOITER; ArduPilot within 15 cm
    hold_s: float = 0.0
    hover_output_mean: float | None = None
    hover_output_plant: float | None = None
    height_target_m: float = 0.0          # above home (the body origin at rest)
    height_error_mean_m: float | None = None
    height_error_max_m: float | None = None
    horizontal_error_max_m: float | None = None
    tilt_max_deg: float | None = None
    exchanges: int = 0
    sim_s: float = 0.0
    wall_s: float = 0.0
    parameters: dict = field(default_factory=dict)


@dataclass
class HoldSamples:
    """The hold's samples, one per pilot poll: mean motor output, height above home, drift."""

    outputs: list = field(default_factory=list)
    heights: list = field(default_factory=list)
    horiz: list = field(default_factory=list)
    tilts: list = field(default_factory=list)

    def add(self, fw: FirmwarePlant, start: np.ndarray) -> None:
        """Take the plant's state now (truth) and the firmware's last outputs."""
        s = fw.state
        self.outputs.append(float(np.mean(fw.outputs)))
        self.heights.append(fw.z_home - float(s.xi_I[2]))
        self.horiz.append(float(np.linalg.norm(s.xi_I[:2] - start[:2])))
        self.tilts.append(math.degrees(math.acos(min(1.0, float(s.R_IB[2, 2])))))

    def judge(self, report: HoverReport, hold_s: float) -> None:
        """Fill the hold's figures of ``report``."""
        h_err = np.array(self.heights) - report.height_target_m
        report.hold_s = hold_s
        report.hover_output_mean = float(np.mean(self.outputs))
        report.height_error_mean_m = float(np.mean(h_err))
        report.height_error_max_m = float(np.max(np.abs(h_err)))
        report.horizontal_error_max_m = float(np.max(self.horiz))
        report.tilt_max_deg = float(np.max(self.tilts))
        report.ok = True


def fly_hover(height_m: float = 1.5, hold_s: float = 10.0, seed: int = 0,
              instance: int | None = None) -> HoverReport:
    """Boot PX4 on the plant, take off to ``height_m``, hold ``hold_s``; return the figures."""
    world, vehicle = load_world(), load_vehicle()
    plant = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
    params = {**px4_hil_parameters(vehicle, plant), 'MIS_TAKEOFF_ALT': round(height_m, 3)}
    report = HoverReport(height_target_m=height_m, parameters=params)
    inst = free_instance() if instance is None else instance
    link = Px4SimLink(inst)
    link.open()
    sitl = Px4Sitl(inst, params, script='px4-hil')
    pilot = None
    t_wall0 = time.monotonic()
    try:
        sitl.start()
        link.accept(ACCEPT_TIMEOUT_S)
        sensors = Px4Sensors(SIH_DEFAULT_HOME[2], world.floor_z, seed=seed)
        start = np.array(world.initial_position_I, float)
        fw = FirmwarePlant(world, vehicle, Px4Exchange(link, sensors), px4_motor_model(plant),
                           start, world.initial_yaw)
        pilot = Pilot(inst)
        _fly(fw, pilot, report, hold_s, start)
        report.hover_output_plant = px4_motor_model(plant).output_for(
            plant.mass * GRAVITY / 4.0)
        report.exchanges = fw.exchanges
        report.sim_s = fw.t
    except (FirmwareLinkError, RuntimeError, OSError) as exc:
        report.error = f'{type(exc).__name__}: {exc}'
        tail = sitl.log_tail(8)
        if tail:
            report.error += f'\nPX4 log:\n{tail}'
    finally:
        report.wall_s = time.monotonic() - t_wall0
        if pilot is not None:
            pilot.close()
        sitl.stop()
        link.close()
    return report


def _fly(fw: FirmwarePlant, pilot: Pilot, report: HoverReport, hold_s: float,
         start: np.ndarray) -> None:
    """Step the plant; the pilot arms, takes off and watches the hold (sim-time schedule)."""
    home = SIH_DEFAULT_HOME
    next_command = ARM_AFTER_S
    hold = HoldSamples()
    while True:
        event = fw.substep()
        if event is not None and event.type is EventType.COLLISION:
            raise RuntimeError(f'collision with the {event.surface} at t = {fw.t:.2f} s')
        if fw.step_index % 10:
            continue
        pilot.poll()
        t = fw.t
        if not pilot.armed and t >= next_command and pilot.target is not None:
            # the EKF origin (motion capture has none) and PX4's own take-off, until armed;
            # once armed, a repeated origin or take-off would move PX4's target
            next_command = t + COMMAND_PERIOD_S
            pilot.conn.mav.set_gps_global_origin_send(pilot.target[0], int(home[0] * 1e7),
                                                      int(home[1] * 1e7), int(home[2] * 1e3),
                                                      0)
            pilot.command(MAV_CMD_NAV_TAKEOFF, -1, 0, 0, math.nan, math.nan, math.nan,
                          math.nan)
            pilot.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if fw.armed and report.armed_at_s is None:
            report.armed_at_s = t
        if report.armed_at_s is not None and report.loiter_at_s is None:
            if pilot.main_mode == PX4_MAIN_AUTO and pilot.sub_mode == PX4_SUB_LOITER \
                    and pilot.armed:
                report.loiter_at_s = t
            elif t - report.armed_at_s > TAKEOFF_TIMEOUT_S:
                raise RuntimeError(f'no AUTO.LOITER {TAKEOFF_TIMEOUT_S:.0f} s after arming: '
                                   f'mode {pilot.main_mode}/{pilot.sub_mode}, texts '
                                   f'{pilot.statustext[-3:]}')
        if report.loiter_at_s is None and t > ARM_AFTER_S + 60.0:
            raise RuntimeError(f'PX4 did not arm: texts {pilot.statustext[-3:]}')
        # the hold is judged after 3 s of loiter (the take-off's overshoot settles)
        if report.loiter_at_s is not None and t >= report.loiter_at_s + 3.0:
            hold.add(fw, start)
            if t >= report.loiter_at_s + 3.0 + hold_s:
                break
    hold.judge(report, hold_s)


ARDUPILOT_VERSION = 'ArduCopter V4.5.6 SITL (JSON backend, lockstep)'
ARDUCOPTER_GUIDED = 4
ARDUPILOT_ARM_BY_S = 120.0          # s (sim), GPS lock and EKF3 ready take 40-60 s of it
SETTLED_M = 0.15                    # m, a take-off is over within this of its height


def fly_hover_ardupilot(height_m: float = 1.5, hold_s: float = 10.0,
                        instance: int | None = None) -> HoverReport:
    """Fly ArduCopter on the plant: GUIDED, arm, take off to ``height_m``, hold ``hold_s``."""
    world, vehicle = load_world(), load_vehicle()
    plant = PlantParams.from_vehicle(vehicle, floor_z=world.floor_z)
    params = ardupilot_parameters(vehicle, plant)
    report = HoverReport(firmware=ARDUPILOT_VERSION, height_target_m=height_m,
                         parameters=params)
    inst = free_instance(1, 4) if instance is None else instance
    link = ArduPilotJsonLink(inst)
    link.open()
    sitl = ArduPilotSitl(inst, params)
    gcs = None
    t_wall0 = time.monotonic()
    try:
        sitl.start()
        gcs = mavutil.mavlink_connection(f'udpin:127.0.0.1:{14550 + inst}',
                                         source_system=255, source_component=190)
        fw = FirmwarePlant(world, vehicle, ArduPilotExchange(link),
                           ardupilot_motor_model(plant), np.array(world.initial_position_I),
                           world.initial_yaw)
        _fly_ardupilot(fw, gcs, report, hold_s)
        report.hover_output_plant = ardupilot_motor_model(plant).output_for(
            plant.mass * GRAVITY / 4.0)
        report.exchanges = fw.exchanges
        report.sim_s = fw.t
    except (FirmwareLinkError, RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        report.error = f'{type(exc).__name__}: {exc}'
    finally:
        report.wall_s = time.monotonic() - t_wall0
        if gcs is not None:
            gcs.close()
        sitl.stop()
        link.close()
    return report


def _fly_ardupilot(fw: FirmwarePlant, gcs, report: HoverReport, hold_s: float) -> None:
    """GUIDED, arm and take off by sim time; judge the hold once the take-off settled."""
    next_command, hb, texts = 1.0, None, []
    hold = HoldSamples()
    start = fw.state.xi_I.copy()
    while True:
        event = fw.substep()
        if event is not None and event.type is EventType.COLLISION:
            raise RuntimeError(f'collision with the {event.surface} at t = {fw.t:.2f} s')
        if fw.step_index % 10:
            continue
        while (m := gcs.recv_match(blocking=False)) is not None:
            if m.get_type() == 'HEARTBEAT' and m.get_srcComponent() == 1:
                hb = m
            elif m.get_type() == 'STATUSTEXT':
                texts = (texts + [m.text])[-5:]
        t, h = fw.t, fw.z_home - float(fw.state.xi_I[2])
        armed = hb is not None and bool(hb.base_mode & 128)
        if hb is not None and t >= next_command and report.loiter_at_s is None:
            next_command = t + 1.0
            if hb.custom_mode != ARDUCOPTER_GUIDED:
                gcs.mav.set_mode_send(1, 1, ARDUCOPTER_GUIDED)
            elif not armed:
                gcs.mav.command_long_send(1, 1, MAV_CMD_COMPONENT_ARM_DISARM, 0, 1,
                                          0, 0, 0, 0, 0, 0)
            elif h < 0.5 * report.height_target_m:
                gcs.mav.command_long_send(1, 1, MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0,
                                          report.height_target_m)
        if armed and report.armed_at_s is None:
            report.armed_at_s = t
        if report.armed_at_s is None and t > ARDUPILOT_ARM_BY_S:
            raise RuntimeError(f'ArduPilot did not arm in GUIDED by {t:.0f} s: {texts}')
        if report.armed_at_s is not None and report.loiter_at_s is None \
                and abs(h - report.height_target_m) < SETTLED_M:
            report.loiter_at_s = t
        if report.loiter_at_s is not None and t >= report.loiter_at_s + 3.0:
            hold.add(fw, start)
            if t >= report.loiter_at_s + 3.0 + hold_s:
                break
    hold.judge(report, hold_s)


def main(argv: list | None = None) -> int:
    """Fly the hover; print the report; exit 0 when it flew, 1 when not, 2 without PX4."""
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--height', type=float, default=1.5, help='take-off height, m (> 0)')
    p.add_argument('--hold-s', type=float, default=10.0, help='hold judged, s sim (> 0)')
    p.add_argument('--seed', type=int, default=0, help='sensor noise seed (PX4)')
    p.add_argument('--autopilot', choices=('px4', 'ardupilot'), default='px4',
                   help='the firmware: PX4 v1.16 (px4-hil) or ArduCopter 4.5.6 (JSON)')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    a = p.parse_args(argv)
    if not (a.height > 0.0 and a.hold_s > 0.0):
        p.error('--height and --hold-s must be > 0')
    try:
        find_px4_sitl()
    except FileNotFoundError as exc:
        print(f'firmware_hover: {exc}', file=sys.stderr)
        return 2
    r = (fly_hover(a.height, a.hold_s, a.seed) if a.autopilot == 'px4'
         else fly_hover_ardupilot(a.height, a.hold_s))
    if a.json:
        print(json.dumps(asdict(r), indent=1))
    else:
        print(_format(r))
    return 0 if r.ok else 1


def _format(r: HoverReport) -> str:
    """One screen of the report."""
    if not r.ok:
        return f'{r.firmware}: FAILED after {r.sim_s:.1f} s sim, {r.wall_s:.1f} s wall\n{r.error}'
    return '\n'.join([
        f'{r.firmware}',
        f'  armed at {r.armed_at_s:.2f} s, holding at {r.loiter_at_s:.2f} s sim',
        f'  hover output {r.hover_output_mean:.4f} (plant: {r.hover_output_plant:.4f} = '
        f'm g / 4 through the thrust curve)',
        f'  hold of {r.hold_s:.0f} s at {r.height_target_m:.2f} m: height error mean '
        f'{r.height_error_mean_m * 100:+.1f} cm, max {r.height_error_max_m * 100:.1f} cm; '
        f'horizontal max {r.horizontal_error_max_m * 100:.1f} cm; tilt max '
        f'{r.tilt_max_deg:.2f} deg',
        f'  {r.exchanges} sensor/output exchanges, {r.sim_s:.1f} s sim in {r.wall_s:.1f} s '
        f'wall ({r.sim_s / max(r.wall_s, 1e-9):.1f}x real time)'])


if __name__ == '__main__':
    sys.exit(main())
