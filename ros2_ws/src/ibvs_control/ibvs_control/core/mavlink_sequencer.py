"""Arming / flight-mode state machine of the MAVLink bridge (ROS-free, no I/O).

The sequencer decides *which commands* to send to the autopilot and *when*; the bridge sends
them. Sequences (docs/mavlink.md):

PX4
    stream setpoints for more than ``prestream_s`` (PX4 refuses OFFBOARD without a setpoint
    stream), then ``MAV_CMD_DO_SET_MODE`` with param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED (1)
    and param2 = 6 (OFFBOARD main mode; NOT the packed ``6 << 16``, which PX4 acknowledges and
    ignores); wait for COMMAND_ACK *and* a HEARTBEAT whose custom_mode main mode
    (bits 16-23) is 6; then ``MAV_CMD_COMPONENT_ARM_DISARM`` (param1 = 1) unless armed.
ArduPilot (Copter)
    read ``GUID_OPTIONS`` first and refuse (state REFUSED) unless bit 3 is set (thrust is
    then read as thrust, not as a climb rate); then ``MAV_CMD_DO_SET_MODE`` (1, 20 =
    GUIDED_NOGPS), check the HEARTBEAT's custom_mode == 20, then arm.

Engagement starts when the supervisor leaves IDLE for a flying mode; before that the bridge
streams but does not switch. In SHUTDOWN the bridge ramps the thrust down (see
:class:`mavlink_bridge.SetpointShaper`) and the sequencer disarms when the ramp has ended
(``MAV_CMD_COMPONENT_ARM_DISARM`` param1 = 0; if the autopilot refuses - in the air a PX4 or
ArduPilot does - again with param2 = 21196, the force magic). After a link loss the
autopilot's own offboard-loss failsafe has the vehicle; the sequencer re-engages only when the
link is back *and* the supervisor is still in a flying mode.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, IntEnum

from ibvs_control.core.modes import FLYING_MODES, Mode


class MavCmd(IntEnum):
    """MAV_CMD ids sent by the sequencer."""

    DO_SET_MODE = 176
    COMPONENT_ARM_DISARM = 400


class MavResult(IntEnum):
    """MAV_RESULT of COMMAND_ACK."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5


class Autopilot(Enum):
    """Autopilot flavour (decides the offboard mode and parameter names)."""

    PX4 = 'px4'
    ARDUPILOT = 'ardupilot'


MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
PX4_MAIN_MODE_OFFBOARD = 6             # PX4 custom main mode (custom_mode bits 16-23)
PX4_MAIN_MODE_SHIFT = 16
ARDUCOPTER_MODE_GUIDED_NOGPS = 20      # ArduCopter custom_mode
GUID_OPTIONS_THRUST_BIT = 1 << 3       # ArduPilot GUID_OPTIONS bit 3: "SetAttitudeTarget
#                                        interprets thrust as thrust" (not climb rate)
ARM_DISARM_FORCE_MAGIC = 21196         # param2 of COMPONENT_ARM_DISARM: force (dis)arm


def px4_main_mode(custom_mode: int) -> int:
    """PX4 main mode of a HEARTBEAT custom_mode (bits 16-23; sub mode is bits 24-31)."""
    return (int(custom_mode) >> PX4_MAIN_MODE_SHIFT) & 0xFF


class EngageState(Enum):
    """States of :class:`EngageSequencer` (reported on /diagnostics)."""

    NO_LINK = 'no_link'              # no autopilot heartbeat (never, or lost)
    PREFLIGHT = 'preflight'          # link up, waiting for the parameters it needs
    STANDBY = 'standby'              # streaming; supervisor IDLE: do not switch
    SET_MODE = 'set_mode'            # DO_SET_MODE sent, waiting for ACK + heartbeat mode
    ARMING = 'arming'                # in the offboard mode, arming
    ENGAGED = 'engaged'              # offboard and armed: the IBVS setpoints fly
    SHUTDOWN_RAMP = 'shutdown_ramp'  # mode 4: thrust ramping down
    DISARMING = 'disarming'          # ramp ended, disarm sent
    DONE = 'done'                    # disarmed after the shutdown
    HELD = 'held'                    # not flying the IBVS setpoints; autopilot in charge
    REFUSED = 'refused'              # configuration forbids flying (e.g. GUID_OPTIONS)
    FAILED = 'failed'                # mode switch or arming failed after all retries


@dataclass(frozen=True)
class SequencerConfig:
    """Timing of the sequences (s) and the number of command attempts."""

    autopilot: Autopilot = Autopilot.PX4
    prestream_s: float = 1.2         # PX4: setpoint stream length before OFFBOARD (> 1 s)
    command_retry_s: float = 1.0     # resend an unanswered/refused command after this
    max_attempts: int = 5            # then FAILED
    disarm_force_after_s: float = 1.0  # refused or ignored disarm: force after this


