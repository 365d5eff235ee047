"""The ``px4-sih`` scenario harness: start PX4 SIH as the Pelican, and the pilot's GCS.

PX4 v1.16 SITL with SIH (``../shared/px4-sitl``, not part of the repository; located by
:func:`ibvs_sim.core.px4_plant.find_px4_sitl`) is the plant and the autopilot. This module:

- :class:`Px4Sitl` starts one instance with the Pelican's SIH parameters
  (:func:`~ibvs_sim.core.px4_plant.sih_parameters` of vehicle.yaml), the home the ``px4_sim``
  node maps from, and the take-off height of the scenario's start (MIS_TAKEOFF_ALT); stops it
  by its work directory (``px4-sih stop``: that PID only);
- :class:`Pilot` is the harness acting as the pilot's ground station on PX4's GCS link
  (udpout to 127.0.0.1:18570 + i): it arms PX4 and commands its own take-off
  (MAV_CMD_NAV_TAKEOFF to MIS_TAKEOFF_ALT; PX4 then holds in AUTO.LOITER). The graph's
  bridge never arms (issue 13 safety policy, docs/mavlink.md): it engages OFFBOARD once the
  scenario calls ibvs/start, as against the sim, and finds the vehicle armed.

Clocks: every wait here is on the steady clock (``time.monotonic``), with its own named limit.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import os
from pathlib import Path
import socket
import subprocess
import tempfile
import time
from typing import Callable, TYPE_CHECKING

from ibvs_sim.core.px4_plant import (EARTH_RADIUS_M, find_px4_sitl, MOCAP_EKF2_PARAMETERS,
                                     SIH_DEFAULT_HOME)

if TYPE_CHECKING:
    import numpy as np

START_TIMEOUT_S = 90.0          # s (steady), px4-sih start (it waits for "Ready for takeoff")
STOP_TIMEOUT_S = 30.0           # s (steady), px4-sih stop
COMMAND_RETRY_S = 1.0           # s (steady), a command without its ack is sent again
HEARTBEAT_PERIOD_S = 1.0        # s (steady), the GCS's own heartbeat
#: Nice value of a SITL autopilot's threads: on a vehicle the autopilot has its own flight
#: controller; here a starved PX4 lets SIH's clock slip (measured: 6700 ppm skew and a jump
#: that reset the bridge's clock sync, IMU stale -> FAILSAFE, with PX4 at the graph's
#: priority). It lessens starvation, it does not end it: a CI run beside the other test
#: worker still had PX4's simulated magnetometer time out at nice -5.
SITL_NICE = -5
PX4_INSTANCE_PORT_BASES = (14540, 14580, 18570, 19410, 19450)   # UDP, + i
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_LAND = 21
MAV_CMD_DO_REPOSITION = 192
MAV_DO_REPOSITION_FLAGS_CHANGE_MODE = 1
MAV_FRAME_GLOBAL = 0
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_PX4 = 12
PX4_MAIN_AUTO, PX4_SUB_LOITER, PX4_SUB_TAKEOFF = 4, 3, 2
PX4_MAIN_OFFBOARD = 6


def free_instance(first: int = 5, last: int = 9) -> int:
    """Return a PX4 instance in [first, last] whose UDP ports (bases + i) are all free now."""
    for i in range(first, last + 1):
        free = True
        for base in PX4_INSTANCE_PORT_BASES:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                try:
                    s.bind(('127.0.0.1', base + i))
                except OSError:
                    free = False
        if free:
            return i
    raise RuntimeError(f'no free PX4 instance in {first}-{last} (UDP ports '
                       f'{PX4_INSTANCE_PORT_BASES} + i taken)')


def _launcher(sitl_dir: Path, work: Path, script_name: str = 'px4-sih') -> Path:
    """Return ``script_name`` (px4-sih, px4-hil); through a private bin/ of symlinks when needed.

    PX4's start script runs px4-param etc., which must be links to the px4 binary; a copy of
    the folder that turned them into 3-byte text files ("px4") makes PX4 exit at start.
    """
    script = sitl_dir / script_name
    if os.access(sitl_dir / 'bin' / 'px4-param', os.X_OK):
        return script
    shadow = work / 'px4-sitl'
    (shadow / 'bin').mkdir(parents=True, exist_ok=True)
    for f in (sitl_dir / 'bin').iterdir():
        link = shadow / 'bin' / f.name
        if link.exists() or link.is_symlink():
            continue
        if f.name.startswith('px4-') and f.stat().st_size < 16 \
                and f.read_text().strip() == 'px4':
            link.symlink_to('px4')
        else:
            link.symlink_to(f)
    for name in ('etc', 'px4-sih', script_name):
        if not (shadow / name).exists():
            (shadow / name).symlink_to(sitl_dir / name)
    return shadow / script_name


@dataclass
class Px4Sitl:
    """One PX4 SITL instance (``start`` / ``stop``); ``env`` = the script's printed variables.

    ``script``: ``px4-sih`` (SIH is the plant) or ``px4-hil`` (the sim's plant in lockstep:
    PX4 waits for its simulator, ``airframe`` its PX4_SIM_MODEL).
    """

    instance: int
    params: dict
    sitl_dir: str | None = None
    env: dict | None = None
    work: str | None = None
    script: str = 'px4-sih'
    airframe: str | None = None

    def start(self) -> dict:
        """Start PX4; raise RuntimeError if it fails.

        px4-sih returns once PX4 is ready for take-off, px4-hil once it waits for (or has
        reached) its simulator.
        """
        sitl = Path(self.sitl_dir or find_px4_sitl())
        self.work = tempfile.mkdtemp(prefix=f'{self.script}-{self.instance}-')
        script = _launcher(sitl, Path(self.work), self.script)
        args = [str(script), 'start', '-i', str(self.instance), '-w',
                os.path.join(self.work, 'w')]
        if self.airframe:
            args += ['-a', self.airframe]
        for name, value in self.params.items():
            args += ['-p', f'{name}={value}']
        out = subprocess.run(args, capture_output=True, text=True, timeout=START_TIMEOUT_S)
        env = dict(line.split('=', 1) for line in out.stdout.split() if '=' in line)
        if out.returncode != 0 or 'PX4_WORKDIR' not in env:
            raise RuntimeError(f'{self.script} start failed ({out.returncode}): '
                               f'{out.stderr[-1500:]}')
        self.env = env
        self._script = script
        return env

    def renice(self, nice: int) -> str:
        """Set the nice value of every thread of this PX4 (:func:`renice_threads`)."""
        return renice_threads(int(self.env['PX4_PID']), nice)

    def stop(self) -> None:
        """Stop this instance (by its work directory: only its own PID)."""
        if self.env is None:
            return
        subprocess.run([str(self._script), 'stop', self.env['PX4_WORKDIR']],
                       capture_output=True, timeout=STOP_TIMEOUT_S)
        self.env = None

    def log_tail(self, n: int = 20) -> str:
        """Return the last ``n`` lines of PX4's console log ('' when absent)."""
        try:
            with open(self.env['PX4_LOG'] if self.env else '', errors='replace') as f:
                return ''.join(f.readlines()[-n:])
        except (OSError, KeyError):
            return ''


