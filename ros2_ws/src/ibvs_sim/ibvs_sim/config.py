"""The typed configurations of the ``sim`` and ``px4_sim`` nodes (ROS-free).

Each field is a ROS parameter (:func:`~ibvs_common.core.params.param`: default, description,
range): the nodes declare them with ``declare_config``. Times say their clock: sim (the sim's
own, published on ``/clock``), wall (the steady clock) or system. The ``fault_*`` parameters
and ``min_image_subscribers`` are switches for the tests and the launcher, not tuning.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import vec_map_to_I
from ibvs_common.core.params import param
from ibvs_sim.core.autopilot import AutopilotConfig
from ibvs_sim.core.camera_model import CameraTiming, Jitter, StampAt
from ibvs_sim.core.dynamics import WindConfig
from ibvs_sim.core.faults import CameraFaults, fault_windows
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.px4_plant import SIH_DEFAULT_HOME
from ibvs_sim.core.radio import PilotSwitchRadio
from ibvs_sim.core.sim_core import SimConfig

CAMERAS = ('front', 'down')
START_I = [-2.0, 0.1, -1.82]      # m, {I}: the reference start (world.yaml's)
WORLD_FILE = "world YAML; '' = the installed world.yaml"
PAD_LAYOUT_FILE = "pad layout YAML; '' = the installed pad_layout.yaml"
VEHICLE_FILE = "vehicle YAML; '' = the installed vehicle.yaml"
READ_NOISE = ("grey levels (of 255), std of the cameras' Gaussian read noise; 0 = "
              'noise-free')
_FAULT = ' [start, end) s (sim time), fault injection (tests only); [0, 0] = never'
_FAULTS = (' [start, end) s (sim time), or several: [start, end, start, end, ...]; fault '
           'injection (tests only); [0, 0] = never')


def _fault_window(values: list, name: str) -> tuple[float, float]:
    """Return the one [start, end] sim-time window (s) of a fault parameter; [0, 0] = never."""
    if len(values) != 2:
        raise ValueError(f'parameter {name} needs one window [start, end], got {list(values)}')
    return fault_windows(f'parameter {name}', values)[0]


def _axis_stds(values: list, name: str, unit: str, most: float) -> tuple[float, float, float]:
    """Return a noise std per body axis (FRD x, y, z) of parameter ``name``, each in [0, most]."""
    std = tuple(float(v) for v in values)
    if len(std) != 3 or not all(math.isfinite(v) and 0.0 <= v <= most for v in std):
        raise ValueError(f'parameter {name} needs 3 stds ({unit}, FRD x, y, z), '
                         f'each in [0, {most:g}], got {list(values)}')
    return std


FIRMWARES = ('', 'px4', 'ardupilot')      # SimNodeConfig.firmware


@dataclass(frozen=True)
class SimNodeConfig:
    """Parameters of the ``sim`` node (the checks of their combinations at construction)."""

    pacing: str = param(
        Pacing.LOCKSTEP.value, "'lockstep': sim time moves on from a delivery of images only "
        "once the graph answered it (or after lockstep_timeout_s); 'realtime': free-running, "
        'late frames dropped')
    lockstep_timeout_s: float = param(
        5.0, 's (wall, steady clock), lockstep wait before simulating anyway, > 0', 0.0)
    real_time_factor: float = param(1.0, 'realtime pacing: sim s per wall s, (0, 10]',
                                    0.0, 10.0)
    tick_period_s: float = param(
        0.002, 's (wall, steady clock), how often the node checks the pacing, > 0', 0.0)
    initial_override: bool = param(
        False, 'true: start at initial_position_I / initial_yaw; false: world.yaml '
        'initial_condition')
    initial_position_I: list = param(
        START_I, 'm, start position in the paper frame {I} (NED-type, z down), 3 numbers')
    initial_yaw: float = param(
        0.0, 'rad, start yaw about z_I (0: the front camera faces the wall)',
        -2.0 * math.pi, 2.0 * math.pi)
    wind_force_map: list = param([0.0, 0.0, 0.0],
                                 'N, steady disturbance force in map (ENU), 3 numbers')
    wind_gust_amplitude_N: float = param(
        0.0, 'N, gust amplitude per horizontal axis (half vertically)', 0.0)
    wind_gust_frequency_hz: float = param(0.5, 'Hz (sim time), base gust frequency', 0.0)
    mavlink_url: str = param('udpin:127.0.0.1:14560',
                             "the autopilot's MAVLink endpoint (pymavlink URL)")
    signing_key_file: str = param('', "MAVLink 2 signing key file; '' = signing off")
    world_file: str = param('', WORLD_FILE)
    pad_layout_file: str = param('', PAD_LAYOUT_FILE)
    vehicle_file: str = param(
        '', "the onboard calibration (vehicle YAML) whose camera_info the sim publishes, as a "
        "camera driver publishes the file it was given; '' = the installed vehicle.yaml")
    true_vehicle_file: str = param(
        '', 'the true vehicle (YAML) the sim flies and renders: plant, camera mounts R_BC, '
        'lever arms t_BC, intrinsics, distortion, camera-IMU time offsets, frame rates; a '
        "calibration error is this file against vehicle_file; '' = vehicle_file")
    seed: int = param(0, 'seed of the gust phases, autopilot sensor noise, camera read noise, '
                      'camera delivery jitter and dropped frames', 0)
    camera_read_noise_std: float = param(1.5, READ_NOISE, 0.0, 255.0)
    camera_rate_hz: list = param(
        [0.0, 0.0], 'Hz (sim time), [front, down] frame rates; 0 = the true vehicle '
        "file's rate_hz; a frame's stamp instant is rounded to the 2 ms physics grid")
    camera_latency_s: float = param(
        0.0, 's (sim time), both cameras: an image is published this long after the instant '
        'its stamp refers to (lockstep: the graph computes it then)', 0.0, 1.0)
    camera_jitter_s: float = param(
        0.0, 's (sim time), delivery jitter added to the latency: half-width (uniform) or '
        'standard deviation (normal); seeded', 0.0, 1.0)
    camera_jitter_distribution: str = param("uniform", "'uniform' or 'normal'")
    camera_drop_probability: float = param(
        0.0, 'probability that a camera loses a frame (each camera and frame, seeded; never '
        'frame 0), [0, 1)', 0.0, 1.0)
    camera_exposure_s: float = param(
        0.0, 's (sim time), exposure time: motion blur by averaging renders over it; 0 = an '
        'instant, at most one frame period', 0.0, 1.0)
    camera_exposure_samples: int = param(
        5, 'renders averaged over an exposure > 0 (the render cost per frame, times this)',
        1, 64)
    camera_stamp_at: str = param(
        "mid", "the instant of the exposure an image's stamp refers to: 'start', 'mid', 'end'")
    min_image_subscribers: int = param(
        0, 'frame 0 waits until each camera has this many image subscribers (a wiring switch: '
        'the launcher sets it to the image consumers it starts; 0 = none awaited)', 0)
    subscriber_wait_timeout_s: float = param(
        30.0, 's (wall, steady clock), then frame 0 starts anyway, > 0', 0.0)
    start_on_setpoints: bool = param(True,
                                     'frame 0 also waits until the bridge streams setpoints')
    telemetry_default_hz: float = param(
        100.0, 'Hz (sim time), IMU/attitude stream rate before any SET_MESSAGE_INTERVAL, > 0',
        0.0)
    attitude_estimate_offset_rad: list = param(
        [0.0, 0.0], "rad, [roll, pitch] static error of the autopilot's attitude estimate, "
        'reported and flown (an accelerometer bias b tilts it b / g; PX4 SIH: 1.5-1.8 deg), '
        'each within +-0.2')
    attitude_noise_std_rad: float = param(
        0.0122, "rad, stationary std per axis of the autopilot's attitude-estimate error "
        '(Gauss-Markov), reported and flown (PX4 SIH on motion capture: 0.0122, 0.7 deg)',
        0.0, 0.1)
    attitude_noise_tau_s: float = param(
        2.0, 's (sim time), correlation time of that error; 0 = white', 0.0, 600.0)
    accel_noise_std_mps2: list = param(
        [0.28, 0.95, 0.80], "m/s^2, std per body axis (FRD x, y, z) of the white noise on each "
        "HIGHRES_IMU accelerometer sample: PX4 SIH's as the bridge receives it (SIH's 0.5, 1.7, "
        "1.4 through PX4's IMU filter; the sim had 0.05 before 2026-12-05), each within [0, 5]")
    gyro_noise_std_radps: list = param(
        [0.005, 0.005, 0.005], 'rad/s, std per body axis (FRD x, y, z) of the white noise on '
        "each ATTITUDE_QUATERNION and HIGHRES_IMU rate sample, each within [0, 1]; PX4 SIH's "
        'imu/data against its truth in flight: 0.083, 0.040, 0.017 (not the default yet: with '
        'it one CI start loses the pad near the floor, docs/sim_autopilot.md)')
    fault_front_camera_off_s: list = param([0.0, 0.0], 'no front images in' + _FAULTS)
    fault_down_camera_off_s: list = param([0.0, 0.0], 'no down images in' + _FAULTS)
    fault_front_camera_freeze_s: list = param(
        [0.0, 0.0], 'the front camera re-publishes one image in' + _FAULTS)
    fault_down_camera_freeze_s: list = param(
        [0.0, 0.0], 'the down camera re-publishes one image in' + _FAULTS)
    fault_imu_off_s: list = param(
        [0.0, 0.0], 'the autopilot sends no ATTITUDE_QUATERNION / HIGHRES_IMU in' + _FAULT)
    fault_imu_nan_s: list = param(
        [0.0, 0.0], 'the autopilot sends ATTITUDE_QUATERNION / HIGHRES_IMU full of NaN in'
        + _FAULT)
    firmware: str = param(
        '', "'' = the sim's own autopilot emulation on mavlink_url; 'px4' = a real PX4 SITL "
        '(px4-hil, started by the caller) flies the plant in lockstep on TCP 4560 + '
        "firmware_instance; 'ardupilot' = a real ArduCopter SITL (ardupilot-sitl start --json, "
        'started by the caller) on its JSON backend, UDP 9002 + 10 firmware_instance. The sim '
        'relays mavlink_url to its companion port, and frame 0 waits until the firmware took '
        'off and holds at the start (docs/firmware_lockstep.md); lockstep pacing only')
    firmware_instance: int = param(0, 'the instance of the firmware (its ports)', 0, 9)
    pilot_switch_channel: int = param(
        0, "the pilot's radio: RC input (sticks centred) with a mission switch on this channel "
        '(1-8), OFF until pilot_switch_on_s; reported in RC_CHANNELS by the emulated '
        'autopilot when asked, given to a firmware (px4) as its RC input; 0 = no RC '
        '(docs/sim_autopilot.md, docs/firmware_lockstep.md)', 0, 8)
    pilot_switch_on_s: float = param(
        1.0, 's of sim time (the mission clock): the simulated pilot flips the switch ON; < 0: '
        'only when told (sim/pilot_switch, std_msgs/Bool)')
    pilot_switch_off_s: float = param(
        -1.0, 's of sim time: the simulated pilot flips the switch OFF again (an abort); < 0: '
        'never')

    def __post_init__(self) -> None:
        """Check what the ranges cannot say; raise ValueError naming the parameter."""
        try:
            Pacing(self.pacing)
        except ValueError as exc:
            raise ValueError(f"parameter pacing must be 'lockstep' or 'realtime', "
                             f'got {self.pacing!r}') from exc
        pos = [float(x) for x in self.initial_position_I]
        yaw = float(self.initial_yaw)
        if len(pos) != 3 or not all(math.isfinite(x) for x in pos + [yaw]):
            raise ValueError(f'initial_position_I needs 3 finite numbers and initial_yaw a '
                             f'finite one, got {pos}, {yaw}')
        wind = [float(x) for x in self.wind_force_map]
        if len(wind) != 3 or not all(math.isfinite(x) for x in wind):
            raise ValueError(f'parameter wind_force_map needs 3 finite numbers, got {wind}')
        if self.lockstep_timeout_s <= 0 or self.tick_period_s <= 0:
            raise ValueError('lockstep_timeout_s and tick_period_s must be positive')
        if int(self.min_image_subscribers) < 0 or not self.subscriber_wait_timeout_s > 0:
            raise ValueError(f'min_image_subscribers must be >= 0 and subscriber_wait_timeout_s '
                             f'> 0, got {self.min_image_subscribers}, '
                             f'{self.subscriber_wait_timeout_s}')
        noise = float(self.camera_read_noise_std)
        if not (math.isfinite(noise) and noise >= 0.0):
            raise ValueError(f'camera_read_noise_std must be >= 0 grey levels, got {noise}')
        telemetry_hz = float(self.telemetry_default_hz)
        if not (math.isfinite(telemetry_hz) and telemetry_hz > 0):
            raise ValueError(f'telemetry_default_hz must be > 0, got {telemetry_hz}')
        self.camera_faults()
        rates = [float(x) for x in self.camera_rate_hz]
        if len(rates) != len(CAMERAS) or not all(math.isfinite(r) and r >= 0.0 for r in rates):
            raise ValueError(f'parameter camera_rate_hz needs [front, down] rates >= 0 Hz, got '
                             f'{list(self.camera_rate_hz)}')
        try:
            Jitter(self.camera_jitter_distribution)
        except ValueError as exc:
            raise ValueError("parameter camera_jitter_distribution must be 'uniform' or "
                             f"'normal', got {self.camera_jitter_distribution!r}") from exc
        try:
            StampAt(self.camera_stamp_at)
        except ValueError as exc:
            raise ValueError("parameter camera_stamp_at must be 'start', 'mid' or 'end', got "
                             f'{self.camera_stamp_at!r}') from exc
        if not 0.0 <= float(self.camera_drop_probability) < 1.0:
            raise ValueError(f'parameter camera_drop_probability must be in [0, 1), got '
                             f'{self.camera_drop_probability}')
        _fault_window(self.fault_imu_off_s, 'fault_imu_off_s')
        _fault_window(self.fault_imu_nan_s, 'fault_imu_nan_s')
        if self.firmware not in FIRMWARES:
            raise ValueError(f'parameter firmware must be one of {FIRMWARES}, got '
                             f'{self.firmware!r}')
        if self.firmware == 'ardupilot' and self.pilot_switch_channel:
            raise ValueError('firmware ardupilot takes no RC input from the sim (its JSON '
                             'backend has none here): pilot_switch_channel must be 0')
        if self.firmware and Pacing(self.pacing) is not Pacing.LOCKSTEP:
            raise ValueError(f'firmware {self.firmware!r} runs in lockstep only (pacing '
                             f'{self.pacing!r})')

    def sim_config(self, vehicle: VehicleConfig) -> SimConfig:
        """Return the simulation's settings for the true ``vehicle`` (its cameras' timing)."""
        override = bool(self.initial_override)
        timing = self.camera_timing(vehicle)
        return SimConfig(
            pacing=Pacing(self.pacing), lockstep_timeout_s=float(self.lockstep_timeout_s),
            real_time_factor=float(self.real_time_factor),
            camera_rate_hz=timing[CAMERAS[0]].rate_hz, camera_timing=timing,
            initial_position_I=(tuple(float(x) for x in self.initial_position_I)
                                if override else None),
            initial_yaw=float(self.initial_yaw) if override else None,
            wind=self.wind_config(), cameras=CAMERAS,
            read_noise_std=float(self.camera_read_noise_std), noise_seed=int(self.seed))

    def camera_timing(self, vehicle: VehicleConfig) -> dict[str, CameraTiming]:
        """Return each camera's timing: these parameters, the true ``vehicle``'s time offsets.

        A rate of 0 is the vehicle's ``rate_hz``. Raises ValueError naming the parameters.
        """
        out = {}
        for name, rate in zip(CAMERAS, self.camera_rate_hz):
            cam = vehicle.cameras[name]
            try:
                out[name] = CameraTiming(
                    rate_hz=float(rate) or cam.rate_hz, latency_s=float(self.camera_latency_s),
                    jitter_s=float(self.camera_jitter_s),
                    jitter=Jitter(self.camera_jitter_distribution),
                    drop_probability=float(self.camera_drop_probability),
                    exposure_s=float(self.camera_exposure_s),
                    exposure_samples=int(self.camera_exposure_samples),
                    stamp_at=StampAt(self.camera_stamp_at), time_offset_s=cam.time_offset_s)
            except ValueError as exc:
                raise ValueError(f'camera_* parameters of the {name} camera: {exc}') from exc
        return out

    def wind_config(self) -> WindConfig:
        """Return the wind: the steady force turned from map (ENU) to {I}, the seeded gusts."""
        wind_map = tuple(float(x) for x in self.wind_force_map)
        return WindConfig(steady_force_I=tuple(vec_map_to_I(np.array(wind_map))),
                          gust_amplitude_N=float(self.wind_gust_amplitude_N),
                          gust_frequency_hz=float(self.wind_gust_frequency_hz),
                          seed=int(self.seed))

    def autopilot_config(self, vehicle: VehicleConfig, floor_z: float,
                         radio: PilotSwitchRadio | None = None) -> AutopilotConfig:
        """Return the autopilot's settings (raises ValueError for a bad estimate error).

        ``radio``: the pilot's radio it reports (:meth:`radio`), or None.
        """
        return AutopilotConfig(
            url=str(self.mavlink_url), hover_thrust=vehicle.hover_thrust,
            signing_key_file=self.signing_key_file or None, noise_seed=int(self.seed),
            mass=vehicle.mass, floor_z=floor_z,
            telemetry_default_hz=float(self.telemetry_default_hz),
            imu_off_s=_fault_window(self.fault_imu_off_s, 'fault_imu_off_s'),
            imu_nan_s=_fault_window(self.fault_imu_nan_s, 'fault_imu_nan_s'),
            attitude_estimate_offset_rad=tuple(
                float(x) for x in self.attitude_estimate_offset_rad),
            attitude_noise_std=float(self.attitude_noise_std_rad),
            attitude_noise_tau_s=float(self.attitude_noise_tau_s),
            accel_noise_std=_axis_stds(self.accel_noise_std_mps2, 'accel_noise_std_mps2',
                                       'm/s^2', 5.0),
            gyro_noise_std=_axis_stds(self.gyro_noise_std_radps, 'gyro_noise_std_radps',
                                      'rad/s', 1.0),
            radio=radio)

    def radio(self) -> PilotSwitchRadio | None:
        """Return the pilot's RC input with its mission switch (None: no RC)."""
        if not self.pilot_switch_channel:
            return None
        on, off = float(self.pilot_switch_on_s), float(self.pilot_switch_off_s)
        return PilotSwitchRadio(int(self.pilot_switch_channel), on if on >= 0.0 else None,
                                off if off >= 0.0 else None)

    def camera_faults(self) -> CameraFaults:
        """Return the cameras' fault injection: each camera's off and frozen windows."""
        off = {'front': self.fault_front_camera_off_s, 'down': self.fault_down_camera_off_s}
        frozen = {'front': self.fault_front_camera_freeze_s,
                  'down': self.fault_down_camera_freeze_s}
        return CameraFaults(
            {cam: fault_windows(f'parameter fault_{cam}_camera_off_s', w)
             for cam, w in off.items()},
            {cam: fault_windows(f'parameter fault_{cam}_camera_freeze_s', w)
             for cam, w in frozen.items()})


