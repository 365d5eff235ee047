"""The engage / arm / hand-back state machine of the MAVLink bridge (ROS-free, no I/O).

The sequencer decides which commands go to the autopilot, when, and whether setpoints stream;
the bridge sends them. It carries out the safety policy (docs/mavlink.md, "Engage, arm, hand
back" and "Safety policy"). What differs between autopilots (modes, their commands, preflight
checks, when setpoints may stream) is an :class:`AutopilotStrategy`:
:mod:`~ibvs_control.mavlink.sequencer.px4` and :mod:`~ibvs_control.mavlink.sequencer.ardupilot`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum, IntEnum

from ibvs_common.core.modes import FLYING_MODES, Mode
from ibvs_common.core.params import param


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


MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1   # DO_SET_MODE param1: param2 is a custom mode
ARM_DISARM_FORCE_MAGIC = 21196         # param2 of COMPONENT_ARM_DISARM: force (dis)arm
INPUT_LOSS_ACTIONS = ('auto', 'stop', 'land')


class SwitchWait(Enum):
    """Why the switch to the offboard mode waits (:meth:`AutopilotStrategy.switch_wait`)."""

    NONE = 'none'                    # switch now
    STREAM = 'stream'                # the setpoint stream is not long enough yet
    ARMABLE = 'armable'              # the autopilot is not armable yet


class EngageState(Enum):
    """States of :class:`EngageSequencer` (reported on /diagnostics)."""

    NO_LINK = 'no_link'              # no autopilot heartbeat (never, or lost)
    PREFLIGHT = 'preflight'          # link up, waiting for the parameters it needs
    STANDBY = 'standby'              # supervisor IDLE (PX4: streaming); not engaged
    SET_MODE = 'set_mode'            # DO_SET_MODE sent, waiting for the heartbeat's mode
    WAIT_ARM = 'wait_arm'            # in the offboard mode, disarmed, no arm request
    ARMING = 'arming'                # in the offboard mode, arming on request
    ENGAGED = 'engaged'              # offboard and armed: the IBVS setpoints fly
    SHUTDOWN_RAMP = 'shutdown_ramp'  # mode 4: thrust ramping down
    DISARMING = 'disarming'          # ramp ended, disarm sent (touchdown rule for the force)
    LANDING = 'landing'              # the autopilot's land mode asked for / flying
    DONE = 'done'                    # disarmed after a shutdown or a landing
    HELD = 'held'                    # not streaming; the pilot / autopilot is in charge
    REFUSED = 'refused'              # configuration forbids flying (e.g. GUID_OPTIONS)
    FAILED = 'failed'                # mode switch or arming failed after all retries


# States where the bridge was flying the vehicle (a link loss there hands it to the autopilot;
# leaving them for HELD, NO_LINK or FAILED releases the mission: bridge.py, pilot_switch.py).
FLIGHT_STATES = (EngageState.SET_MODE, EngageState.WAIT_ARM, EngageState.ARMING,
                 EngageState.ENGAGED)
_SHUTDOWN_STATES = (EngageState.SHUTDOWN_RAMP, EngageState.DISARMING, EngageState.LANDING)


@dataclass(frozen=True)
class SequencerConfig:
    """Timing of the sequences (s), command attempts and the input-loss action."""

    prestream_s: float = param(
        1.2, 's (steady clock), PX4: setpoint stream before OFFBOARD (> 1 s)', 0.0, None)
    command_retry_s: float = param(
        1.0, 's (steady clock), resend an ineffective command after this', 0.0, None)
    max_attempts: int = param(5, 'mode-switch attempts before FAILED', 1, None)
    arm_backoff_max_s: float = param(
        8.0, 's (steady clock), arming retries back off (doubling) up to this', 0.0, None)
    arm_timeout_s: float = param(60.0, 's (steady clock), arming refused this long: FAILED',
                                 0.0, None)
    armable_unknown_wait_s: float = param(
        1.0, 's (steady clock), disarmed and no SYS_STATUS pre-arm report yet: the mode switch '
        'waits this long for one, then tries', 0.0, None)
    disarm_force_after_s: float = param(
        1.0, 's (ROS clock, IMU stamps), touchdown rule: evidence and first refusal this old '
        'before a forced disarm', 0.0, None)
    disarm_timeout_s: float = param(
        10.0, "s (steady clock), still armed this long after the ramp: the autopilot's land "
        'mode', 0.0, None)
    input_loss_action: str = param(
        'auto', 'forces lost: stop | land | auto (PX4: stop, ArduPilot: land)')

    def __post_init__(self):
        if self.input_loss_action not in INPUT_LOSS_ACTIONS:
            raise ValueError(f'input_loss_action must be one of {INPUT_LOSS_ACTIONS}, not '
                             f'{self.input_loss_action!r}')
        for name in ('prestream_s', 'command_retry_s', 'arm_backoff_max_s', 'arm_timeout_s',
                     'armable_unknown_wait_s', 'disarm_force_after_s', 'disarm_timeout_s'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be > 0')
        if int(self.max_attempts) < 1:
            raise ValueError('max_attempts must be >= 1')


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
    idle_reports: int = 0              # IDLE reports of the supervisor so far
    armed: bool = False
    custom_mode: int = 0
    streaming_s: float = 0.0           # how long setpoints have been streamed without a gap
    hover_thrust_ready: bool = False
    guid_options: int | None = None    # ArduPilot parameter (None: not read yet)
    params_timed_out: bool = False     # the parameter requests got no answer in time
    ramp_done: bool = False            # the mode-4 ramp has ended
    armable: bool | None = None        # SYS_STATUS pre-arm bit (None: not reported)
    landed: bool | None = None         # EXTENDED_SYS_STATE (None: not reported)
    inputs_lost: bool = False          # safety: no valid force for hold_last_s while engaged
    touchdown: bool = False            # safety: the touchdown rule holds
    airborne_at_low_thrust: bool = False  # safety: no ground contact, thrust far below hover
    #: monotonic s (``t``'s clock) of the newest autopilot HEARTBEAT; None: not given (a
    #: command is then judged by ``command_retry_s`` alone)
    heartbeat_t: float | None = None


class AutopilotStrategy(ABC):
    """What the sequences need to know of one autopilot: its modes, commands and checks."""

    autopilot: Autopilot
    default_loss_action: str           # input_loss_action 'auto': 'stop' or 'land'
    streams_while_idle: bool           # PREFLIGHT / STANDBY: a keepalive setpoint stream
    streams_before_switch: bool        # SET_MODE: setpoints before the switch is asked for

    @abstractmethod
    def in_offboard(self, custom_mode: int) -> bool:
        """Whether the HEARTBEAT custom_mode is the bridge's offboard mode."""

    @abstractmethod
    def in_land_mode(self, custom_mode: int) -> bool:
        """Whether the HEARTBEAT custom_mode is the autopilot's land mode."""

    @abstractmethod
    def offboard_params(self) -> tuple[float, ...]:
        """DO_SET_MODE params of the offboard mode."""

    @abstractmethod
    def land_params(self) -> tuple[float, ...]:
        """DO_SET_MODE params of the land mode."""

    def refusal(self, inp: SequencerInputs) -> str:
        """Why the configuration forbids flying ('' if it does not, or not known yet)."""
        return ''

    def parameters_ready(self, inp: SequencerInputs) -> bool:
        """Whether the autopilot parameters the checks need have been read."""
        return True

    @abstractmethod
    def switch_wait(self, inp: SequencerInputs, engaging_s: float,
                    config: SequencerConfig) -> SwitchWait:
        """Return what the offboard-mode switch waits for, ``engaging_s`` into SET_MODE."""