def px4_boot_parameters(sih: dict, takeoff_alt_m: float,
                        home: tuple = SIH_DEFAULT_HOME, offboard_loss_s: float = 1.0,
                        mocap: bool = False) -> dict:
    """Return the PX4 parameters of a px4-sih run: SIH's, home, take-off height, failsafes.

    ``takeoff_alt_m``: MIS_TAKEOFF_ALT, the start height above home (m). COM_OF_LOSS_T: the
    offboard-loss timeout (s, PX4's clock) after which PX4's own failsafe (land) acts.
    ``mocap``: EKF2 on motion capture (px4_sim's MocapRelay), GPS and magnetometer off
    (:data:`~ibvs_sim.core.px4_plant.MOCAP_EKF2_PARAMETERS`).
    """
    if not (math.isfinite(takeoff_alt_m) and takeoff_alt_m > 0.0):
        raise ValueError(f'take-off altitude must be > 0 m, got {takeoff_alt_m}')
    return {**sih, 'SIH_LOC_LAT0': home[0], 'SIH_LOC_LON0': home[1], 'SIH_LOC_H0': home[2],
            'MIS_TAKEOFF_ALT': round(float(takeoff_alt_m), 3),
            'COM_OF_LOSS_T': float(offboard_loss_s),
            **(MOCAP_EKF2_PARAMETERS if mocap else {})}