@dataclass(frozen=True)
class Px4SimNodeConfig:
    """Parameters of the ``px4_sim`` node."""

    state_url: str = param('udpin:127.0.0.1:19410',
                           'where PX4 SIH sends HIL_STATE_QUATERNION (pymavlink URL, '
                           'udpin:127.0.0.1:<19410 + instance>)')
    state_rate_hz: float = param(
        100.0, 'Hz (PX4 boot clock), HIL_STATE_QUATERNION rate asked with '
        'SET_MESSAGE_INTERVAL, > 0', 0.0, 1000.0)
    state_timeout_s: float = param(
        0.2, 's (system clock), a frame is not rendered from a ground-truth sample older than '
        'this, > 0', 0.0)
    tick_period_s: float = param(
        0.002, 's (steady clock), how often the node reads the link and checks the frame '
        'grid, > 0', 0.0)
    home_lat_deg: float = param(
        SIH_DEFAULT_HOME[0], 'deg, PX4 home latitude (SIH_LOC_LAT0 PX4 was started with; used '
        'as PX4 stores it, float32)', -90.0, 90.0)
    home_lon_deg: float = param(SIH_DEFAULT_HOME[1], 'deg, PX4 home longitude (SIH_LOC_LON0)',
                                -180.0, 180.0)
    home_alt_m: float = param(SIH_DEFAULT_HOME[2],
                              'm AMSL, PX4 home altitude (SIH_LOC_H0): the ground',
                              -1000.0, 10000.0)
    rest_height_m: float = param(
        0.1, 'm, body origin above the floor when PX4 rests on the ground at home (the '
        'envelope half height)', 0.0, 10.0)
    initial_override: bool = param(
        False, 'true: the take-off point is below initial_position_I; false: below world.yaml '
        'initial_condition')
    initial_position_I: list = param(
        START_I, 'm, scenario start in {I} (only x, y: the take-off point), 3 numbers')
    position_filter_tau_s: float = param(
        0.2, 's (system clock), time constant pulling the integrated velocity to the 1e-7 deg '
        'quantised fix; 0 = raw fix', 0.0, 10.0)
    airborne_clearance_m: float = param(
        0.3, 'm, contact events only after the envelope was this high above the floor', 0.0)
    world_file: str = param('', WORLD_FILE)
    pad_layout_file: str = param('', PAD_LAYOUT_FILE)
    vehicle_file: str = param('', VEHICLE_FILE)
    seed: int = param(0, 'seed of the camera read noise', 0)
    camera_read_noise_std: float = param(1.5, READ_NOISE, 0.0, 255.0)
    mocap_rate_hz: float = param(
        50.0, 'Hz (steady clock), the ground truth sent back to PX4 as motion capture '
        '(VISION_POSITION_ESTIMATE, EKF origin = home) for its own estimator; PX4 must boot '
        'with MOCAP_EKF2_PARAMETERS; 0 = off', 0.0, 1000.0)

    def __post_init__(self) -> None:
        """Check what the ranges cannot say; raise ValueError naming the parameter."""
        pos = [float(x) for x in self.initial_position_I]
        if len(pos) != 3 or not all(math.isfinite(x) for x in pos):
            raise ValueError(f'initial_position_I needs 3 finite numbers, got {pos}')
        for key in ('state_rate_hz', 'state_timeout_s', 'tick_period_s'):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f'{key} must be > 0, got {value}')
