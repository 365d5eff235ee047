"""The pilot before the mission: the firmware takes off and holds at the scenario's start.

With the emulated autopilot the sim starts in a hover at the start. A real firmware starts
on the floor, disarmed. :class:`Px4StartPilot` is the pilot's ground station on PX4's GCS
link (udpout 127.0.0.1:(18570 + instance)) while the sim steps the plant before its first
camera frame: once EKF2 has had ``arm_after_s`` of motion capture it sends the EKF origin,
PX4's own take-off (MIS_TAKEOFF_ALT, set at boot to the start's height above the floor
rest) and the arming, every ``command_period_s``, until PX4 is armed; then it waits until
the vehicle holds still at the start (:meth:`settled`). The plant starts on the floor right
below the start with the start's yaw, so a vertical take-off reaches it.
:class:`ArduPilotStartPilot` does the same on ArduPilot's GCS link (SERIAL2, udpin
127.0.0.1:(14550 + instance)): GUIDED, arm, then ArduCopter's own take-off
(MAV_CMD_NAV_TAKEOFF to the start's height above home), once EKF3 uses the GPS it makes from
the plant's position (about 65 s after boot). All times are sim time (s); ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import os

import numpy as np

from ibvs_sim.core.dynamics import State
from ibvs_sim.core.px4_plant import SIH_DEFAULT_HOME

os.environ.setdefault('MAVLINK20', '1')
from pymavlink import mavutil  # noqa: E402  (after MAVLINK20)

PX4_GCS_LISTEN_BASE = 18570
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_PX4 = 12
ARDUPILOT_GCS_SEND_BASE = 14550     # ArduPilot's SERIAL2 sends to 127.0.0.1:(14550 + instance)
ARDUCOPTER_MODE_GUIDED = 4


@dataclass(frozen=True)
class StartHold:
    """When the take-off counts as over: still at the start (sim time)."""

    arm_after_s: float = 12.0        # s, EKF2 on motion capture by then
    command_period_s: float = 1.0    # s, origin / take-off / arm repeated until armed
    position_tol_m: float = 0.10     # m, truth within this of the start
    speed_tol_mps: float = 0.05      # m/s, and slower than this
    still_for_s: float = 1.0         # s, for this long
    # s of plant time from boot: the pre-roll failed after this. PX4 in 0.5 m/s^2 gusts took
    # 133 and 137 s to hold still enough (a campaign start each, "horizontal position
    # unstable"); its usual pre-roll is ~24 s
    timeout_s: float = 300.0

    def still(self, t: float, since: float | None, armed: bool, state: State,
              start_I: np.ndarray) -> float | None:
        """Return since when (sim s) the armed vehicle is still at the start; None if not now."""
        near = float(np.linalg.norm(state.xi_I - start_I)) < self.position_tol_m
        slow = float(np.linalg.norm(state.v_I)) < self.speed_tol_mps
        if not (armed and near and slow):
            return None
        return t if since is None else since


#: ArduPilot: EKF3 uses its GPS ~65 s after boot; its take-off holds within ~7 cm of the
#: height (barometer and EKF: docs/firmware_lockstep.md, the hover check)
ARDUPILOT_START_HOLD = StartHold(arm_after_s=1.0, position_tol_m=0.15)


class _GroundStation:
    """The pilot's GCS on a firmware's link: heartbeat, STATUSTEXT, arming, the settled check.

    A firmware's pilot gives its own ``url``, which HEARTBEATs are the firmware's
    (:meth:`_firmware_heartbeat`, which also sets ``target``) and the commands due at a time
    (:meth:`_command_due`, called every ``hold.command_period_s`` once ``target`` is known).
    """

    def __init__(self, url: str, start_I: np.ndarray, hold: StartHold) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.start_I = np.asarray(start_I, float)
        self.hold = hold
        self.target: tuple | None = None
        self.armed = False
        self.texts: list = []
        self.armed_at_s: float | None = None
        self._next_command = self.hold.arm_after_s
        self._still_since: float | None = None
        self._beat = -math.inf

    def step(self, t: float, state: State) -> bool:
        """Read the firmware, command what is due at sim time ``t``; True once settled."""
        self._read()
        if t - self._beat >= 1.0:
            self._beat = t
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)     # a GCS
        if self.target is not None and t >= self._next_command:
            self._next_command = t + self.hold.command_period_s
            self._command_due(state)
        if self.armed and self.armed_at_s is None:
            self.armed_at_s = t
        self._still_since = self.hold.still(t, self._still_since, self.armed, state,
                                            self.start_I)
        return (self._still_since is not None
                and t - self._still_since >= self.hold.still_for_s)

    def _command_due(self, state: State) -> None:
        raise NotImplementedError

    def _firmware_heartbeat(self, m) -> bool:
        raise NotImplementedError

    def _command(self, cmd: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(*self.target, int(cmd), 0, *p)

    def _read(self) -> None:
        while True:
            try:
                m = self.conn.recv_match(blocking=False)
            except (OSError, ValueError):
                continue
            if m is None:
                return
            kind = m.get_type()
            if kind == 'HEARTBEAT' and self._firmware_heartbeat(m):
                self.target = (m.get_srcSystem(), m.get_srcComponent())
                self.armed = bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == 'STATUSTEXT':
                self.texts = (self.texts + [str(m.text)])[-5:]

    def close(self) -> None:
        """Close the GCS socket."""
        self.conn.close()


class Px4StartPilot(_GroundStation):
    """PX4's take-off and hold at the start, by sim time (see module doc)."""

    def __init__(self, instance: int, start_I: np.ndarray, hold: StartHold | None = None,
                 home: tuple = SIH_DEFAULT_HOME) -> None:
        super().__init__(f'udpout:127.0.0.1:{PX4_GCS_LISTEN_BASE + int(instance)}', start_I,
                         hold or StartHold())
        self.home = home

    def _firmware_heartbeat(self, m) -> bool:
        return m.autopilot == MAV_AUTOPILOT_PX4

    def _command_due(self, state: State) -> None:
        """Send the EKF origin, PX4's take-off and the arming until armed.

        Once armed, a repeated origin or take-off would move PX4's target.
        """
        if self.armed:
            return
        lat, lon, alt = self.home
        self.conn.mav.set_gps_global_origin_send(self.target[0], int(lat * 1e7),
                                                 int(lon * 1e7), int(alt * 1e3), 0)
        self._command(MAV_CMD_NAV_TAKEOFF, -1, 0, 0, math.nan, math.nan, math.nan, math.nan)
        self._command(MAV_CMD_COMPONENT_ARM_DISARM, 1)


