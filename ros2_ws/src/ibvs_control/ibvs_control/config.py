"""The typed configurations of the supervisor and controller nodes (ROS-free).

Each field is a ROS parameter (:func:`~ibvs_common.core.params.param`) or a group of them;
the nodes declare them with ``declare_config`` and the harness's feature-level loop builds
the same cores from the same dataclasses and params.yaml.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ibvs_common.core.attitude_buffer import AttitudeBufferConfig
from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_common.core.params import group, param
from ibvs_control.core.control_laws import (
    CrossingGains, CrossingLaw, DisturbanceLaw, GainError, IntegralGains, LandingGains,
    ObserverGains, WindowGains)
from ibvs_control.core.controller import ControllerConfig
from ibvs_control.core.rate_governor import GovernorConfig
from ibvs_control.core.supervisor import SupervisorConfig

FRAME_DEADLINE = ("s (ROS clock, from the frame's first product, never before its stamp): a "
                  'frame waits at most this for the other products its mode needs, then it is '
                  'skipped')
VEHICLE_FILE = "vehicle YAML (mass, camera mounts); '' = the installed vehicle.yaml"
WINDOW_LAYOUT_FILE = ("window layout YAML (r_w, the window's known width); '' = the installed "
                      'window_layout.yaml')
PAD_LAYOUT_FILE = "pad layout YAML (group sizes); '' = the installed pad_layout.yaml"


@dataclass(frozen=True)
class ModeSupervisorNodeConfig:
    """Parameters of the ``mode_supervisor`` node."""

    update_rate_hz: float = param(
        20.0, 'Hz (ROS clock timer): the staleness rules are applied this often when inputs '
        'stop, > 0', 1e-3)
    frame_deadline_s: float = param(0.04, FRAME_DEADLINE, 0.0)
    vehicle_file: str = param('', VEHICLE_FILE)
    window_layout_file: str = param('', WINDOW_LAYOUT_FILE)
    pad_layout_file: str = param('', PAD_LAYOUT_FILE)
    require_preflight_go: bool = param(
        True, 'true: ibvs/start is refused while the latest preflight verdict (ibvs/preflight) '
        'is no-go; false: the operator overrides it, the start goes on and the no-go is '
        'logged. No verdict at all (the preflight not run) refuses nothing')
    preflight_max_age_s: float = param(
        900.0, 's (ROS clock): with require_preflight_go, a preflight go older than this when '
        'ibvs/start comes refuses the start (the checks describe the vehicle as it was: a '
        'battery, a camera or a parameter may have changed since); 0 = a go never expires',
        0.0)
    publish_camera_tf: bool = param(
        True, 'true: publish the cameras\' mounts of vehicle.yaml (base_link -> each '
        'optical frame) once at start on /tf_static (latched), for RViz and Foxglove; needs '
        'tf2_msgs (without it one warning, nothing published)')
    supervisor: SupervisorConfig = group(SupervisorConfig)
    governor: GovernorConfig = group(GovernorConfig)
    imu: AttitudeBufferConfig = group(AttitudeBufferConfig, 'imu_')

    def supervisor_config(self, r_w: float, pad: PadLayout) -> SupervisorConfig:
        """Return the core's config with the window width and group sizes from the layouts."""
        return dataclasses.replace(self.supervisor, r_w=float(r_w),
                                   group_half_sides={g.name: g.c for g in pad.groups})


@dataclass(frozen=True)
class ForceControllerNodeConfig:
    """Parameters of the ``force_controller`` node."""

    crossing_law: str = param('closed', 'mode 2 law: closed | intended | seed (docs/spec.md '
                              'section 3)')
    disturbance_law: str = param(
        'observer_integral',
        "window and landing laws: 'paper' (proportional) | 'integral' (with integral action on "
        "the image errors, integral.*) | 'observer' (with a disturbance observer on imu/data "
        "specific force, observer.*) | 'observer_integral' (both: the observer for the wind, "
        'the integrals for accelerometer bias and attitude-estimate error); docs/design.md')
    frame_deadline_s: float = param(0.04, FRAME_DEADLINE, 0.0)
    vehicle_file: str = param('', VEHICLE_FILE)
    window_layout_file: str = param('', WINDOW_LAYOUT_FILE)
    pad_layout_file: str = param('', PAD_LAYOUT_FILE)
    landing: LandingGains = group(LandingGains, 'landing.')
    window: WindowGains = group(WindowGains, 'window.')
    crossing: CrossingGains = group(CrossingGains, 'crossing.')
    integral: IntegralGains = group(IntegralGains, 'integral.')
    observer: ObserverGains = group(ObserverGains, 'observer.')
    imu: AttitudeBufferConfig = group(AttitudeBufferConfig, 'imu_')

    def controller_config(self, vehicle: VehicleConfig, r_w: float,
                          pad: PadLayout | None = None) -> ControllerConfig:
        """Return the controller core's config, validated (raises GainError, a ValueError)."""
        try:
            law = CrossingLaw(self.crossing_law)
        except ValueError as exc:
            raise GainError(f'crossing_law must be one of {[x.value for x in CrossingLaw]}, '
                            f'not {self.crossing_law!r}') from exc
        try:
            disturbance = DisturbanceLaw(self.disturbance_law)
        except ValueError as exc:
            raise GainError(f'disturbance_law must be one of '
                            f'{[x.value for x in DisturbanceLaw]}, not '
                            f'{self.disturbance_law!r}') from exc
        cfg = ControllerConfig(
            mass=vehicle.mass, r_w=float(r_w), R_BC_front=vehicle.cameras['front'].R_BC,
            R_BC_down=vehicle.cameras['down'].R_BC, landing=self.landing, window=self.window,
            crossing=self.crossing, crossing_law=law, disturbance_law=disturbance,
            integral=self.integral, observer=self.observer,
            group_half_sides={} if pad is None else {g.name: g.c for g in pad.groups},
            t_BC_front=vehicle.cameras['front'].t_BC, t_BC_down=vehicle.cameras['down'].t_BC)
        cfg.validate()
        return cfg
