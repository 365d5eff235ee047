"""The bridge's diagnostics: its log events and its /diagnostics snapshot (ROS-free)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ibvs_control.mavlink.time_sync import TimeSyncStatus

if TYPE_CHECKING:       # annotation only: the bridge imports this module
    from ibvs_control.mavlink.bridge import MavlinkBridge


class EventLog:
    """(level, text) events of the bridge's parts, in order, until the node logs them."""

    def __init__(self) -> None:
        self._events: list[tuple[str, str]] = []

    def add(self, level: str, text: str) -> None:
        """Note one event ('info', 'warn' or 'error')."""
        self._events.append((level, text))

    def pop(self) -> list[tuple[str, str]]:
        """Return the events since the last call."""
        events, self._events = self._events, []
        return events


@dataclass(frozen=True)
class BridgeStatus:
    """Snapshot for /diagnostics."""

    link_up: bool
    heartbeat_age_s: float
    autopilot: str
    armed: bool
    custom_mode: int
    engage_state: str
    engage_reason: str
    supervisor_mode: str
    streaming: bool
    arm_requested: bool
    hover_thrust: float | None           # what the setpoints use now
    hover_thrust_seed: float | None
    hover_thrust_source: str
    hover_estimate_std: float | None
    setpoint_source: str
    setpoint_rate_hz: float
    rejected_setpoints: int
    landed_state: int | None
    armable: bool | None
    autopilot_internal_errors: int
    last_autopilot_reason: str
    dead_bridge_failsafe: bool | None       # the autopilot lands if we stop; None: unknown
    counters: dict
    time_sync: TimeSyncStatus
    imu_dropped_unsynced: int
    link_error: str = ''                    # the connection's last error ('' if none)
    stale_setpoints: int = 0                # of rejected_setpoints: images too old
    telemetry_slowed: bool = False          # the high-rate streams at their rate at rest
    # the dead-bridge failsafe parameters as read (PX4 COM_OF_LOSS_T, COM_OBL_RC_ACT;
    # ArduPilot FS_GCS_ENABLE, SYSID_MYGCS), and this bridge's MAVLink system id
    dead_bridge_params: dict = field(default_factory=dict)
    source_system: int = 0
    pilot_input: str = 'UNKNOWN'           # ibvs/pilot_input (core/pilot_input.py)


def bridge_status(bridge: MavlinkBridge, now: float) -> BridgeStatus:
    """Return the snapshot of ``bridge`` at steady time ``now``."""
    link, eng, sp, hover = bridge.link, bridge.engagement, bridge.setpoints, bridge.hover
    hb = link.heartbeat
    seq = eng.sequencer
    c = link.counters
    tel = bridge.telemetry
    streams = bridge.rates.streams
    return BridgeStatus(
        link_up=link.link_up, heartbeat_age_s=link.heartbeat_age(),
        autopilot=eng.autopilot.value if eng.autopilot else 'unknown',
        armed=bool(hb and hb.armed), custom_mode=hb.custom_mode if hb else 0,
        engage_state=seq.state.value if seq else 'no_link',
        engage_reason=seq.last_reason if seq else '',
        supervisor_mode=eng.supervisor_mode.name, streaming=sp.may_stream(),
        arm_requested=bool(seq.arm_requested if seq else eng.arm_pending),
        hover_thrust=hover.now(), hover_thrust_seed=hover.seed.value,
        hover_thrust_source=hover.seed.source + (
            ' + online estimate' if bridge.config.estimator.enabled else ''),
        hover_estimate_std=hover.estimator.std,
        setpoint_source=sp.source.value, setpoint_rate_hz=sp.rate.rate(now),
        rejected_setpoints=sp.shaper.rejected, landed_state=tel.landed_state,
        armable=tel.armable, autopilot_internal_errors=tel.internal_errors,
        last_autopilot_reason=tel.last_reason,
        dead_bridge_failsafe=bridge.params.dead_bridge_failsafe,
        counters={'received': c.received, 'sent': c.sent, 'bad_data': c.bad_data,
                  'foreign': c.foreign, 'reconnects': c.reconnects, 'reopens': c.reopens,
                  'link_losses': c.link_losses, 'send_errors': c.send_errors,
                  'peers': c.peers, 'headings_missing': sp.pairing.missing,
                  'late_headings': sp.pairing.late,
                  'timesync_answered': bridge.timesync.answered,
                  'hover_estimate_samples': hover.estimator.accepted,
                  'hover_estimate_rejected': hover.estimator.rejected,
                  'autopilot_reasons': tel.reasons,
                  'streams_refused': len(streams.refused) if streams else 0},
        time_sync=bridge.time_sync.status(), imu_dropped_unsynced=tel.imu_dropped_unsynced,
        link_error=link.last_error, stale_setpoints=sp.shaper.stale,
        telemetry_slowed=bridge.rates.slowed,
        dead_bridge_params=dict(bridge.params.dead_bridge_params),
        source_system=bridge.params.source_system,
        pilot_input=bridge.pilot.value(now).name)
