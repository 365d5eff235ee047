"""The bridge's safety policy: the event -> action -> who-acts table, and its detectors.

ROS-free, no I/O. :data:`POLICY` is the table written in docs/mavlink.md ("Safety policy"); a
test checks that the two agree. :class:`SafetyMonitor` turns the bridge's inputs into the
events the :class:`~ibvs_control.mavlink.sequencer.EngageSequencer` acts on:

- forces lost: no valid ``ibvs/force_setpoint`` for ``hold_last_s`` of *vehicle* time (the
  ROS clock: system time on a vehicle, sim time in the sim, so a lockstep sim waiting for the
  graph does not count);
- the touchdown rule: the commanded thrust is at most ``low_thrust_ratio`` x hover and the
  IMU's specific force stays above ``supported_g`` x g (the ground carries the vehicle: in the
  air the specific force would be the thrust's, well below g) for ``disarm_force_after_s``;
- airborne at low thrust: the same low thrust but a specific force below ``airborne_g`` x g for
  ``airborne_s`` (falling: no ground contact), e.g. a SHUTDOWN issued in the air.

The durations run on the autopilot's IMU time (its boot clock), sample by sample.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

from ibvs_common.core.frames import GRAVITY
from ibvs_common.core.stamps import NS_PER_S


@dataclass(frozen=True)
class Rule:
    """One row of the policy table."""

    event: str
    action: str
    who: str


POLICY: tuple[Rule, ...] = (
    Rule('start', 'stream setpoints only (PX4) or nothing (ArduPilot); never arm',
         'bridge'),
    Rule('supervisor leaves IDLE (engage)',
         'PX4: > prestream_s of setpoints, then OFFBOARD; ArduPilot: once armable if '
         'disarmed (SYS_STATUS pre-arm bit), GUIDED_NOGPS (if GUID_OPTIONS bit 3), '
         'setpoints from then on', 'bridge'),
    Rule('engaged while disarmed',
         'arm only if asked (ibvs/arm, arm_on_start), once armable (SYS_STATUS pre-arm bit), '
         'retried with backoff; reasons logged (STATUSTEXT, EVENT)', 'bridge'),
    Rule('a force of an image older than max_force_age_s (the graph falls behind)',
         'refused, not flown: counts as no force (stale_setpoints in /diagnostics)', 'bridge'),
    Rule('forces stop for hold_last_s (vehicle time)',
         'hold the last setpoint until then; then PX4: stop streaming; ArduPilot: LAND '
         '(input_loss_action)', 'autopilot: offboard-loss failsafe (PX4) / LAND (ArduPilot)'),
    Rule('supervisor FAILSAFE',
         "the autopilot's land mode (PX4 AUTO.LAND, ArduPilot LAND); level hold until it "
         'shows, then no setpoints; also after a forces-lost stop while the autopilot is '
         'still in its offboard mode, and after an offboard switch not yet confirmed',
         'autopilot'),
    Rule('supervisor SHUTDOWN',
         'thrust ramp to 0 over shutdown_ramp_s, then disarm (touchdown rule for a force)',
         'bridge'),
    Rule('shutdown in the air (IMU: no ground contact at low thrust)',
         "the autopilot's land mode", 'autopilot'),
    Rule('landed (EXTENDED_SYS_STATE) after the ramp or in the land mode', 'plain disarm',
         'bridge, then autopilot (auto-disarm)'),
    Rule('plain disarm refused',
         'forced disarm (21196) only under the touchdown rule, >= disarm_force_after_s after '
         'the first refusal; after disarm_timeout_s the land mode', 'bridge'),
    Rule('mode not asked for (pilot / GCS, e.g. POSCTL, GUIDED)',
         'stop streaming at once; never take the vehicle back', 'pilot / autopilot'),
    Rule('heartbeat lost for heartbeat_timeout_s (>= 3 periods)',
         'stop streaming; on link back: in the shutdown, disarm or land mode; otherwise hold '
         'off (still offboard: the input-loss action)', "autopilot's failsafe"),
    Rule('ArduPilot internal error 0x100000 (issue #26865)',
         'reported as an error (log, /diagnostics): no re-arming until reboot', 'operator'),
)


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of :class:`SafetyMonitor`."""

    hold_last_s: float = 0.25          # s of vehicle time without a valid force: inputs lost
    low_thrust_ratio: float = 0.5      # commanded thrust / hover at most this: "low thrust"
    supported_g: float = 0.8           # |specific force| above this x g at low thrust: ground
    airborne_g: float = 0.6            # below this x g at low thrust: no ground contact
    airborne_s: float = 0.4            # s of IMU time, airborne evidence (>= 0.4 m fallen)
    disarm_force_after_s: float = 1.0  # s of IMU time, touchdown evidence

    def __post_init__(self):
        for name in ('hold_last_s', 'airborne_s', 'disarm_force_after_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        if not 0.0 < self.airborne_g < self.supported_g <= 1.0:
            raise ValueError('need 0 < airborne_g < supported_g <= 1')
        if not 0.0 < self.low_thrust_ratio < 1.0:
            raise ValueError('low_thrust_ratio must be in (0, 1)')


def silence_s(now_s: float, since_s: float, hold_last_s: float) -> float:
    """Vehicle time (s, ROS clock) from ``since_s`` to ``now_s`` for the hold rule.

    0 for a clock a little back (at most ``hold_last_s``: readings of two threads out of
    order, a short step); infinite for a clock stepped back by more, where the time since can
    no longer be measured (see :meth:`SafetyMonitor.forces_silent_s`).
    """
    elapsed = now_s - since_s
    if elapsed < -hold_last_s:
        return math.inf
    return max(0.0, elapsed)


class SafetyMonitor:
    """Detectors of the policy's events (see the module doc)."""

    def __init__(self, config: SafetyConfig = SafetyConfig()) -> None:
        self.config = config
        self._last_force_s: float | None = None
        self._supported_since: int | None = None
        self._airborne_since: int | None = None
        self.touchdown = False
        self.airborne_at_low_thrust = False

    # --- forces ----------------------------------------------------------------------------
    def on_force(self, vehicle_s: float | None) -> None:
        """Note a valid force received at vehicle time ``vehicle_s`` (ROS clock, s)."""
        if vehicle_s is not None:
            self._last_force_s = float(vehicle_s)

    def start_count(self, vehicle_s: float | None) -> None:
        """Start the silence count now if no force came yet (an engagement starts)."""
        if self._last_force_s is None and vehicle_s is not None:
            self._last_force_s = float(vehicle_s)

    def forces_silent_s(self, vehicle_s: float | None) -> float:
        """Seconds of vehicle time since the last valid force (0 if unknown).

        Infinite when the ROS clock went back by more than ``hold_last_s`` since that force
        (the system clock stepped back in flight): the silence can no longer be measured, and
        counting from 0 again would hold the last setpoint for the length of the step. A step
        back shorter than that (or readings taken in two threads a little out of order) adds
        at most ``hold_last_s`` to the hold.
        """
        if vehicle_s is None or self._last_force_s is None:
            return 0.0
        return silence_s(float(vehicle_s), self._last_force_s, self.config.hold_last_s)

    def inputs_lost(self, vehicle_s: float | None) -> bool:
        """Whether no valid force came for ``hold_last_s`` of vehicle time."""
        return self.forces_silent_s(vehicle_s) > self.config.hold_last_s

    # --- ground contact --------------------------------------------------------------------
    def on_accel(self, boot_ns: int, f_norm: float, thrust: float, hover: float) -> None:
        """One IMU sample: |specific force| (m/s^2) while ``thrust`` is commanded."""
        c = self.config
        low = hover > 0.0 and thrust <= c.low_thrust_ratio * hover
        g = f_norm / GRAVITY
        if low and g >= c.supported_g:
            if self._supported_since is None:
                self._supported_since = int(boot_ns)
        else:
            self._supported_since = None
        if low and g <= c.airborne_g:
            if self._airborne_since is None:
                self._airborne_since = int(boot_ns)
        else:
            self._airborne_since = None
        self.touchdown = (self._supported_since is not None and boot_ns - self._supported_since
                          >= c.disarm_force_after_s * NS_PER_S)
        self.airborne_at_low_thrust = (self._airborne_since is not None
                                       and boot_ns - self._airborne_since
                                       >= c.airborne_s * NS_PER_S)

    def reset_contact(self) -> None:
        """Forget the ground-contact evidence (no IMU, link lost)."""
        self._supported_since = self._airborne_since = None
        self.touchdown = self.airborne_at_low_thrust = False