@dataclass(frozen=True)
class CommandRequest:
    """A COMMAND_LONG the bridge must send now."""

    command: MavCmd
    params: tuple[float, ...]
    reason: str


@dataclass(frozen=True)
class SequencerInputs:
    """What the sequencer needs to know at one step."""

    t: float                           # monotonic s
    link_up: bool
    supervisor_mode: Mode
    armed: bool = False
    custom_mode: int = 0
    streaming_s: float = 0.0           # how long setpoints have been streamed without a gap
    hover_thrust_ready: bool = False
    guid_options: int | None = None    # ArduPilot parameter (None: not read yet)
    params_timed_out: bool = False     # the parameter requests got no answer in time
    ramp_done: bool = False            # SetpointShaper: the mode-4 ramp has ended


@dataclass
class _Pending:
    command: MavCmd
    sent_t: float
    attempts: int
    ack: MavResult | None = None


@dataclass
class EngageSequencer:
    """The arming / mode state machine. Call :meth:`step` periodically, feed ACKs."""

    config: SequencerConfig = field(default_factory=SequencerConfig)
    state: EngageState = EngageState.NO_LINK
    engaged_once: bool = False         # were we ever engaged (re-engage after link loss)
    disarm_forced: bool = False
    _held_for_link_loss: bool = False  # HELD because of a link loss (may re-engage)
    last_reason: str = ''
    _pending: _Pending | None = None
    _events: list = field(default_factory=list)

    # --- inputs ------------------------------------------------------------------------
    def on_command_ack(self, command: int, result: int) -> None:
        """Record a COMMAND_ACK for the command we are waiting on."""
        if self._pending is not None and int(command) == int(self._pending.command):
            try:
                self._pending.ack = MavResult(int(result))
            except ValueError:
                self._pending.ack = MavResult.FAILED

    def pop_events(self) -> list[str]:
        """Human-readable transitions since the last call (for the node's log)."""
        events, self._events = self._events, []
        return events

    # --- helpers -----------------------------------------------------------------------
    def _go(self, state: EngageState, reason: str) -> None:
        if state != self.state:
            self._events.append(f'{self.state.value} -> {state.value}: {reason}')
            self.state = state
            self.last_reason = reason
            self._pending = None

    def in_offboard(self, custom_mode: int) -> bool:
        """Whether the HEARTBEAT custom_mode is the bridge's offboard mode."""
        if self.config.autopilot == Autopilot.PX4:
            return px4_main_mode(custom_mode) == PX4_MAIN_MODE_OFFBOARD
        return int(custom_mode) == ARDUCOPTER_MODE_GUIDED_NOGPS

    def _mode_params(self) -> tuple[float, ...]:
        mode = (PX4_MAIN_MODE_OFFBOARD if self.config.autopilot == Autopilot.PX4
                else ARDUCOPTER_MODE_GUIDED_NOGPS)
        return (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(mode))

    def _command(self, t: float, command: MavCmd, params: tuple[float, ...],
                 reason: str) -> list[CommandRequest]:
        """Send (or resend after command_retry_s) a command; FAILED after max_attempts."""
        p = self._pending
        if p is not None and p.command == command:
            if t - p.sent_t < self.config.command_retry_s:
                return []  # answered or not, the heartbeat tells whether it took effect
            if p.attempts >= self.config.max_attempts:
                self._go(EngageState.FAILED, f'{command.name} not effective after '
                         f'{p.attempts} attempts (last ack: {p.ack})')
                return []
            attempts = p.attempts + 1
        else:
            attempts = 1
        self._pending = _Pending(command, t, attempts)
        return [CommandRequest(command, params, reason)]

    # --- the machine -------------------------------------------------------------------
    def step(self, inp: SequencerInputs) -> list[CommandRequest]:
        """Advance the machine; return the commands to send now."""
        s = self.state
        if not inp.link_up:
            if s not in (EngageState.NO_LINK, EngageState.REFUSED, EngageState.DONE):
                self._go(EngageState.NO_LINK, 'autopilot heartbeat lost: the autopilot '
                         'failsafe has the vehicle')
            return []
        if s in (EngageState.REFUSED, EngageState.DONE, EngageState.FAILED):
            return []
        if s == EngageState.NO_LINK:
            self._go(EngageState.PREFLIGHT, 'autopilot heartbeat received')
            s = self.state
        flying = inp.supervisor_mode in FLYING_MODES
        if s == EngageState.PREFLIGHT:
            return self._preflight(inp)
        if s in (EngageState.STANDBY, EngageState.HELD):
            if s == EngageState.STANDBY and flying and not self.engaged_once:
                self._go(EngageState.SET_MODE, f'supervisor mode {inp.supervisor_mode.name}')
            elif s == EngageState.HELD and flying and self._held_for_link_loss:
                self._go(EngageState.SET_MODE, 'link back, supervisor still flying: '
                         're-engaging')
            else:
                return []
            s = self.state
        if s in (EngageState.SET_MODE, EngageState.ARMING) and not flying:
            self._go(EngageState.HELD, f'supervisor mode {inp.supervisor_mode.name} before '
                     'engagement: not switching')
            self._held_for_link_loss = False
            return []
        if s == EngageState.SET_MODE:
            return self._set_mode(inp)
        if s == EngageState.ARMING:
            return self._arming(inp)
        if s == EngageState.ENGAGED:
            return self._engaged(inp)
        if s == EngageState.SHUTDOWN_RAMP:
            if not inp.armed:
                self._go(EngageState.DONE, 'disarmed during the ramp')
            elif inp.ramp_done:
                self._go(EngageState.DISARMING, 'thrust ramp ended')
                return self._disarm(inp)
            return []
        if s == EngageState.DISARMING:
            return self._disarm(inp)
        return []

    def _preflight(self, inp: SequencerInputs) -> list[CommandRequest]:
        if self.config.autopilot == Autopilot.ARDUPILOT:
            if inp.guid_options is None:
                if inp.params_timed_out:
                    self._go(EngageState.REFUSED, 'GUID_OPTIONS could not be read: refusing '
                             'to fly (thrust might be read as a climb rate)')
                return []
            if not int(inp.guid_options) & GUID_OPTIONS_THRUST_BIT:
                self._go(EngageState.REFUSED, f'GUID_OPTIONS = {int(inp.guid_options)} lacks '
                         'bit 3 (SET_ATTITUDE_TARGET thrust as thrust): refusing to fly; '
                         'set GUID_OPTIONS |= 8 on the autopilot')
                return []
        if not inp.hover_thrust_ready:
            return []
        if self.engaged_once:
            self._go(EngageState.HELD, 'link back')
            self._held_for_link_loss = True
        else:
            self._go(EngageState.STANDBY, 'parameters ready; streaming')
        return []

    def _set_mode(self, inp: SequencerInputs) -> list[CommandRequest]:
        if self.in_offboard(inp.custom_mode):
            self._go(EngageState.ARMING, f'autopilot reports custom_mode {inp.custom_mode}')
            return self._arming(inp)
        if (self.config.autopilot == Autopilot.PX4
                and inp.streaming_s <= self.config.prestream_s):
            return []  # PX4 needs a setpoint stream of > 1 s before OFFBOARD
        return self._command(inp.t, MavCmd.DO_SET_MODE, self._mode_params(),
                             'switch to the offboard mode')

    def _arming(self, inp: SequencerInputs) -> list[CommandRequest]:
        if not self.in_offboard(inp.custom_mode):
            self._go(EngageState.SET_MODE, 'autopilot left the offboard mode while arming')
            return []
        if inp.armed:
            self.engaged_once = True
            self._held_for_link_loss = False
            self._go(EngageState.ENGAGED, 'offboard and armed')
            return []
        return self._command(inp.t, MavCmd.COMPONENT_ARM_DISARM, (1.0,), 'arm')

    def _engaged(self, inp: SequencerInputs) -> list[CommandRequest]:
        if inp.supervisor_mode == Mode.SHUTDOWN:
            self._go(EngageState.SHUTDOWN_RAMP, 'supervisor SHUTDOWN: ramping thrust down')
            return []
        if not self.in_offboard(inp.custom_mode):
            self._go(EngageState.HELD, f'autopilot left the offboard mode (custom_mode '
                     f'{inp.custom_mode}): pilot or autopilot failsafe in charge')
            self._held_for_link_loss = False
            return []
        if not inp.armed:
            self._go(EngageState.HELD, 'autopilot disarmed in flight')
            self._held_for_link_loss = False
        return []

    def _disarm(self, inp: SequencerInputs) -> list[CommandRequest]:
        if not inp.armed:
            self._go(EngageState.DONE, 'disarmed' + (' (forced)' if self.disarm_forced else ''))
            return []
        p = self._pending
        refused = p is not None and p.ack not in (
            None, MavResult.ACCEPTED, MavResult.IN_PROGRESS)
        ignored = p is not None and inp.t - p.sent_t >= self.config.disarm_force_after_s
        if p is None or not (refused or ignored):
            if p is None:
                self._pending = _Pending(MavCmd.COMPONENT_ARM_DISARM, inp.t, 1)
                return [CommandRequest(MavCmd.COMPONENT_ARM_DISARM, (0.0,), 'disarm')]
            return []
        if p.attempts >= self.config.max_attempts:
            self._go(EngageState.FAILED, 'disarm not effective, even forced')
            return []
        self.disarm_forced = True
        self._pending = _Pending(MavCmd.COMPONENT_ARM_DISARM, inp.t, p.attempts + 1)
        return [CommandRequest(MavCmd.COMPONENT_ARM_DISARM,
                               (0.0, float(ARM_DISARM_FORCE_MAGIC)),
                               f'disarm refused or ignored ({p.ack}): forcing')]
