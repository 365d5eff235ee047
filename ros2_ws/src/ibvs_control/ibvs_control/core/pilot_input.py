"""The pilot's side of a mission: start and abort from the radio (ROS-free).

The bridge reads the pilot's mission switch, an RC channel the autopilot reports in
RC_CHANNELS (:mod:`ibvs_control.mavlink.pilot_switch`), and publishes it on
``ibvs/pilot_input`` (std_msgs/UInt8, latched) as a :class:`PilotInput`. The supervisor turns
its changes into commands (:class:`PilotInputWatch`):

- **start** when it turns ON and the last position known before was OFF. A switch already ON
  when the graph boots (or when RC comes back) starts nothing: the pilot flips it OFF and ON.
  The start goes through the same preflight gate and checks as ``ibvs/start``;
- **abort** when it turns OFF while a mode flies or a start is pending (in IDLE the pending
  start is dropped). The bridge also reports OFF when the vehicle left its hands in flight
  (the pilot or the GCS switched the autopilot out of the offboard mode, the link was lost):
  the mission is then over, whether a switch is configured or not;
- UNKNOWN (no switch configured, no valid RC_CHANNELS for ``pilot_switch_timeout_s``) changes
  nothing: on an RC loss the autopilot's own RC failsafe acts.
"""
from __future__ import annotations

from enum import Enum, IntEnum


class PilotInput(IntEnum):
    """The value published on ``ibvs/pilot_input`` (std_msgs/UInt8)."""

    UNKNOWN = 0     # no switch configured, or no valid RC reading
    OFF = 1         # switch off, or the vehicle left the bridge's hands (latched, see module)
    ON = 2          # switch on: the pilot asks for the mission


class PilotAction(Enum):
    """What a change of the pilot's input asks of the supervisor."""

    NONE = 'none'
    START = 'start'
    ABORT = 'abort'


class PilotInputWatch:
    """Edges of ``ibvs/pilot_input`` as supervisor commands (the rules of the module)."""

    def __init__(self) -> None:
        self.value = PilotInput.UNKNOWN
        self.last_known: PilotInput | None = None    # the last ON / OFF seen
        self.on_without_off = False                  # ON seen without an OFF before it

    def on_input(self, value: int) -> PilotAction:
        """Take one ``ibvs/pilot_input`` value; ValueError for a value outside the enum."""
        new = PilotInput(int(value))
        old, self.value = self.value, new
        if new == old or new == PilotInput.UNKNOWN:
            return PilotAction.NONE
        before, self.last_known = self.last_known, new
        if new == PilotInput.OFF:
            self.on_without_off = False
            return PilotAction.ABORT
        if before == PilotInput.OFF:
            return PilotAction.START
        self.on_without_off = True
        return PilotAction.NONE