class ArduPilotStartPilot(_GroundStation):
    """ArduCopter's GUIDED take-off and hold at the start, by sim time (see module doc).

    ``z_home``: the {I} height (NED, m) of home, the body origin at rest on the floor;
    ``takeoff_m``: the start's height above it.
    """

    def __init__(self, instance: int, start_I: np.ndarray, z_home: float, takeoff_m: float,
                 hold: StartHold | None = None) -> None:
        super().__init__(f'udpin:127.0.0.1:{ARDUPILOT_GCS_SEND_BASE + int(instance)}',
                         start_I, hold or ARDUPILOT_START_HOLD)
        self.z_home, self.takeoff_m = float(z_home), float(takeoff_m)
        self.mode: int | None = None

    def _firmware_heartbeat(self, m) -> bool:
        if m.get_srcComponent() != 1 or m.type == 6:       # not a GCS's
            return False
        self.mode = int(m.custom_mode)
        return True

    def _command_due(self, state: State) -> None:
        """GUIDED, then the arming, then ArduCopter's take-off (once: one in the air re-aims)."""
        if self.mode != ARDUCOPTER_MODE_GUIDED:
            self.conn.mav.set_mode_send(self.target[0], 1, ARDUCOPTER_MODE_GUIDED)
        elif not self.armed:
            self._command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
        elif self.z_home - float(state.xi_I[2]) < 0.5 * self.takeoff_m:
            self._command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, self.takeoff_m)
