"""The autopilot parameters the bridge reads, and what they imply (docs/mavlink.md).

Required (the engage sequencer waits for them, then falls back or refuses after
``timeout_s`` of the bridge's clock):

- the hover-thrust parameter, PX4 ``MPC_THR_HOVER`` / ArduPilot ``MOT_THST_HOVER``: the seed
  of the online hover-thrust estimate (:class:`~ibvs_control.mavlink.hover.HoverThrustSeed`,
  when it is to come from the autopilot);
- on ArduPilot, ``GUID_OPTIONS`` (bit 3: GUIDED_NOGPS takes thrust, not climb rate) and
  ``ATC_ANGLE_BOOST`` (ArduPilot divides the thrust by cos(tilt) itself: the bridge then sends
  the vertical component of F, so that the tilt is not compensated twice; unread: ArduPilot's
  default 1 is assumed).

Advisory (read ``ADVISORY_PARAM_READS`` times, reported once, never required): what the
autopilot does when this bridge dies or its setpoints stop: PX4 ``COM_OF_LOSS_T`` /
``COM_OBL_RC_ACT``, ArduPilot ``FS_GCS_ENABLE`` / ``SYSID_MYGCS``.

:class:`AutopilotParams` keeps what was read, says which reads are due and returns log
events; the bridge sends the reads and applies the results (seed, tilt boost).
"""
from __future__ import annotations

import enum
import math
import struct

import numpy as np

from ibvs_control.mavlink.hover import HoverThrustSeed
from ibvs_control.mavlink.sequencer import Autopilot

HOVER_PARAM = {Autopilot.PX4: 'MPC_THR_HOVER', Autopilot.ARDUPILOT: 'MOT_THST_HOVER'}
GUID_OPTIONS_PARAM = 'GUID_OPTIONS'
ANGLE_BOOST_PARAM = 'ATC_ANGLE_BOOST'
ARDUPILOT_ANGLE_BOOST_DEFAULT = 1
# ArduPilot's GCS failsafe: the only thing that lands the vehicle when this bridge dies in
# GUIDED_NOGPS (GUID_TIMEOUT only levels it and keeps the last thrust); read, never required
GCS_FAILSAFE_PARAM, MY_GCS_PARAM = 'FS_GCS_ENABLE', 'SYSID_MYGCS'
# ... and its timing: the last attitude target is flown GUID_TIMEOUT (default 3 s), then the
# vehicle is levelled at its height and coasts (GUIDED_NOGPS holds no position) until
# FS_GCS_TIMEOUT (default 5 s, at least 2) without our HEARTBEAT; then LAND, which first holds
# 4 s. The bridge killed in WINDOW on ArduCopter 4.5.6 in lockstep: GUID_TIMEOUT 3 s flew into
# the window frame; 1 s stopped 0.31 m from the wall and touched it landing; 0.5 s, 0.44 m
GUID_TIMEOUT_PARAM, GCS_TIMEOUT_PARAM = 'GUID_TIMEOUT', 'FS_GCS_TIMEOUT'
ARDUPILOT_GUID_TIMEOUT_MAX_S = 1.0   # s, a longer GUID_TIMEOUT is warned about (default 3 s)
ARDUPILOT_GCS_TIMEOUT_MAX_S = 3.0    # s, a longer FS_GCS_TIMEOUT is warned about (default 5 s)
ARDUPILOT_TIMEOUT_MAX_S = {GUID_TIMEOUT_PARAM: ARDUPILOT_GUID_TIMEOUT_MAX_S,
                           GCS_TIMEOUT_PARAM: ARDUPILOT_GCS_TIMEOUT_MAX_S}
# PX4's offboard-loss failsafe: what acts when the bridge stops streaming or dies (read, never
# required). COM_OBL_RC_ACT (PX4 v1.16; the action with or without RC):
OFFBOARD_LOSS_T_PARAM, OFFBOARD_LOSS_ACT_PARAM = 'COM_OF_LOSS_T', 'COM_OBL_RC_ACT'
PX4_OFFBOARD_LOSS_ACTIONS = {0: 'Position mode', 1: 'Altitude mode', 2: 'Manual', 3: 'Return mode',
                             4: 'Land mode', 5: 'Hold mode', 6: 'Terminate', 7: 'Disarm'}