class Pilot:
    """The harness as the pilot's GCS on PX4's GCS link: heartbeat, arm, take-off, state."""

    def __init__(self, instance: int) -> None:
        os.environ.setdefault('MAVLINK20', '1')
        from pymavlink import mavutil
        self.conn = mavutil.mavlink_connection(f'udpout:127.0.0.1:{18570 + int(instance)}',
                                               source_system=255, source_component=190)
        self.armed = False
        self.main_mode = self.sub_mode = None
        self.relative_alt_m: float | None = None     # GLOBAL_POSITION_INT (PX4's estimate)
        self.target: tuple[int, int] | None = None   # PX4's ids (MAV_SYS_ID = 1 + instance)
        self.position_est = None      # PX4's own (lat, lon deg, alt m AMSL): its estimate
        self.yaw_est: float | None = None             # rad, PX4's own heading (ATTITUDE)
        self.acks: dict = {}
        self.statustext: list[str] = []
        self._beat = -math.inf

    def poll(self) -> None:
        """Send the GCS heartbeat when due; read what PX4 sent (never blocks)."""
        now = time.monotonic()
        if now - self._beat >= HEARTBEAT_PERIOD_S:
            self._beat = now
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)     # GCS, invalid autopilot
        while True:
            try:
                m = self.conn.recv_match(blocking=False)
            except (OSError, ValueError):
                continue
            if m is None:
                return
            kind = m.get_type()
            if kind == 'HEARTBEAT' and m.autopilot == MAV_AUTOPILOT_PX4:
                self.target = (m.get_srcSystem(), m.get_srcComponent())
                self.armed = bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
                self.main_mode = (m.custom_mode >> 16) & 0xFF
                self.sub_mode = (m.custom_mode >> 24) & 0xFF
            elif kind == 'ATTITUDE':
                self.yaw_est = float(m.yaw)
            elif kind == 'GLOBAL_POSITION_INT':
                self.relative_alt_m = m.relative_alt * 1e-3
                self.position_est = (m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3)
            elif kind == 'COMMAND_ACK':
                self.acks[int(m.command)] = int(m.result)
            elif kind == 'STATUSTEXT':
                self.statustext = (self.statustext + [str(m.text)])[-20:]

    def command(self, cmd: int, *params: float) -> bool:
        """Send COMMAND_LONG ``cmd`` with up to 7 params to PX4; False before its HEARTBEAT."""
        if self.target is None:
            return False
        p = list(params) + [0.0] * (7 - len(params))
        self.acks.pop(int(cmd), None)
        self.conn.mav.command_long_send(*self.target, int(cmd), 0, *p)
        return True

    def loitering(self, min_alt_m: float = 0.0) -> bool:
        """Whether PX4 holds (AUTO.LOITER) armed at least ``min_alt_m`` above home."""
        return (self.armed and self.main_mode == PX4_MAIN_AUTO
                and self.sub_mode == PX4_SUB_LOITER and self.relative_alt_m is not None
                and self.relative_alt_m >= min_alt_m)

    def take_off(self, timeout_s: float, min_alt_m: float,
                 spin: Callable[[float], None] | None = None) -> str | None:
        """Command PX4's take-off and arm, retrying each second; wait for AUTO.LOITER.

        Holding counts once PX4's own altitude estimate is ``min_alt_m`` above home (an
        arming that landed in AUTO.LOITER on the ground is not a take-off). ``spin(dt)`` is
        called between polls (the scenario keeps its ROS node spinning). Return None once PX4
        holds, else why not after ``timeout_s`` (steady clock).
        """
        deadline = time.monotonic() + timeout_s
        sent = -math.inf
        while time.monotonic() < deadline:
            self.poll()
            if self.loitering(min_alt_m):
                return None
            if time.monotonic() - sent >= COMMAND_RETRY_S and not (
                    self.armed and self.main_mode == PX4_MAIN_AUTO
                    and self.sub_mode == PX4_SUB_TAKEOFF):
                sent = time.monotonic()
                # NaN altitude / position: PX4 climbs to MIS_TAKEOFF_ALT above home, here
                self.command(MAV_CMD_NAV_TAKEOFF, -1, 0, 0, math.nan, math.nan, math.nan,
                             math.nan)
                if not self.armed:
                    self.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
            (spin or time.sleep)(0.02)
        return (f'PX4 not holding after its take-off within {timeout_s:.0f} s: armed '
                f'{self.armed}, main mode {self.main_mode}, sub mode {self.sub_mode}, '
                f'altitude {self.relative_alt_m} m, acks '
                f'{self.acks}, last texts {self.statustext[-3:]}')

    def reposition_by(self, d_ned: np.ndarray, d_yaw_rad: float = 0.0) -> bool:
        """Move PX4's hold point by ``d_ned`` (m, NED) and its heading by ``d_yaw_rad``.

        MAV_CMD_DO_REPOSITION (COMMAND_INT, global frame, AMSL altitude) to PX4's own
        estimate plus the offset (the map of ``geodetic_to_ned`` to first order), heading
        (param 4, rad in PX4) its ATTITUDE yaw plus ``d_yaw_rad``. False before PX4's
        HEARTBEAT, position and attitude.
        """
        if self.target is None or self.position_est is None or self.yaw_est is None:
            return False
        lat, lon, alt = self.position_est
        m_per_deg = EARTH_RADIUS_M * math.pi / 180.0
        lat_t = lat + float(d_ned[0]) / m_per_deg
        lon_t = lon + float(d_ned[1]) / (m_per_deg * math.cos(math.radians(lat)))
        self.acks.pop(MAV_CMD_DO_REPOSITION, None)
        self.conn.mav.command_int_send(*self.target, MAV_FRAME_GLOBAL, MAV_CMD_DO_REPOSITION,
                                       0, 0, -1.0, MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0.0,
                                       math.remainder(self.yaw_est + d_yaw_rad, 2 * math.pi),
                                       int(round(lat_t * 1e7)),
                                       int(round(lon_t * 1e7)), alt - float(d_ned[2]))
        return True

    def close(self) -> None:
        """Close the GCS socket."""
        self.conn.close()


def renice_threads(pid: int, nice: int) -> str:
    """Set the nice value of every thread of process ``pid`` (Linux); return what was done.

    For a SITL autopilot (PX4, ArduPilot): on a vehicle it runs on its own flight controller;
    here it shares the cores with the graph or the tests, and a starved SITL lets its clock
    slip, its sensors time out and its failsafes act (docs/px4_sih.md). Linux keeps a nice
    value per thread, so each one of /proc/PID/task is set. A permission error (no
    CAP_SYS_NICE for a negative value) is reported, not raised.
    """
    done, failed = 0, 0
    try:
        tids = os.listdir(f'/proc/{pid}/task')
    except OSError as exc:
        return f'not reniced: {exc}'
    for tid in tids:
        try:
            os.setpriority(os.PRIO_PROCESS, int(tid), int(nice))
            done += 1
        except OSError:
            failed += 1
    return f'{done} threads at nice {nice}' + (f', {failed} refused' if failed else '')
