"""ArduCopter 4.5.6 SITL on its JSON backend flies the sim's plant (``--autopilot ardupilot``).

:class:`ArduPilotSitl` starts and stops ``../shared/ardupilot-sitl/ardupilot-sitl start
--json`` with the Pelican's parameters (:func:`ardupilot_mission_parameters`), as
:class:`~ibvs_harness.px4_sih.Px4Sitl` does PX4's ``px4-hil``; the sim node
(``firmware: ardupilot``) binds the JSON port first and flies the plant under ArduPilot's
servo outputs (docs/firmware_lockstep.md "The mission on ArduPilot").
"""
from __future__ import annotations

from dataclasses import dataclass
import os
from pathlib import Path
import socket
import subprocess
import tempfile

from ibvs_common.core.config import VehicleConfig
from ibvs_sim.core.firmware.ardupilot_json import ardupilot_parameters, JSON_PORT_BASE
from ibvs_sim.core.px4_plant import find_px4_sitl

ARDUPILOT_FIRMWARE = 'ArduCopter V4.5.6 SITL (JSON backend, lockstep)'
#: ArduPilot's pacing limit against the wall clock: the lockstep paces it, this only caps it
SPEEDUP = 50
START_TIMEOUT_S = 60.0          # s (steady), ardupilot-sitl start (returns once it runs)
STOP_TIMEOUT_S = 30.0           # s (steady)
#: UDP ports of instance i: base + step i (JSON, companion SERIAL1, GCS SERIAL2, SITL RC in)
UDP_PORTS = ((JSON_PORT_BASE, 10), (14540, 1), (14550, 1), (5501, 10))
TCP_PORTS = ((5760, 10),)       # SERIAL0's TCP server
#: ArduPilot's GCS failsafe on the bridge's HEARTBEAT: LAND (docs/mavlink.md "Autopilot set-up")
FS_GCS_LAND = 5
#: GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET thrust is thrust, not climb rate (the bridge needs it)
GUID_OPTIONS_THRUST = 8
#: SERIAL1 (the companion link) at 921600 baud, as docs/onboard.md's UART. ArduPilot stamps a
#: TIMESYNC request with its arrival less the time its bytes took at the port's baud rate; at
#: the default 57600 a burst of the bridge's datagrams made that 11 ms, and the bridge's clock
#: offset 11 ms short (measured: every lockstep frame then waited for its setpoint in vain)
SERIAL1_BAUD = 921
# the dead-bridge failsafe's timing: the last attitude target is flown GUID_TIMEOUT (default
# 3 s: the bridge killed in WINDOW flew the vehicle into the window frame), then ArduCopter
# levels it and holds its height until FS_GCS_TIMEOUT (default 5 s, at least 2) without our
# HEARTBEAT, then LAND
GUID_TIMEOUT_S = 0.5
FS_GCS_TIMEOUT_S = 2.0


def ardupilot_sitl_dir() -> Path:
    """Return ../shared/ardupilot-sitl; FileNotFoundError naming where it was looked for."""
    d = Path(find_px4_sitl()).parent / 'ardupilot-sitl'
    if not (d / 'ardupilot-sitl').is_file():
        raise FileNotFoundError(f'ArduPilot SITL not found ({d / "ardupilot-sitl"}): '
                                '--autopilot ardupilot needs ArduCopter 4.5.6 SITL as '
                                '../shared/ardupilot-sitl next to the repository')
    return d


def ardupilot_mission_parameters(vehicle: VehicleConfig, bridge_system: int) -> dict:
    """Return the parameters a user sets to fly this vehicle with the bridge.

    The Pelican's frame, motors and hover throttle (:func:`ardupilot_parameters`), GUIDED_NOGPS
    thrust (GUID_OPTIONS 8), the companion UART's baud rate, and the dead-bridge failsafe:
    LAND when the HEARTBEAT of ``bridge_system`` (the bridge's ``source_system``) stops
    (FS_GCS_ENABLE 5, SYSID_MYGCS).
    """
    return {**ardupilot_parameters(vehicle), 'GUID_OPTIONS': GUID_OPTIONS_THRUST,
            'SERIAL1_BAUD': SERIAL1_BAUD, 'FS_GCS_ENABLE': FS_GCS_LAND,
            'SYSID_MYGCS': int(bridge_system), 'GUID_TIMEOUT': GUID_TIMEOUT_S,
            'FS_GCS_TIMEOUT': FS_GCS_TIMEOUT_S}


def free_instance(first: int = 1, last: int = 4) -> int:
    """Return an ArduPilot instance in [first, last] whose ports are all free now."""
    for i in range(first, last + 1):
        ports = ([(socket.SOCK_DGRAM, base + step * i) for base, step in UDP_PORTS]
                 + [(socket.SOCK_STREAM, base + step * i) for base, step in TCP_PORTS])
        if all(_free(kind, port) for kind, port in ports):
            return i
    raise RuntimeError(f'no free ArduPilot instance in {first}-{last}')


def _free(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


@dataclass
class ArduPilotSitl:
    """One ArduCopter SITL on the JSON backend (``start`` / ``stop``); ``env``: its variables."""

    instance: int
    params: dict
    env: dict | None = None

    def start(self) -> dict:
        """Start ArduPilot (it waits for the physics' answers); raise RuntimeError if it fails."""
        script = ardupilot_sitl_dir() / 'ardupilot-sitl'
        work = tempfile.mkdtemp(prefix=f'ap-json-{self.instance}-')
        args = [str(script), 'start', '--json', '--speedup', str(SPEEDUP),
                '-i', str(self.instance), '-w', work]
        for name, value in self.params.items():
            args += ['-p', f'{name}={value}']
        out = subprocess.run(args, capture_output=True, text=True, timeout=START_TIMEOUT_S)
        env = dict(line.split('=', 1) for line in out.stdout.split() if '=' in line)
        if out.returncode != 0 or 'AP_WORKDIR' not in env:
            raise RuntimeError(f'ardupilot-sitl start failed ({out.returncode}): '
                               f'{out.stderr[-1500:]}')
        self.env = env
        return env

    def stop(self) -> None:
        """Stop this instance (by its work directory: only its own PID)."""
        if self.env is None:
            return
        subprocess.run([str(ardupilot_sitl_dir() / 'ardupilot-sitl'), 'stop',
                        self.env['AP_WORKDIR']], capture_output=True, timeout=STOP_TIMEOUT_S)
        self.env = None

    def log_tail(self, n: int = 20) -> str:
        """Return the last ``n`` lines of ArduPilot's console log ('' when absent)."""
        try:
            path = self.env.get('AP_LOG') or os.path.join(self.env['AP_WORKDIR'],
                                                          'arducopter.log')
            with open(path, errors='replace') as f:
                return ''.join(f.readlines()[-n:])
        except (OSError, KeyError, AttributeError):
            return ''
