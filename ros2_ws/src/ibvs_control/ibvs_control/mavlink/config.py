"""The typed configuration of the MAVLink bridge and of its node (ROS-free).

:class:`BridgeConfig` is what the core needs; :class:`MavlinkBridgeNodeConfig` is every
parameter of the ``mavlink_bridge`` node (:func:`~ibvs_common.core.params.param` fields and
groups of the core's configs), declared by the node with ``declare_config``. Its
:meth:`~MavlinkBridgeNodeConfig.bridge_config` reads the files the parameters name.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

from ibvs_common.core.config import ConfigError, load_vehicle
from ibvs_common.core.params import group, param
from ibvs_control.mavlink.hover import EstimatorConfig
from ibvs_control.mavlink.link import LinkConfig, load_signing_key, MIN_HEARTBEAT_TIMEOUT_S
from ibvs_control.mavlink.pilot_switch import PilotSwitchConfig
from ibvs_control.mavlink.safety import SafetyConfig
from ibvs_control.mavlink.sequencer import SequencerConfig
from ibvs_control.mavlink.telemetry import load_px4_events, message_ids
from ibvs_control.mavlink.time_sync import TimeSyncConfig

# PX4's onboard-link defaults that the bridge never reads (~300 of its ~400 messages/s,
# measured on PX4 v1.16 SITL): each costs the bridge a parse in Python (docs/mavlink.md)
DEFAULT_STREAMS_OFF = ('ATTITUDE', 'GLOBAL_POSITION_INT', 'LOCAL_POSITION_NED', 'ODOMETRY',
                       'ALTITUDE', 'DISTANCE_SENSOR', 'POSITION_TARGET_LOCAL_NED',
                       'SERVO_OUTPUT_RAW', 'VFR_HUD', 'GPS_RAW_INT')
DEFAULT_COVARIANCE = [1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4]
AUTOPILOTS = ('auto', 'px4', 'ardupilot')


def _rate(default: float, description: str) -> float:
    return param(default, description, 0.0, None)


@dataclass(frozen=True)
class BridgeConfig:
    """Everything the bridge core needs: node parameters and the vehicle's values."""

    link: LinkConfig = group(LinkConfig)
    autopilot: str = param('auto', 'auto (from HEARTBEAT) | px4 | ardupilot')
    hover_thrust_source: str = param(
        'autopilot', 'hover thrust seed: autopilot (MPC_THR_HOVER / MOT_THST_HOVER) | config')
    param_timeout_s: float = param(
        3.0, 's (steady clock), unanswered autopilot parameter reads: fallback / refuse',
        0.0, None)
    param_retry_s: float = 0.5
    attitude_rate_hz: float = _rate(100.0, 'Hz, ATTITUDE_QUATERNION stream asked of the '
                                    'autopilot')
    imu_rate_hz: float = _rate(100.0, 'Hz, HIGHRES_IMU (PX4) / SCALED_IMU (ArduPilot) stream '
                               'asked')
    thrust_rate_hz: float = _rate(50.0, 'Hz, ATTITUDE_TARGET stream asked (the thrust applied)')
    status_rate_hz: float = _rate(5.0, 'Hz, EXTENDED_SYS_STATE and SYS_STATUS streams asked')
    heartbeat_request_hz: float = _rate(5.0, "Hz, ArduPilot's HEARTBEAT stream asked (PX4's "
                                        'is 1 Hz)')
    streams_off: tuple = ()                  # message ids (the node: names, streams_off)
    stream_rate_hz: float = _rate(
        30.0, 'Hz (steady clock timer), setpoint repeat when none left for 1/this, link '
        'supervision, engage sequencing; > 0')
    idle_tick_rate_hz: float = param(
        10.0, 'Hz (steady clock), the same step while quiet (standby, supervisor IDLE, clocks '
        'synced): also the keepalive stream rate then; > 2 (PX4 wants > 2 Hz before OFFBOARD)',
        2.0, None)
    quiet_telemetry_rate_hz: float = _rate(
        10.0, 'Hz, the attitude, IMU and thrust streams asked while the vehicle rests '
        '(disarmed, supervisor IDLE, no arm request, no frame status), full rates again before '
        'anything engages or at the first frame; 0 = full rates always')
    quiet_telemetry_delay_s: float = param(
        2.0, 's (steady clock) at rest, and without a frame status, before the streams slow '
        'down', 0.0, None)
    time_sync: TimeSyncConfig = group(TimeSyncConfig, 'timesync_')
    hold_last_s: float = param(
        0.5, 's (ROS clock, vehicle time), the last valid setpoint is kept this long, then the '
        'vehicle is handed back (input_loss_action); as long as the supervisor\'s staleness '
        'timeouts, so that a computer that falls behind for a moment skips frames instead of '
        'ending the mission (PX4 holds an offboard setpoint COM_OF_LOSS_T, 1 s by default)',
        0.0, None)
    max_force_age_s: float = param(
        0.25, 's (ROS clock), a force computed from an image older than this when it arrives '
        'is refused (not flown: the held setpoint goes on, and after hold_last_s of refusals '
        'the vehicle is handed back): a graph that falls behind does not fly old images; '
        '0 = off', 0.0, None)
    max_force_factor: float = param(3.0, '|F| above this factor * m g is refused', 0.0, None)
    max_tilt_rad: float = param(0.6, 'rad, tilt limit of the thrust direction', 0.0, math.pi)
    shutdown_ramp_s: float = param(
        2.0, 's (ROS clock, force stamps), SHUTDOWN: thrust ramp to 0, then disarm', 0.0, None)
    arm_on_start: bool = param(
        False, 'true: an arm request from the start (sim scenario only); otherwise only the '
        'ibvs/arm service arms')
    sequencer: SequencerConfig = group(SequencerConfig)
    pilot_switch: PilotSwitchConfig = group(PilotSwitchConfig, 'pilot_switch_')
    estimator: EstimatorConfig = group(EstimatorConfig, 'hover_estimator_')
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    px4_events: dict | None = None           # PX4 event id -> text (all_events.json), or None
    # the vehicle (vehicle.yaml, or the hover_thrust parameter: bridge_config below)
    mass: float = 1.0                        # kg
    max_thrust_factor: float = 2.0           # max thrust / (m g)
    configured_hover_thrust: float = 0.5     # normalised

    def __post_init__(self):
        if self.autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot must be 'auto', 'px4' or 'ardupilot', not "
                             f'{self.autopilot!r}')
        if self.hover_thrust_source not in ('autopilot', 'config'):
            raise ValueError("hover_thrust_source must be 'autopilot' or 'config'")
        if not self.idle_tick_rate_hz > 2.0:
            raise ValueError(f'idle_tick_rate_hz must be > 2 (PX4 needs a setpoint stream '
                             f'above 2 Hz before OFFBOARD), got {self.idle_tick_rate_hz}')
        if not 0.05 <= self.configured_hover_thrust <= 0.95:
            raise ValueError(f'configured hover thrust {self.configured_hover_thrust} outside '
                             '[0.05, 0.95]')
        for name in ('param_timeout_s', 'param_retry_s', 'attitude_rate_hz', 'imu_rate_hz',
                     'thrust_rate_hz', 'status_rate_hz', 'heartbeat_request_hz',
                     'stream_rate_hz', 'idle_tick_rate_hz'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        for name in ('quiet_telemetry_rate_hz', 'quiet_telemetry_delay_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f'{name} must be finite and >= 0, got {v}')


@dataclass(frozen=True)
class MavlinkBridgeNodeConfig:
    """Parameters of the ``mavlink_bridge`` node."""

    vehicle_file: str = param('', "vehicle YAML (mass, max thrust); '' = the installed "
                              'vehicle.yaml')
    hover_thrust: float = param(-1.0, 'normalised thrust (0, 1]; <= 0 = the vehicle.yaml '
                                'hover_thrust', None, 1.0)
    signing_key_file: str = param('', "MAVLink 2 signing key file (32 bytes raw or 64 hex); "
                                  "'' = signing off")
    px4_events_file: str = param('', "PX4 all_events.json(.xz) to name EVENT ids; '' = ids "
                                 'only')
    streams_off: list = param(
        list(DEFAULT_STREAMS_OFF),
        'MAVLink message names whose streams are switched off on this link '
        '(SET_MESSAGE_INTERVAL -1): what the autopilot streams by default and the bridge does '
        "not read; never one it reads. [''] = none")
    heartbeat_rate_hz: float = _rate(1.0, 'Hz (steady clock timer), our HEARTBEAT; > 0')
    diagnostics_rate_hz: float = _rate(1.0, 'Hz (steady clock timer), /diagnostics; > 0')
    min_imu_subscribers: int = param(
        0, 'no setpoint stream until imu/data has matched this many subscribers', 0, None)
    frame_id: str = param('base_link', 'frame_id of imu/data')
    orientation_covariance: list = param(
        DEFAULT_COVARIANCE, 'rad^2, imu/data orientation covariance (row-major 3x3)')
    angular_velocity_covariance: list = param(
        DEFAULT_COVARIANCE, '(rad/s)^2, imu/data angular velocity covariance (row-major 3x3)')
    linear_acceleration_covariance: list = param(
        DEFAULT_COVARIANCE, '(m/s^2)^2, imu/data linear acceleration covariance (row-major '
        '3x3)')
    bridge: BridgeConfig = group(BridgeConfig)

    def __post_init__(self):
        timeout = self.bridge.link.heartbeat_timeout_s
        if not timeout >= MIN_HEARTBEAT_TIMEOUT_S:
            raise ValueError(f'heartbeat_timeout_s must be >= {MIN_HEARTBEAT_TIMEOUT_S} s (3 '
                             f'heartbeat periods), got {timeout}')
        for name in ('heartbeat_rate_hz', 'diagnostics_rate_hz'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be > 0')
        if self.min_imu_subscribers < 0:
            raise ValueError(f'min_imu_subscribers must be >= 0, got {self.min_imu_subscribers}')

    def bridge_config(self) -> BridgeConfig:
        """Return the core's config with what the files name; ValueError: why not."""
        try:
            vehicle = load_vehicle(self.vehicle_file or None)
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc
        key = load_signing_key(self.signing_key_file) if self.signing_key_file else None
        events = None
        if self.px4_events_file:
            try:
                events = load_px4_events(self.px4_events_file)
            except (OSError, ValueError) as exc:
                raise ValueError(f'px4_events_file {self.px4_events_file}: {exc}') from exc
        hover = self.hover_thrust if self.hover_thrust > 0.0 else vehicle.hover_thrust
        return replace(
            self.bridge, link=replace(self.bridge.link, signing_key=key),
            streams_off=message_ids(n for n in self.streams_off if n.strip()),
            px4_events=events, mass=vehicle.mass, max_thrust_factor=vehicle.max_thrust_factor,
            configured_hover_thrust=hover)