@dataclass
class _Pending:
    command: MavCmd
    sent_t: float
    attempts: int
    ack: MavResult | None = None
    forced: bool = False


@dataclass
class EngageSequencer:
    """The engage / arm / hand-back state machine. Call :meth:`step` often, feed ACKs."""

    strategy: AutopilotStrategy
    config: SequencerConfig = field(default_factory=SequencerConfig)
    state: EngageState = EngageState.NO_LINK
    disarm_forced: bool = False
    arm_requested: bool = False        # ibvs/arm or arm_on_start (cleared once used)
    last_reason: str = ''
    _engaged_at_idle: int = 0          # idle_reports when the last engagement started
    _lost_in: EngageState | None = None   # state when the link was lost
    _pending: _Pending | None = None
    _heartbeat_t: float | None = None  # the newest HEARTBEAT of the last step's inputs
    _entered_t: float = 0.0
    _arm_start_t: float | None = None
    _land_confirmed: bool = False
    _first_refusal_t: float | None = None
    _stopped_on_loss: bool = False     # HELD because the forces stopped ('stop' action)
    _said: set = field(default_factory=set)
    _events: list = field(default_factory=list)

    # --- inputs ------------------------------------------------------------------------
    def on_command_ack(self, command: int, result: int) -> None:
        """Record a COMMAND_ACK for the command we are waiting on."""
        if self._pending is not None and int(command) == int(self._pending.command):
            try:
                self._pending.ack = MavResult(int(result))
            except ValueError:
                self._pending.ack = MavResult.FAILED

    def request_arm(self) -> tuple[bool, str]:
        """Take an arm request (ibvs/arm): latched until used or the vehicle is handed back."""
        if self.state in (EngageState.REFUSED, EngageState.FAILED):
            return False, f'not arming: bridge {self.state.value} ({self.last_reason})'
        self.arm_requested = True
        return True, (f'arm request accepted (bridge {self.state.value}): the bridge arms the '
                      'vehicle once it is in the offboard mode and armable')

    def pop_events(self) -> list[str]:
        """Human-readable transitions since the last call (for the node's log)."""
        events, self._events = self._events, []
        return events

    # --- what the bridge does ----------------------------------------------------------
    @property
    def streaming(self) -> bool:
        """Whether setpoints should stream now (the link being up is checked by the bridge)."""
        s = self.state
        if s == EngageState.SET_MODE and not self.strategy.streams_before_switch \
                and self._pending is None:
            return False
        if s in (EngageState.SET_MODE, EngageState.WAIT_ARM, EngageState.ARMING,
                 EngageState.ENGAGED, EngageState.SHUTDOWN_RAMP, EngageState.DISARMING):
            return True
        if s == EngageState.LANDING:
            return not self._land_confirmed
        return (self.strategy.streams_while_idle
                and s in (EngageState.PREFLIGHT, EngageState.STANDBY))

    @property
    def level_hold(self) -> bool:
        """Whether the content is the level hold (until the autopilot's land mode shows)."""
        return self.state == EngageState.LANDING

    @property
    def engaged(self) -> bool:
        """Whether the IBVS setpoints fly the vehicle."""
        return self.state == EngageState.ENGAGED

    # --- helpers -----------------------------------------------------------------------
    def _go(self, state: EngageState, reason: str, t: float | None = None) -> None:
        if state != self.state:
            self._events.append(f'{self.state.value} -> {state.value}: {reason}')
            self.state = state
            self.last_reason = reason
            self._pending = None
            self._stopped_on_loss = False
            self._said.discard('state')
            if t is not None:
                self._entered_t = t
            if state in (EngageState.HELD, EngageState.DONE, EngageState.FAILED):
                self.arm_requested = False
            if state not in (EngageState.SET_MODE, EngageState.ARMING):
                self._arm_start_t = None        # each engagement's arming has its own time
            if state == EngageState.LANDING:
                self._land_confirmed = False
            if state == EngageState.DISARMING:
                self._first_refusal_t = None

    def _say_once(self, key: str, text: str) -> None:
        """Log ``text`` once per ``key``.

        A 'state' text (what the state waits for) is also the reason /diagnostics shows until
        the next transition.
        """
        if key not in self._said:
            self._said.add(key)
            self._events.append(text)
            if key == 'state':
                self.last_reason = text

    @property
    def loss_action(self) -> str:
        """'stop' or 'land' when the forces are lost (``input_loss_action``)."""
        if self.config.input_loss_action != 'auto':
            return self.config.input_loss_action
        return self.strategy.default_loss_action

    def _command(self, t: float, command: MavCmd, params: tuple[float, ...], reason: str,
                 period: float | None = None) -> list[CommandRequest] | None:
        """Send (or resend after ``period``) a command; None once max_attempts are used."""
        period = self.config.command_retry_s if period is None else period
        p = self._pending
        if p is not None and p.command == command:
            if t - p.sent_t < period:
                return []  # answered or not, the heartbeat tells whether it took effect
            if self._heartbeat_t is not None and self._heartbeat_t <= p.sent_t:
                # no HEARTBEAT since it was sent: whether it took effect is not known yet. A
                # firmware in lockstep slower than real time reports its mode at 1 Hz of its
                # own clock: 5 attempts 1 s apart on this clock saw none (a PX4 campaign run
                # failed "offboard mode not effective" at 0.13 x real time). A link without
                # HEARTBEATs is lost after heartbeat_timeout_s (NO_LINK).
                return []
            if p.attempts >= self.config.max_attempts:
                return None
            attempts = p.attempts + 1
        else:
            attempts = 1
        self._pending = _Pending(command, t, attempts)
        return [CommandRequest(command, params, reason)]

    # --- the machine -------------------------------------------------------------------
    def step(self, inp: SequencerInputs) -> list[CommandRequest]:
        """Advance the machine; return the commands to send now."""
        s = self.state
        self._heartbeat_t = inp.heartbeat_t
        if not inp.link_up:
            if s not in (EngageState.NO_LINK, EngageState.REFUSED, EngageState.DONE,
                         EngageState.FAILED):
                self._lost_in = s
                self._go(EngageState.NO_LINK, 'autopilot heartbeat lost: setpoints stopped, the '
                         "autopilot's own failsafe has the vehicle", inp.t)
            return []
        if s in (EngageState.REFUSED, EngageState.FAILED):
            return []
        if s == EngageState.NO_LINK:
            self._go(EngageState.PREFLIGHT, 'autopilot heartbeat received', inp.t)
            s = self.state
        if s == EngageState.PREFLIGHT:
            return self._preflight(inp)
        handler = {EngageState.STANDBY: self._standby, EngageState.HELD: self._idle_again,
                   EngageState.DONE: self._idle_again, EngageState.SET_MODE: self._set_mode,
                   EngageState.WAIT_ARM: self._arming, EngageState.ARMING: self._arming,
                   EngageState.ENGAGED: self._engaged,
                   EngageState.SHUTDOWN_RAMP: self._shutdown_ramp,
                   EngageState.DISARMING: self._disarming,
                   EngageState.LANDING: self._landing}[s]
        return handler(inp)

    def _preflight(self, inp: SequencerInputs) -> list[CommandRequest]:
        refusal = self.strategy.refusal(inp)
        if refusal:
            self._go(EngageState.REFUSED, refusal, inp.t)
            return []
        if not self.strategy.parameters_ready(inp) or not inp.hover_thrust_ready:
            return []
        lost_in, self._lost_in = self._lost_in, None
        if lost_in in _SHUTDOWN_STATES:
            return self._resolve_shutdown(inp, 'link back during the shutdown')
        if lost_in in FLIGHT_STATES:
            if inp.armed and self.strategy.in_offboard(inp.custom_mode):
                return self._inputs_lost(inp, 'link back, vehicle still in the offboard mode '
                                              'without our setpoints')
            self._go(EngageState.HELD, "link back: the autopilot's failsafe had the vehicle; "
                     'not taking it back', inp.t)
            return []
        self._go(EngageState.STANDBY, 'parameters ready', inp.t)
        return self._standby(inp)

    def _standby(self, inp: SequencerInputs) -> list[CommandRequest]:
        if self.strategy.in_offboard(inp.custom_mode) and inp.armed:
            self._go(EngageState.HELD, f'the autopilot is in the offboard mode (custom_mode '
                     f'{inp.custom_mode}) without the bridge asking: not streaming', inp.t)
            return []
        if inp.supervisor_mode in FLYING_MODES and inp.idle_reports > self._engaged_at_idle:
            self._engaged_at_idle = inp.idle_reports
            self._go(EngageState.SET_MODE, f'supervisor mode {inp.supervisor_mode.name}', inp.t)
            return self._set_mode(inp)
        return []

    def _idle_again(self, inp: SequencerInputs) -> list[CommandRequest]:
        """HELD / DONE: silent; a new engagement needs the supervisor back in IDLE first.

        One exception: setpoints stopped because the forces did, the autopilot still armed in
        the offboard mode (its offboard-loss failsafe has not acted yet) and the supervisor
        now fails safe: the land mode is asked for. A dead camera stops the forces and goes
        stale at the same instant (``hold_last_s`` = the staleness timeouts), and which of the
        two the bridge hears first is a race; PX4 would otherwise fly the last setpoint for
        ``COM_OF_LOSS_T`` more (0.7 m towards the wall in a CI run).
        """
        if self.state == EngageState.HELD and self._stopped_on_loss \
                and inp.supervisor_mode == Mode.FAILSAFE and inp.armed \
                and self.strategy.in_offboard(inp.custom_mode):
            return self._land(inp, 'supervisor FAILSAFE after the forces stopped, the autopilot '
                                   "still in the offboard mode: the autopilot's land mode")
        if inp.supervisor_mode == Mode.IDLE and inp.idle_reports > self._engaged_at_idle:
            self._go(EngageState.STANDBY, 'supervisor IDLE again: ready for a new engagement',
                     inp.t)
        return []

    def _set_mode(self, inp: SequencerInputs) -> list[CommandRequest]:
        asked = self._pending is not None and self._pending.command == MavCmd.DO_SET_MODE
        if inp.supervisor_mode in (Mode.FAILSAFE, Mode.SHUTDOWN) and asked and inp.armed:
            # the switch may have taken effect before its HEARTBEAT (PX4 reports its mode at
            # 1 Hz): the autopilot may be flying our setpoints, which now end
            return self._land(inp, f'supervisor {inp.supervisor_mode.name} after the offboard '
                                   "mode was asked for: the autopilot's land mode")
        if inp.supervisor_mode not in FLYING_MODES:
            self._go(EngageState.HELD, f'supervisor mode {inp.supervisor_mode.name} before '
                     'engagement: not switching', inp.t)
            return []
        if self.strategy.in_offboard(inp.custom_mode):
            self._go(EngageState.ARMING if not inp.armed else EngageState.ENGAGED,
                     f'autopilot reports custom_mode {inp.custom_mode}', inp.t)
            return self._arming(inp) if not inp.armed else []
        wait = self.strategy.switch_wait(inp, inp.t - self._entered_t, self.config)
        if wait == SwitchWait.ARMABLE:
            return self._wait_armable(inp)
        if wait == SwitchWait.STREAM:
            return []
        out = self._command(inp.t, MavCmd.DO_SET_MODE, self.strategy.offboard_params(),
                            'switch to the offboard mode')
        if out is None:
            self._go(EngageState.FAILED, f'offboard mode not effective after '
                     f'{self.config.max_attempts} attempts (last ack: {self._pending.ack})',
                     inp.t)
            return []
        return out

    def _wait_armable(self, inp: SequencerInputs) -> list[CommandRequest]:
        """Not armable yet, and the strategy switches only an armable autopilot: wait.

        An arm request bounds the wait by ``arm_timeout_s``, as in ARMING.
        """
        self._say_once('state', 'waiting for the autopilot to be armable (pre-arm checks '
                                'not passed yet; its reasons are logged) before switching to '
                                'the offboard mode')
        if self.arm_requested:
            if self._arm_start_t is None:
                self._arm_start_t = inp.t
            if inp.t - self._arm_start_t > self.config.arm_timeout_s:
                self._go(EngageState.FAILED, f'not armable after {self.config.arm_timeout_s:.0f}'
                         ' s: the offboard mode was not requested', inp.t)
        return []

    def _arming(self, inp: SequencerInputs) -> list[CommandRequest]:
        if inp.supervisor_mode not in FLYING_MODES:
            self._go(EngageState.HELD, f'supervisor mode {inp.supervisor_mode.name} before '
                     'the vehicle was armed: not arming', inp.t)
            return []
        if not self.strategy.in_offboard(inp.custom_mode):
            self._go(EngageState.HELD, f'autopilot left the offboard mode (custom_mode '
                     f'{inp.custom_mode}) before arming: pilot / GCS in charge', inp.t)
            return []
        if inp.armed:
            self.arm_requested = False
            self._go(EngageState.ENGAGED, 'offboard and armed', inp.t)
            return []
        if not self.arm_requested:
            self._arm_start_t = None
            self._go(EngageState.WAIT_ARM, 'vehicle disarmed: waiting for an arm request '
                     '(ibvs/arm service, or arm_on_start)', inp.t)
            return []
        if self.state == EngageState.WAIT_ARM:
            self._go(EngageState.ARMING, 'arm requested', inp.t)
        if self._arm_start_t is None:
            self._arm_start_t = inp.t
        if inp.t - self._arm_start_t > self.config.arm_timeout_s:
            self._go(EngageState.FAILED, f'not armed after {self.config.arm_timeout_s:.0f} s '
                     f'(last ack: {self._pending.ack if self._pending else None})', inp.t)
            return []
        if inp.armable is False:
            self._say_once('state', 'waiting for the autopilot to be armable (pre-arm checks '
                                    'not passed yet; its reasons are logged)')
            return []
        p = self._pending
        n = p.attempts if p is not None and p.command == MavCmd.COMPONENT_ARM_DISARM else 0
        period = min(self.config.command_retry_s * 2 ** max(n - 1, 0),
                     self.config.arm_backoff_max_s)
        if p is not None and p.ack == MavResult.ACCEPTED:
            # accepted: the armed flag comes with the next HEARTBEAT (PX4: 1 Hz), which can be
            # later than command_retry_s; a second ARM then is noise (issue 13: "ARM is sent
            # twice", measured again on PX4 SITL): wait the longest backoff before resending
            period = self.config.arm_backoff_max_s
        if p is not None and p.command == MavCmd.COMPONENT_ARM_DISARM \
                and inp.t - p.sent_t < period:
            return []
        self._pending = _Pending(MavCmd.COMPONENT_ARM_DISARM, inp.t, n + 1)
        return [CommandRequest(MavCmd.COMPONENT_ARM_DISARM, (1.0,),
                               f'arm (attempt {n + 1}'
                               + (f', last ack {p.ack.name}' if p and p.ack else '') + ')')]

    def _engaged(self, inp: SequencerInputs) -> list[CommandRequest]:
        if inp.supervisor_mode == Mode.SHUTDOWN:
            self._go(EngageState.SHUTDOWN_RAMP, 'supervisor SHUTDOWN: ramping thrust down', inp.t)
            return []
        if inp.supervisor_mode == Mode.FAILSAFE:
            return self._land(inp, "supervisor FAILSAFE: the autopilot's land mode")
        if not self.strategy.in_offboard(inp.custom_mode):
            self._go(EngageState.HELD, f'autopilot left the offboard mode (custom_mode '
                     f'{inp.custom_mode}): pilot / GCS or autopilot failsafe in charge, '
                     'setpoints stopped', inp.t)
            return []
        if not inp.armed:
            self._go(EngageState.HELD, 'autopilot disarmed in flight', inp.t)
            return []
        if inp.inputs_lost:
            return self._inputs_lost(inp, 'no valid force for hold_last_s')
        return []

    def _inputs_lost(self, inp: SequencerInputs, why: str) -> list[CommandRequest]:
        if self.loss_action == 'land':
            return self._land(inp, f"{why}: the autopilot's land mode")
        self._go(EngageState.HELD, f"{why}: setpoints stopped, the autopilot's offboard-loss "
                 'failsafe takes the vehicle (PX4 COM_OF_LOSS_T, COM_OBL_RC_ACT)', inp.t)
        self._stopped_on_loss = True
        return []

    def _shutdown_ramp(self, inp: SequencerInputs) -> list[CommandRequest]:
        if not inp.armed:
            self._go(EngageState.DONE, 'disarmed during the ramp', inp.t)
        elif not self.strategy.in_offboard(inp.custom_mode):
            self._go(EngageState.HELD, f'autopilot left the offboard mode during the shutdown '
                     f'(custom_mode {inp.custom_mode})', inp.t)
        elif inp.airborne_at_low_thrust:
            return self._land(inp, "shutdown in the air (the IMU shows no ground contact at "
                                   "low thrust): the autopilot's land mode")
        elif inp.ramp_done:
            self._go(EngageState.DISARMING, 'thrust ramp ended', inp.t)
            return self._disarming(inp)
        return []

    def _resolve_shutdown(self, inp: SequencerInputs, why: str) -> list[CommandRequest]:
        if not inp.armed:
            self._go(EngageState.DONE, f'{why}: disarmed', inp.t)
            return []
        if inp.landed:
            self._go(EngageState.DISARMING, f'{why}: landed, disarming', inp.t)
            return self._disarming(inp)
        return self._land(inp, f"{why}: still in the air, the autopilot's land mode")

    def _disarming(self, inp: SequencerInputs) -> list[CommandRequest]:
        """Plain disarm; forced only by the touchdown rule (docs/mavlink.md)."""
        if not inp.armed:
            self._go(EngageState.DONE, 'disarmed' + (' (forced)' if self.disarm_forced else ''),
                     inp.t)
            return []
        if inp.airborne_at_low_thrust:
            return self._land(inp, "not on the ground after the ramp (IMU): the autopilot's "
                                   'land mode')
        if inp.t - self._entered_t > self.config.disarm_timeout_s:
            return self._land(inp, f'still armed {self.config.disarm_timeout_s:.0f} s after the '
                                   "ramp: the autopilot's land mode (it disarms on touchdown)")
        p = self._pending
        if p is not None and p.ack not in (None, MavResult.ACCEPTED, MavResult.IN_PROGRESS) \
                and self._first_refusal_t is None:
            self._first_refusal_t = inp.t
        if p is not None and inp.t - p.sent_t < self.config.command_retry_s:
            return []        # one disarm per command_retry_s, refused or not: never two at once
        refused_long = (self._first_refusal_t is not None
                        and inp.t - self._first_refusal_t >= self.config.disarm_force_after_s)
        force = refused_long and inp.touchdown
        if force:
            self.disarm_forced = True
        n = 1 if p is None else p.attempts + 1
        self._pending = _Pending(MavCmd.COMPONENT_ARM_DISARM, inp.t, n, forced=force)
        if force:
            return [CommandRequest(MavCmd.COMPONENT_ARM_DISARM,
                                   (0.0, float(ARM_DISARM_FORCE_MAGIC)),
                                   'disarm refused for '
                                   f'{inp.t - self._first_refusal_t:.1f} s while the touchdown '
                                   'rule holds: forcing')]
        if inp.landed is False:
            self._say_once('state', 'disarm: the autopilot says in the air; waiting for its '
                                    'landed state or the touchdown rule')
        return [CommandRequest(MavCmd.COMPONENT_ARM_DISARM, (0.0,), 'disarm')]

    def _land(self, inp: SequencerInputs, why: str) -> list[CommandRequest]:
        self._go(EngageState.LANDING, why, inp.t)
        return self._landing(inp)

    def _landing(self, inp: SequencerInputs) -> list[CommandRequest]:
        if not inp.armed:
            self._go(EngageState.DONE, 'disarmed (landed by the autopilot)', inp.t)
            return []
        if self.strategy.in_land_mode(inp.custom_mode):
            if not self._land_confirmed:
                self._land_confirmed = True
                self._pending = None
                self._events.append(f'autopilot in its land mode (custom_mode {inp.custom_mode})'
                                    ': setpoints stopped')
            if inp.landed:
                out = self._command(inp.t, MavCmd.COMPONENT_ARM_DISARM, (0.0,),
                                    'landed in the land mode: disarm')
                return out or []
            return []
        if self._land_confirmed:
            self._go(EngageState.HELD, f'the land mode was left (custom_mode {inp.custom_mode})'
                     ': pilot / GCS in charge', inp.t)
            return []
        out = self._command(inp.t, MavCmd.DO_SET_MODE, self.strategy.land_params(),
                            "switch to the autopilot's land mode")
        if out is None:
            self._go(EngageState.HELD, f'land mode not effective after '
                     f'{self.config.max_attempts} attempts: setpoints stopped, the autopilot\'s '
                     'offboard-loss failsafe acts', inp.t)
            return []
        return out