PX4_OFFBOARD_LOSS_LAND = 4
PX4_OFFBOARD_LOSS_T_MAX_S = 2.0   # s, a longer time-out is warned about (PX4's default: 1 s)
# the pair that says whether the autopilot lands a dead bridge's vehicle at all
FAILSAFE_PAIR = {Autopilot.ARDUPILOT: (GCS_FAILSAFE_PARAM, MY_GCS_PARAM),
                 Autopilot.PX4: (OFFBOARD_LOSS_T_PARAM, OFFBOARD_LOSS_ACT_PARAM)}
DEAD_BRIDGE_PARAMS = {Autopilot.ARDUPILOT: (*FAILSAFE_PAIR[Autopilot.ARDUPILOT],
                                            GUID_TIMEOUT_PARAM, GCS_TIMEOUT_PARAM),
                      Autopilot.PX4: FAILSAFE_PAIR[Autopilot.PX4]}
MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 6, 9
ADVISORY_PARAM_READS = 30     # read requests (every retry_s) before giving them up
_NEEDS_POSITION = 'needs a position estimate, which this vehicle does not have'
_NEEDS_PILOT = 'needs a pilot on the sticks'
_STOPS_MOTORS = 'stops the motors in the air'
PX4_OFFBOARD_LOSS_WHY = {0: _NEEDS_POSITION, 3: _NEEDS_POSITION, 5: _NEEDS_POSITION,
                         1: _NEEDS_PILOT, 2: _NEEDS_PILOT, 6: _STOPS_MOTORS, 7: _STOPS_MOTORS}


def param_value(value: float, param_type: int, bytewise: bool) -> float:
    """Return the value of a PARAM_VALUE's ``param_value`` field of type ``param_type``.

    PX4 copies an integer parameter's bytes into the float field (MAVLink's bytewise parameter
    encoding, its MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); ArduPilot casts the integer
    to a float (C-cast encoding). ``bytewise``: the autopilot's encoding is bytewise.
    """
    if not bytewise or param_type == MAV_PARAM_TYPE_REAL32:
        return value
    fmt = '<i' if param_type == MAV_PARAM_TYPE_INT32 else '<I'    # PX4: INT32 only
    return float(struct.unpack(fmt, struct.pack('<f', value))[0])


class Changed(enum.Flag):
    """What a parameter value or a time-out changed, for the bridge to apply."""

    NOTHING = 0
    SEED = enum.auto()           # the hover-thrust seed is now known: start the estimator
    TILT_BOOST = enum.auto()     # whether the autopilot boosts the thrust in a tilt


class AutopilotParams:
    """What the bridge read of the autopilot's parameters; which reads are due; events."""

    def __init__(self, seed: HoverThrustSeed, source_system: int, retry_s: float,
                 timeout_s: float) -> None:
        """Read for ``seed``; ``source_system``: this bridge's MAVLink system id.

        ``retry_s``, ``timeout_s``: s of the bridge's clock between reads of an unanswered
        parameter, and before the required ones fall back (seed) or refuse (GUID_OPTIONS).
        """
        self.seed = seed
        self.source_system = int(source_system)
        self.retry_s, self.timeout_s = float(retry_s), float(timeout_s)
        self.autopilot: Autopilot | None = None      # set by the bridge once known
        self.guid_options: int | None = None
        self.angle_boost: int | None = None
        self.dead_bridge_params: dict = {}   # DEAD_BRIDGE_PARAMS of the autopilot, as read
        self.dead_bridge_failsafe: bool | None = None   # None: unknown (not read yet)
        self._since: float | None = None
        self._last_request = -math.inf
        self._advisory_reads = 0
        self._events: list[tuple[str, str]] = []

    @property
    def tilt_boosted_by_autopilot(self) -> bool:
        """Whether the autopilot divides the thrust by cos(tilt) itself (ArduPilot boost)."""
        return self.autopilot == Autopilot.ARDUPILOT and bool(self.angle_boost)

    def pop_events(self) -> list[tuple[str, str]]:
        """(level, text) events since the last call: 'info', 'warn' or 'error'."""
        events, self._events = self._events, []
        return events

    def timed_out(self, now: float) -> bool:
        """Whether ``timeout_s`` passed since the first read was due (``now``: bridge clock)."""
        return self._since is not None and now - self._since >= self.timeout_s

    def missing(self) -> list[str]:
        """Return the required parameters not known yet."""
        if self.autopilot is None:
            return []
        out = [HOVER_PARAM[self.autopilot]] if self.seed.value is None else []
        if self.autopilot == Autopilot.ARDUPILOT:
            out += [name for name, v in ((GUID_OPTIONS_PARAM, self.guid_options),
                                         (ANGLE_BOOST_PARAM, self.angle_boost)) if v is None]
        return out

    def due(self, now: float) -> tuple[list[str], Changed]:
        """Return (names to read now, what a time-out changed) at ``now`` (bridge clock)."""
        if self._since is None:
            self._since = now
        missing = self.missing()
        advisory = [n for n in DEAD_BRIDGE_PARAMS.get(self.autopilot, ())
                    if n not in self.dead_bridge_params
                    and self._advisory_reads < ADVISORY_PARAM_READS]
        reads: list[str] = []
        if (missing or advisory) and now - self._last_request >= self.retry_s:
            self._last_request = now
            self._advisory_reads += bool(advisory)
            reads = missing + advisory
        changed = Changed.NOTHING
        if missing and self.timed_out(now):
            had_seed = self.seed.value is not None
            self.seed.on_timeout()
            if not had_seed and self.seed.value is not None:
                changed |= Changed.SEED
            if self.autopilot == Autopilot.ARDUPILOT and self.angle_boost is None:
                changed |= self._set_angle_boost(
                    ARDUPILOT_ANGLE_BOOST_DEFAULT, f"{ANGLE_BOOST_PARAM} unread: assuming "
                    f"ArduPilot's default {ARDUPILOT_ANGLE_BOOST_DEFAULT}")
        return reads, changed

    def on_param(self, raw_name: bytes | str, value: float) -> Changed:
        """Take one PARAM_VALUE (name as bytes or str, value decoded); return what changed."""
        name = raw_name.decode('ascii', 'replace') if isinstance(raw_name, bytes) else raw_name
        name = name.rstrip('\x00')
        if self.autopilot is not None and name == HOVER_PARAM[self.autopilot] \
                and self.seed.use_autopilot and self.seed.source == 'pending':
            self.seed.on_param(name, value)
            if self.seed.error:
                self._events.append(('error', self.seed.error))
            else:
                self._events.append(('info', f'hover thrust seed {value:.3f} from {name}'))
            return Changed.SEED
        if name == GUID_OPTIONS_PARAM and np.isfinite(value):
            self.guid_options = int(value)
        elif name == ANGLE_BOOST_PARAM and np.isfinite(value) and self.angle_boost is None:
            return self._set_angle_boost(int(value), f'{ANGLE_BOOST_PARAM} = {int(value)}')
        elif self.autopilot is not None and name in DEAD_BRIDGE_PARAMS[self.autopilot] \
                and np.isfinite(value) and name not in self.dead_bridge_params:
            self.dead_bridge_params[name] = value
            if name in ARDUPILOT_TIMEOUT_MAX_S:
                self._assess_ardupilot_timeout(name, value)
            elif all(n in self.dead_bridge_params for n in FAILSAFE_PAIR[self.autopilot]) \
                    and self.dead_bridge_failsafe is None:
                if self.autopilot == Autopilot.PX4:
                    self._assess_px4_offboard_loss()
                else:
                    self._assess_ardupilot_gcs_failsafe()
        return Changed.NOTHING

    def _assess_ardupilot_timeout(self, name: str, value: float) -> None:
        """Warn (once) about a long GUID_TIMEOUT or FS_GCS_TIMEOUT.

        Either lets a dead bridge's vehicle fly on (docs/mavlink.md "Autopilot set-up").
        """
        limit = ARDUPILOT_TIMEOUT_MAX_S[name]
        if value <= limit:
            return
        what = ('flies the last attitude target' if name == GUID_TIMEOUT_PARAM
                else 'coasts, levelled at its height, before LAND')
        self._events.append((
            'warn', f'ArduPilot {name} = {value:g} s: if this bridge dies in flight the vehicle '
                    f'{what} that long (at most {limit:g} s advised; the bridge killed in the '
                    'approach with the defaults flew the vehicle into the window frame)'))

    def _set_angle_boost(self, value: int, why: str) -> Changed:
        self.angle_boost = value
        self._events.append(('info', f'{why}: ' + (
            'ArduPilot boosts the thrust by 1/cos(tilt) itself, the bridge sends the vertical '
            'component of F' if self.tilt_boosted_by_autopilot else 'the bridge sends |F|')))
        return Changed.TILT_BOOST

    def _assess_px4_offboard_loss(self) -> None:
        """Tell (once) what PX4 does when our setpoints stop (bridge dead or forces lost)."""
        p = self.dead_bridge_params
        action, timeout = int(p[OFFBOARD_LOSS_ACT_PARAM]), float(p[OFFBOARD_LOSS_T_PARAM])
        what = PX4_OFFBOARD_LOSS_ACTIONS.get(action, 'unknown')
        self.dead_bridge_failsafe = action == PX4_OFFBOARD_LOSS_LAND
        said = f'{OFFBOARD_LOSS_ACT_PARAM} = {action} ({what}), {OFFBOARD_LOSS_T_PARAM} = ' \
               f'{timeout:g} s'
        if self.dead_bridge_failsafe:
            self._events.append((
                'info', f'dead-bridge failsafe: {said}: PX4 lands when our setpoints stop '
                        '(the bridge stops them hold_last_s after the last force)'))
        else:
            why = PX4_OFFBOARD_LOSS_WHY.get(action, 'is not an action of PX4 v1.16')
            self._events.append((
                'warn', f'PX4 offboard loss: {said}: {what} {why} (without RC PX4 falls back '
                        f'to its own failsafe); set {OFFBOARD_LOSS_ACT_PARAM} = '
                        f'{PX4_OFFBOARD_LOSS_LAND} (Land mode) (docs/mavlink.md '
                        '"Autopilot set-up")'))
        if timeout > PX4_OFFBOARD_LOSS_T_MAX_S:
            self._events.append((
                'warn', f'PX4 offboard loss: {OFFBOARD_LOSS_T_PARAM} = {timeout:g} s: the '
                        'vehicle flies the last setpoint that long after ours stop (PX4 '
                        f'default 1 s; at most {PX4_OFFBOARD_LOSS_T_MAX_S:g} s advised)'))

    def _assess_ardupilot_gcs_failsafe(self) -> None:
        """Tell (once) whether ArduPilot will land the vehicle if this bridge dies in flight."""
        p = {k: int(v) for k, v in self.dead_bridge_params.items()}
        ours = self.source_system
        enabled, gcs = p[GCS_FAILSAFE_PARAM], p[MY_GCS_PARAM]
        self.dead_bridge_failsafe = enabled != 0 and gcs == ours
        if self.dead_bridge_failsafe:
            self._events.append((
                'info', f'dead-bridge failsafe: {GCS_FAILSAFE_PARAM} = {enabled} and '
                        f'{MY_GCS_PARAM} = {gcs} (this bridge): ArduPilot acts when our '
                        'HEARTBEAT stops'))
            return
        why = (f'{GCS_FAILSAFE_PARAM} = 0' if enabled == 0 else
               f"{MY_GCS_PARAM} = {gcs} is not this bridge's system id {ours}")
        self._events.append((
            'warn', f'no dead-bridge failsafe ({why}): if this bridge dies in flight, '
                    'GUIDED_NOGPS levels the vehicle and keeps its last thrust; set '
                    f'{GCS_FAILSAFE_PARAM} = 5 (land) and {MY_GCS_PARAM} = {ours} '
                    '(docs/mavlink.md "Autopilot set-up")'))
