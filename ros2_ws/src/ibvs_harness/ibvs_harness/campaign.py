"""Monte Carlo campaigns under wind at feature level (issue 14): ``make mc`` / this module.

``python -m ibvs_harness.campaign --name NAME [--runs N] [--levels 0 0.2 0.5 0.8] ...``

For every law and wind level, ``runs`` flights of ibvs_sim's feature-level closed loop
(``feature_sim.run_feature_scenario``: the ROS-free controller and supervisor as the nodes run
them, with the parameter file's gains and thresholds over the code defaults, geometric
features, a point-mass plant):

- start: uniform in world.yaml's random box (docs/spec.md section 2: x in [-2.6, -1.8],
  y in [-0.3, 0.3], z in [-1.9, -1.35] m, {I}), at rest, level, the reference yaw;
- wind (``dynamics.WindConfig.from_level``, docs/sim.md "Wind"): horizontal magnitude
  ``level`` (m/s^2 = |Delta_h| / m) blowing towards a direction uniform in [0, 2 pi) (rad
  from north, +x_I, towards east), a steady vertical component ``vertical_factor x level``
  (positive: down, +z_I), gusts of amplitude ``gust_level x level x m`` (N, a seeded sum of
  sines per axis);
- run ``index`` draws its start, wind direction and gust phases from
  ``numpy.random.SeedSequence([seed, index])`` only: the level and the law do not enter, so
  every law and every level sees the same starts, directions and phases (paired
  comparisons, common random numbers), and a run is the same whatever the worker or order.

Output, ``<results-root>/<name>/`` (default results/campaign/<name>/):

- ``runs/<law>/<level>/<index>/summary.json``: docs/spec.md section 5's summary (ibvs_sim's
  ``evaluate_run``, the criteria of every run) plus a ``run`` block (law, wind, start, seed,
  failure cause, wall time). Resumable: a run whose summary.json exists is not flown again,
  and a larger ``--runs`` adds runs to a campaign;
- ``campaign.json`` (the settings every run depends on: a resume with other settings is
  refused), ``aggregate.json`` and ``table.md`` (per law and level: success rate with its 95 %
  Wilson interval, clearance, crossing speed, landing error, touchdown speed, failure
  causes), and PNG plots when matplotlib is importable.

Parallel over processes (``--workers``, default ``os.cpu_count()``).

``--image-level``: the same runs through the whole graph in lockstep, one
``python -m ibvs_harness.run_scenario`` subprocess per run (no bag, no plots), each worker on
its own ROS_DOMAIN_ID (``--domain-base`` + worker). The steady wind goes on its ``--wind``,
the law's overrides and the gusts (amplitude, frequency, the sim's ``seed`` for the phases)
in a per-run params.yaml (``--params-file``); the sim node has one gust sine per axis, so
``--gust-components`` must be 1. About a minute of wall clock per run on this machine.
``--autopilot px4|ardupilot``: the same starts and wind, flown by a real firmware on the
sim's plant in lockstep (``run_scenario --autopilot``; worker w on its own instance,
docs/firmware_lockstep.md "Campaigns").
"""
from __future__ import annotations

import argparse
import dataclasses
from dataclasses import asdict, dataclass
import functools
import hashlib
import json
import math
import multiprocessing
import os
import sys
import time
from typing import Callable, TYPE_CHECKING

import numpy as np

from ibvs_harness.campaign_plots import write_plots
from ibvs_harness.campaign_stats import aggregate, failure_cause, format_table

if TYPE_CHECKING:
    from ibvs_sim.core.dynamics import WindConfig

DEFAULT_LEVELS_MPS2 = (0.0, 0.2, 0.5, 0.8)
DEFAULT_RESULTS_ROOT = os.path.join('results', 'campaign')
MAX_SIM_TIME_S = 60.0             # docs/spec.md section 5


# --- settings -------------------------------------------------------------------------------

@dataclass(frozen=True)
class LawSpec:
    """A control law of the campaign: a label and its force_controller parameter overrides.

    ``overrides``: (name, value) pairs applied over the ``force_controller`` parameters of
    the parameter file (e.g. ``(('crossing_law', 'intended'),)``); every name must be one of
    the node's parameters (``ForceControllerNodeConfig``), every value of its type and range.
    """

    label: str
    overrides: tuple = ()

    @staticmethod
    def parse(text: str) -> 'LawSpec':
        """Parse ``LABEL`` or ``LABEL:name=value,name=value`` (values read as YAML scalars).

        A bare label that is a crossing law (closed, intended, seed) sets ``crossing_law``, one
        that is a disturbance law (paper, integral, observer, observer_integral) sets
        ``disturbance_law``.
        """
        import yaml
        label, _, rest = text.partition(':')
        label = label.strip()
        if not label or not all(c.isalnum() or c in '_.+-' for c in label):
            raise ValueError(f'bad law label {label!r}: use letters, digits, _ . + -')
        pairs = []
        for item in filter(None, (s.strip() for s in rest.split(','))):
            name, eq, value = item.partition('=')
            if not eq or not name.strip():
                raise ValueError(f'law {label}: expected name=value, got {item!r}')
            pairs.append((name.strip(), yaml.safe_load(value)))
        if not pairs:
            from ibvs_control.core.control_laws import CrossingLaw, DisturbanceLaw
            kinds = (('crossing_law', [x.value for x in CrossingLaw]),
                     ('disturbance_law', [x.value for x in DisturbanceLaw]))
            name = next((n for n, values in kinds if label in values), None)
            if name is None:
                raise ValueError(f'law {label!r}: not a law name ({dict(kinds)}) and no '
                                 'overrides given')
            pairs = [(name, label)]
        return LawSpec(label, tuple(pairs))


@dataclass(frozen=True)
class CampaignConfig:
    """Everything a campaign's runs depend on (SI; wind levels in m/s^2 of Delta/m)."""

    name: str
    runs: int = 500
    levels_mps2: tuple = DEFAULT_LEVELS_MPS2
    laws: tuple = (LawSpec('params'),)   # default: the parameter file's laws as they are
    gust_level: float = 0.3           # gust amplitude / steady horizontal magnitude
    vertical_factor: float = 0.3      # steady vertical / horizontal magnitude (+: down)
    gust_frequency_hz: float = 0.5    # Hz, base gust frequency
    gust_components: int = 1          # sines per axis
    flow_noise: float = 0.0           # 1/s, white noise on each flow component
    bearing_noise_rad: float = 0.0    # rad, white noise on each bearing
    # rad (roll, pitch): static error of the autopilot's attitude estimate, flown and read
    # (FeatureSimConfig / the sim's attitude_estimate_offset_rad); docs/design.md
    estimate_error_rad: tuple = (0.0, 0.0)
    # (std rad, tau s) of the estimate's wandering error (Gauss-Markov per axis), flown and
    # read at both levels; None: the params file's sim attitude_noise_std_rad / _tau_s
    estimate_noise: tuple | None = None
    seed: int = 14                    # campaign seed (run i: SeedSequence([seed, i]))
    params_file: str | None = None    # None: the installed params.yaml
    results_root: str = DEFAULT_RESULTS_ROOT
    image_level: bool = False         # True: the whole graph in lockstep (run_scenario)
    domain_base: int = 100            # image level: worker w uses ROS_DOMAIN_ID base + w
    scenario_module: str = 'ibvs_harness.run_scenario'   # image level: run as python -m
    run_timeout_s: float = 900.0      # image level: wall-clock limit of one run
    camera_rate_hz: float = 50.0      # the camera rate (feature level: 1 / camera_dt)
    command_delay_s: float = 0.0      # feature level: frame stamp -> setpoint applied, s
    # feature level: (front, down) each flow measured on every Nth frame, held between (the
    # graph shedding that flow's work); (1, 1) = every frame
    flow_strides: tuple = (1, 1)
    # feature level: m/s^2, std per body axis (FRD) of one accelerometer sample (PX4 SIH's:
    # 0.28 0.95 0.80); the frame mean the observer reads has std / sqrt(samples per frame)
    accel_noise_std: tuple = (0.0, 0.0, 0.0)
    sensors: str = 'ideal'            # sensor_errors.PROFILES: each run draws its errors
    #: image level: the autopilot, 'sim' (the emulation) or a real firmware in lockstep ('px4',
    #: 'ardupilot'; worker w flies instance FIRMWARE_INSTANCE_BASE[autopilot] + w)
    autopilot: str = 'sim'
    sensor_overrides: tuple = ()      # (field, value) pairs replacing the profile's ranges

    @property
    def out_dir(self) -> str:
        """``<results_root>/<name>``."""
        return os.path.join(self.results_root, self.name)

    def model(self, params_text: str) -> dict:
        """Return the settings a run's outcome depends on (besides law, level and index)."""
        return {'gust_level': self.gust_level, 'vertical_factor': self.vertical_factor,
                'gust_frequency_hz': self.gust_frequency_hz,
                'gust_components': self.gust_components, 'flow_noise': self.flow_noise,
                'bearing_noise_rad': self.bearing_noise_rad, 'seed': self.seed,
                'image_level': self.image_level,
                'params_sha256': hashlib.sha256(params_text.encode()).hexdigest(),
                # only when set: campaigns stored before it existed still resume
                **({'estimate_error_rad': list(self.estimate_error_rad)}
                   if any(self.estimate_error_rad) else {}),
                **({'estimate_noise': list(self.estimate_noise)}
                   if self.estimate_noise is not None else {}),
                **({'camera_rate_hz': self.camera_rate_hz}
                   if self.camera_rate_hz != 50.0 else {}),
                **({'command_delay_s': self.command_delay_s} if self.command_delay_s else {}),
                **({'flow_strides': list(self.flow_strides)}
                   if tuple(self.flow_strides) != (1, 1) else {}),
                **({'accel_noise_std': list(self.accel_noise_std)}
                   if any(self.accel_noise_std) else {}),
                **({'sensors': self.sensors} if self.sensors != 'ideal' else {}),
                **({'autopilot': self.autopilot} if self.autopilot != 'sim' else {}),
                **({'sensor_overrides': [list(o) for o in self.sensor_overrides]}
                   if self.sensor_overrides else {})}


@dataclass(frozen=True)
class RunSpec:
    """One run: law, wind level (m/s^2), index, and what the index draws ({I}, rad)."""

    law: LawSpec
    level_mps2: float
    index: int
    initial_position_I: tuple
    direction_rad: float
    gust_seed: int

    def run_dir(self, out_dir: str) -> str:
        """``<out_dir>/runs/<law>/<level>/<index>``."""
        return os.path.join(out_dir, 'runs', self.law.label, level_name(self.level_mps2),
                            str(self.index))


def level_name(level_mps2: float) -> str:
    """Directory name of a wind level (m/s^2): '0', '0.2', '0.35'."""
    return f'{level_mps2:g}'


def draw_run(seed: int, index: int, box: dict) -> tuple[tuple, float, int]:
    """(start in {I} (m), wind direction (rad from north), gust seed) of run ``index``.

    ``box``: {'x': (lo, hi), 'y': ..., 'z': ...} (m, {I}), world.yaml's random box.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))
    xi = tuple(float(rng.uniform(*box[k])) for k in ('x', 'y', 'z'))
    direction = float(rng.uniform(0.0, 2.0 * math.pi))
    gust_seed = int(rng.integers(0, 2 ** 31 - 1))
    return xi, direction, gust_seed


def run_specs(cfg: CampaignConfig, box: dict) -> list[RunSpec]:
    """All runs of a campaign, law-major, then level, then index."""
    draws = [draw_run(cfg.seed, i, box) for i in range(cfg.runs)]
    return [RunSpec(law, float(level), i, *draws[i])
            for law in cfg.laws for level in cfg.levels_mps2 for i in range(cfg.runs)]


# --- flying ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Setup:
    world: object
    pad: object
    vehicle: object
    controller: object
    supervisor: object
    estimate_noise: tuple          # (std rad, tau s): the params' sim attitude_noise_*


def params_estimate_noise(params: dict) -> tuple[float, float]:
    """(std rad, tau s) of the sim's attitude-estimate error, as the sim node reads ``params``.

    ``params``: a loaded parameter file; the sim's code defaults under its ``/**`` block and
    ``sim`` section.
    """
    from ibvs_harness.core_configs import node_config
    from ibvs_sim.config import SimNodeConfig
    sim = node_config(SimNodeConfig, params, 'sim')
    return float(sim.attitude_noise_std_rad), float(sim.attitude_noise_tau_s)


def read_params(params_file: str | None) -> tuple[str, str]:
    """(path, text) of the params file (None: the installed params.yaml)."""
    if params_file is None:
        from ibvs_bringup.graph import default_params_file
        params_file = default_params_file()
    with open(params_file, encoding='utf-8') as f:
        return params_file, f.read()


@functools.lru_cache(maxsize=8)
def load_setup(params_file: str | None, overrides: tuple) -> _Setup:
    """World, pad, vehicle and the controller/supervisor configs as the nodes build them.

    ``ibvs_harness.core_configs`` (each node's code defaults, the file's ``/**`` block and
    its section: gains, laws, window and pad layout files) with ``overrides`` applied to
    force_controller. Cached per (file, overrides) in a process.
    """
    import yaml
    from ibvs_harness.core_configs import controller_config, supervisor_config
    from ibvs_common.core.config import load_pad_layout, load_vehicle
    from ibvs_sim.core.world import load_world
    _, text = read_params(params_file)
    params = yaml.safe_load(text) or {}

    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    try:
        ctrl = controller_config(params, overrides)
    except ValueError as exc:
        raise ValueError(f'law overrides in {params_file or "params.yaml"}: {exc}') from exc
    sup = supervisor_config(params)
    return _Setup(world, pad, vehicle, ctrl, sup, params_estimate_noise(params))


def run_wind(cfg: CampaignConfig, spec: RunSpec, mass_kg: float) -> WindConfig:
    """Return the run's ``dynamics.WindConfig`` (N, {I})."""
    from ibvs_sim.core.dynamics import WindConfig
    return WindConfig.from_level(spec.level_mps2, spec.direction_rad, mass_kg,
                                 cfg.vertical_factor, cfg.gust_level, cfg.gust_frequency_hz,
                                 cfg.gust_components, spec.gust_seed)


def run_record(cfg: CampaignConfig, spec: RunSpec, wind, summary: dict, wall_s: float,
               noise: tuple | None) -> dict:
    return {'campaign': cfg.name, 'feature_level': not cfg.image_level,
            'image_level': cfg.image_level, 'law': spec.law.label,
            'law_overrides': {k: v for k, v in spec.law.overrides},
            'wind_level_mps2': spec.level_mps2, 'wind_direction_rad': spec.direction_rad,
            'wind': {**asdict(wind), 'steady_force_I': list(wind.steady_force_I)},
            'index': spec.index, 'seed': cfg.seed, 'gust_seed': spec.gust_seed,
            'initial_position_I': list(spec.initial_position_I),
            'estimate_error_rad': list(cfg.estimate_error_rad),
            'estimate_noise': None if noise is None else list(noise),
            'failure_cause': failure_cause(summary), 'wall_time_s': wall_s}


def _write_summary(cfg: CampaignConfig, spec: RunSpec, summary: dict) -> None:
    from ibvs_harness.report import write_json
    path = os.path.join(spec.run_dir(cfg.out_dir), 'summary.json')
    tmp = path + '.tmp'
    write_json(tmp, summary)
    os.replace(tmp, path)          # atomic: an interrupted campaign leaves no half summary


def fly_run(cfg: CampaignConfig, spec: RunSpec) -> dict | None:
    """Fly one run, write its summary.json; return the summary (None: could not be flown)."""
    if cfg.image_level:
        return fly_image_run(cfg, spec)
    from ibvs_common.core.modes import Mode
    from ibvs_harness import feature_sim
    setup = load_setup(cfg.params_file, spec.law.overrides)
    wind = run_wind(cfg, spec, setup.vehicle.mass)
    noise_std, noise_tau = cfg.estimate_noise or setup.estimate_noise
    errors = run_sensor_errors(cfg, spec)
    true_vehicle, onboard_vehicle, controller = sensor_vehicles(setup, errors)
    sim_cfg = feature_sim.FeatureSimConfig(
        initial_position_I=np.asarray(spec.initial_position_I, dtype=float),
        initial_yaw=setup.world.initial_yaw, wind=wind,
        crossing_law=setup.controller.crossing_law, max_time_s=MAX_SIM_TIME_S,
        flow_noise=cfg.flow_noise, bearing_noise_rad=cfg.bearing_noise_rad,
        attitude_estimate_offset_rad=tuple(cfg.estimate_error_rad),
        attitude_noise_std=noise_std, attitude_noise_tau_s=noise_tau,
        seed=spec.gust_seed, camera_dt=feature_camera_dt(errors.camera_rate_hz),
        command_delay_s=cfg.command_delay_s + errors.latency_s,
        flow_stride_front=cfg.flow_strides[0], flow_stride_down=cfg.flow_strides[1],
        accel_noise_std_B=tuple(cfg.accel_noise_std))
    t0 = time.monotonic()
    summary, flog = feature_sim.run_feature_scenario(setup.world, setup.pad, true_vehicle,
                                                     controller, setup.supervisor, sim_cfg,
                                                     onboard_vehicle=onboard_vehicle)
    summary = dict(summary)
    summary['run'] = run_record(cfg, spec, wind, summary, time.monotonic() - t0,
                                (noise_std, noise_tau))
    summary['run']['sensor_errors'] = errors.as_dict()
    summary['run']['transitions'] = [f'-> {Mode(m).name} at t = {t:.2f} s: {why}'
                                     for m, t, why in flog.transitions]
    _write_summary(cfg, spec, summary)
    return summary


FEATURE_PHYSICS_DT_S = 0.004      # the feature-level loop's physics step (FeatureSimConfig)


def feature_camera_dt(rate_hz: float) -> float:
    """Return the feature-level frame period of a camera rate, a whole number of physics steps."""
    steps = max(1, int(round(1.0 / rate_hz / FEATURE_PHYSICS_DT_S)))
    return steps * FEATURE_PHYSICS_DT_S if rate_hz != 50.0 else 0.02


def run_sensor_errors(cfg: CampaignConfig, spec: RunSpec):
    """Return the run's drawn sensor errors (sensor_errors.draw; ideal: none, cfg's rate)."""
    from ibvs_harness import sensor_errors
    profile = dataclasses.replace(sensor_errors.PROFILES[cfg.sensors],
                                  camera_rate_hz=cfg.camera_rate_hz, **dict(cfg.sensor_overrides))
    if cfg.sensors == 'ideal' and not cfg.sensor_overrides:
        return sensor_errors.SensorDraw(camera_rate_hz=profile.camera_rate_hz)
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, spec.index, 46]))
    return sensor_errors.draw(profile, rng)


def sensor_vehicles(setup: '_Setup', errors) -> tuple:
    """Return (true vehicle, onboard vehicle, controller config) of a run's sensor errors."""
    if all(e == type(e)() for e in errors.cameras.values()):
        return setup.vehicle, setup.vehicle, setup.controller
    from ibvs_common.core.config import vehicle_from_dict
    from ibvs_harness import sensor_errors
    true_d, onboard_d = sensor_errors.vehicle_files(setup.vehicle.raw, errors)
    true_v, onboard_v = vehicle_from_dict(true_d), vehicle_from_dict(onboard_d)
    front, down = onboard_v.cameras['front'], onboard_v.cameras['down']
    ctrl = dataclasses.replace(setup.controller, R_BC_front=front.R_BC, R_BC_down=down.R_BC,
                               t_BC_front=front.t_BC, t_BC_down=down.t_BC)
    return true_v, onboard_v, ctrl


def image_run_params(cfg: CampaignConfig, spec: RunSpec, wind: WindConfig) -> dict:
    """params.yaml of an image-level run: the law's overrides and the wind's gusts and seed.

    The steady force goes on run_scenario's ``--wind`` ({I}, N; recorded in its summary);
    the gusts (``wind_gust_amplitude_N``, ``wind_gust_frequency_hz``) and their phases (the
    sim's ``seed``, which also seeds its sensor and read noise) through the sim's section.
    The sim node sums one sine per axis (K = 1), so K > 1 is refused here.
    """
    import yaml
    from ibvs_control.config import ForceControllerNodeConfig
    from ibvs_common.core.params import defaults
    from ibvs_harness.core_configs import checked_overrides
    if wind.gust_components != 1:
        raise ValueError('image level: the sim node takes one gust sine per axis '
                         '(--gust-components 1)')
    _, text = read_params(cfg.params_file)
    params = yaml.safe_load(text) or {}
    overrides = checked_overrides(ForceControllerNodeConfig, spec.law.overrides,
                                  'force_controller')
    kinds = defaults(ForceControllerNodeConfig)
    ctrl = params.setdefault('force_controller', {}).setdefault('ros__parameters', {})
    for name, value in overrides.items():   # a double as the node declares it (not 3 for 3.0)
        ctrl[name] = float(value) if isinstance(kinds[name], float) else value
    sim = params.setdefault('sim', {}).setdefault('ros__parameters', {})
    sim['wind_gust_amplitude_N'] = float(wind.gust_amplitude_N)
    sim['wind_gust_frequency_hz'] = float(wind.gust_frequency_hz)
    sim['seed'] = int(wind.seed)
    sim['attitude_estimate_offset_rad'] = [float(a) for a in cfg.estimate_error_rad]
    if cfg.estimate_noise is not None:
        sim['attitude_noise_std_rad'], sim['attitude_noise_tau_s'] = (
            float(x) for x in cfg.estimate_noise)
    return params


def image_sensor_options(run_dir: str, errors) -> list[str]:
    """Return run_scenario's camera-model options of a run's drawn sensor errors.

    The delivery latency and jitter (``--camera-latency``, ``--camera-jitter``, ms); with
    mount, intrinsic, lever-arm or time-offset errors the true and the calibrated vehicle
    files (sensor_errors.vehicle_files) written to ``run_dir`` (``true_vehicle.yaml``,
    ``onboard_vehicle.yaml``: ``--true-vehicle``, ``--onboard-vehicle``), which also carry
    the camera rate; without them a rate other than 50 Hz goes on ``--camera-rate``.
    """
    import yaml
    from ibvs_common.core.config import load_vehicle
    from ibvs_harness import sensor_errors
    opts = []
    if errors.latency_s or errors.jitter_s:
        opts += ['--camera-latency', f'{1e3 * errors.latency_s!r}',
                 '--camera-jitter', f'{1e3 * errors.jitter_s!r}']
    if all(e == type(e)() for e in errors.cameras.values()):
        if errors.camera_rate_hz != 50.0:
            opts += ['--camera-rate', f'{errors.camera_rate_hz!r}']
        return opts
    true_d, onboard_d = sensor_errors.vehicle_files(load_vehicle().raw, errors)
    for option, name, data in (('--true-vehicle', 'true_vehicle.yaml', true_d),
                               ('--onboard-vehicle', 'onboard_vehicle.yaml', onboard_d)):
        path = os.path.abspath(os.path.join(run_dir, name))
        with open(path, 'w', encoding='utf-8') as f:
            yaml.safe_dump(data, f, sort_keys=False)
        opts += [option, path]
    return opts


def fly_image_run(cfg: CampaignConfig, spec: RunSpec) -> dict | None:
    """Fly one run through the whole graph (``python -m ibvs_harness.run_scenario``).

    Lockstep sim time; no bag, no plots; ROS_DOMAIN_ID from this process's environment (set
    per worker by :func:`run_campaign`). The flight's own directory is ``<run>/flight/``
    (logs, run_scenario's summary.json); ``<run>/summary.json`` is written only when the run
    could be flown (run_scenario exit code 0 or 1), so a resume retries the others.
    """
    import subprocess
    import yaml
    from ibvs_common.core.config import load_vehicle
    run_dir = spec.run_dir(cfg.out_dir)
    os.makedirs(run_dir, exist_ok=True)
    wind = run_wind(cfg, spec, load_vehicle().mass)
    params_path = os.path.join(run_dir, 'params.yaml')
    params = image_run_params(cfg, spec, wind)
    with open(params_path, 'w', encoding='utf-8') as f:
        yaml.safe_dump(params, f, sort_keys=False)
    errors = run_sensor_errors(cfg, spec)
    cmd = [sys.executable, '-m', cfg.scenario_module, '--run-name', 'flight',
           '--results-root', run_dir, '--params-file', params_path, '--no-bag', '--no-plots',
           '--timeout', f'{cfg.run_timeout_s:g}', '--initial-position',
           *(f'{x!r}' for x in spec.initial_position_I),
           '--wind', *(f'{x!r}' for x in wind.steady_force_I),
           *image_sensor_options(run_dir, errors), *firmware_options(cfg)]
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    t0 = time.monotonic()
    with open(os.path.join(run_dir, 'run_scenario.log'), 'w', encoding='utf-8') as log:
        code = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                              timeout=cfg.run_timeout_s + 120.0).returncode
    try:
        with open(os.path.join(run_dir, 'flight', 'summary.json'), encoding='utf-8') as f:
            summary = json.load(f)
    except (OSError, ValueError):
        summary = None
    if code not in (0, 1) or summary is None:
        return None
    summary['flight_run'] = summary.pop('run', {})
    summary['run'] = run_record(cfg, spec, wind, summary, time.monotonic() - t0,
                                params_estimate_noise(params))
    summary['run']['ros_domain_id'] = env.get('ROS_DOMAIN_ID')
    summary['run']['sensor_errors'] = errors.as_dict()
    _write_summary(cfg, spec, summary)
    return summary


#: image level on a real firmware: worker w flies this instance + w (PX4: 5-9, whose ports
#: px4_sih.free_instance also picks from; ArduPilot: 1-4)
FIRMWARE_INSTANCE_BASE = {'px4': 5, 'ardupilot': 1}
FIRMWARE_MAX_WORKERS = {'px4': 5, 'ardupilot': 4}
WORKER_ENV = 'IBVS_CAMPAIGN_WORKER'


def firmware_options(cfg: CampaignConfig) -> list:
    """Return run_scenario's autopilot options of an image-level run (none for the emulation).

    Each worker flies its own firmware instance (its ports), so parallel runs never race
    for a free one.
    """
    if cfg.autopilot == 'sim':
        return []
    worker = int(os.environ.get(WORKER_ENV, '0'))
    return ['--autopilot', cfg.autopilot,
            '--px4-instance', str(FIRMWARE_INSTANCE_BASE[cfg.autopilot] + worker)]


def _fly_task(task: tuple) -> tuple[int, dict | None]:
    k, cfg, spec = task
    return k, fly_run(cfg, spec)


def _init_worker(domains) -> None:
    """Pool initializer: this worker's own ROS_DOMAIN_ID (image level: isolated graphs).

    Also its index (:data:`WORKER_ENV`), for its firmware instance.
    """
    domain, worker = domains.get()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ[WORKER_ENV] = str(worker)


def read_summary(cfg: CampaignConfig, spec: RunSpec) -> dict | None:
    """Return the stored summary.json of a run, or None."""
    path = os.path.join(spec.run_dir(cfg.out_dir), 'summary.json')
    try:
        with open(path, encoding='utf-8') as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def check_manifest(cfg: CampaignConfig) -> None:
    """Write campaign.json, or refuse (ValueError) to resume a campaign of other settings."""
    _, text = read_params(cfg.params_file)
    model = cfg.model(text)
    path = os.path.join(cfg.out_dir, 'campaign.json')
    if os.path.exists(path):
        with open(path, encoding='utf-8') as f:
            old = json.load(f).get('model', {})
        diff = {k: (old.get(k), v) for k, v in model.items() if old.get(k) != v}
        if diff:
            raise ValueError(f'{cfg.out_dir} holds a campaign of other settings '
                             f'(old, new): {diff}; use another --name or delete it')
    os.makedirs(cfg.out_dir, exist_ok=True)
    with open(path, 'w', encoding='utf-8') as f:
        json.dump({'name': cfg.name, 'model': model,
                   'laws': [{'label': law.label, 'overrides': dict(law.overrides)}
                            for law in cfg.laws],
                   'levels_mps2': list(cfg.levels_mps2), 'runs': cfg.runs}, f, indent=2)


def run_campaign(cfg: CampaignConfig, workers: int = 1,
                 progress: Callable[[str], None] | None = print,
                 max_wall_s: float | None = None) -> list[dict]:
    """Fly the runs that have no summary.json yet (``workers`` processes); return all summaries.

    Returned: the summaries of every run of the campaign that has one (stored or just flown;
    an image-level run that could not be flown has none). Image level: each worker process
    sets its own ROS_DOMAIN_ID (``domain_base`` + worker) before it starts any graph.
    ``max_wall_s``: stop flying after this many seconds of wall clock (the runs in flight are
    dropped, the stored ones kept: resume later). Raises ValueError for a resume with other
    settings or a bad law override.
    """
    from ibvs_sim.core.world import load_world
    check_manifest(cfg)
    for law in cfg.laws:                   # a bad override fails here, not in every worker
        load_setup(cfg.params_file, law.overrides)
    specs = run_specs(cfg, load_world().random_box)
    done = {s: read_summary(cfg, s) for s in specs}
    # index-major: a campaign stopped early has about as many runs at every law and level
    pending = sorted((s for s in specs if done[s] is None),
                     key=lambda s: (s.index, s.law.label, s.level_mps2))
    if progress:
        progress(f'campaign {cfg.name}: {len(specs)} runs, {len(specs) - len(pending)} done, '
                 f'{len(pending)} to fly on {workers} worker(s)')
    t0 = time.monotonic()
    tasks = [(k, cfg, s) for k, s in enumerate(pending)]
    # spawned workers: a fork of a process with threads (DDS, once rclpy is loaded, e.g. in a
    # test worker) can deadlock (measured: a CI worker hung 600 s)
    ctx = multiprocessing.get_context('spawn')
    pool = None
    if cfg.image_level:                    # every run in a worker with its own domain
        domains = ctx.Queue()
        for w in range(workers):
            domains.put(((cfg.domain_base + w) % 233, w))
        pool = ctx.Pool(workers, initializer=_init_worker, initargs=(domains,))
    elif workers > 1 and len(tasks) > 1:
        pool = ctx.Pool(workers)
    results = map(_fly_task, tasks) if pool is None else \
        pool.imap_unordered(_fly_task, tasks, chunksize=1)
    every = 1 if cfg.image_level else 20
    try:
        for k, (i, summary) in enumerate(results, 1):
            done[pending[i]] = summary
            if summary is None and progress:
                progress(f'  {pending[i].run_dir(cfg.out_dir)}: could not be flown '
                         '(see its run_scenario.log)')
            if progress and (k % every == 0 or k == len(tasks)):
                progress(f'  {k} / {len(tasks)} flown, {time.monotonic() - t0:.0f} s')
            if max_wall_s is not None and time.monotonic() - t0 > max_wall_s:
                if progress:
                    progress(f'  stopped after {max_wall_s:g} s of wall clock: {k} / '
                             f'{len(tasks)} flown (resume with the same command)')
                break
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
    return [done[s] for s in specs if done[s] is not None]


# --- output ---------------------------------------------------------------------------------

def write_outputs(cfg: CampaignConfig, summaries: list[dict], plots: bool = True) -> list[dict]:
    """aggregate.json, table.md and the plots (if matplotlib imports); return the rows."""
    rows = aggregate(summaries)
    with open(os.path.join(cfg.out_dir, 'aggregate.json'), 'w', encoding='utf-8') as f:
        json.dump({'name': cfg.name, 'rows': rows}, f, indent=2)
    level = 'image level (whole graph, lockstep)' if cfg.image_level else 'feature level'
    if cfg.autopilot != 'sim':
        level += f', on {cfg.autopilot} firmware'
    header = (f'Campaign {cfg.name}: {level}, {cfg.runs} runs per law and level, starts '
              f'in the SPEC box, wind towards a random horizontal direction, vertical '
              f'x{cfg.vertical_factor:g} (down), gusts {100 * cfg.gust_level:g} % '
              f'({cfg.gust_components} sine(s) per axis, {cfg.gust_frequency_hz:g} Hz), '
              f'seed {cfg.seed}.\n\n')
    with open(os.path.join(cfg.out_dir, 'table.md'), 'w', encoding='utf-8') as f:
        f.write(header + format_table(rows))
    if plots:
        write_plots(rows, summaries, cfg.out_dir)
    return rows


# --- command line ---------------------------------------------------------------------------

def sensor_overrides(items: list) -> tuple:
    """Parse ``FIELD=VALUE`` (a float, or two for a range) of --sensor-set; ValueError if bad."""
    from ibvs_harness.sensor_errors import SensorProfile
    known = {f.name for f in dataclasses.fields(SensorProfile)}
    out = []
    for item in items:
        name, _, value = item.partition('=')
        if name not in known or not value:
            raise ValueError(f'--sensor-set {item!r}: not FIELD=VALUE of {sorted(known)}')
        numbers = tuple(float(v) for v in value.split(','))
        out.append((name, numbers if len(numbers) > 1 else numbers[0]))
    return tuple(out)


def checked_sensor_overrides(parser: argparse.ArgumentParser, items: list) -> tuple:
    """Return sensor_overrides(items), or end the command with its error (exit status 2)."""
    try:
        return sensor_overrides(items)
    except ValueError as exc:
        parser.error(str(exc))


def parse_args(argv: list | None = None) -> tuple[CampaignConfig, int, bool, bool,
                                                  float | None]:
    """Parse the command line into (config, workers, plots, aggregate_only, max_wall_s)."""
    p = argparse.ArgumentParser(
        prog='python -m ibvs_harness.campaign',
        description='Monte Carlo campaign under wind, feature level (issue 14): N random '
                    'starts in the SPEC box per law and wind level; resumable.')
    p.add_argument('--name', default='feature',
                   help='results/campaign/<name>/ (a resume needs the same settings)')
    p.add_argument('--runs', type=int, default=500, help='runs per law and wind level')
    p.add_argument('--levels', type=float, nargs='+', default=list(DEFAULT_LEVELS_MPS2),
                   metavar='A', help='wind levels, m/s^2 of |Delta_h| / m (default: '
                   + ' '.join(f'{x:g}' for x in DEFAULT_LEVELS_MPS2) + ')')
    p.add_argument('--gust-level', type=float, default=0.3,
                   help='gust amplitude as a fraction of the steady horizontal force')
    p.add_argument('--vertical-factor', type=float, default=0.3,
                   help='steady vertical force / horizontal (positive: down, +z_I)')
    p.add_argument('--gust-frequency', type=float, default=0.5, metavar='HZ')
    p.add_argument('--gust-components', type=int, default=1, metavar='K',
                   help='sines per axis (docs/sim.md "Wind")')
    p.add_argument('--crossing-law', nargs='+', default=None,
                   choices=('closed', 'intended', 'seed'),
                   help='mode-2 laws to compare, each a law labelled by its name')
    p.add_argument('--law', action='append', default=[], metavar='LABEL[:NAME=VALUE,...]',
                   help='a law: a crossing or disturbance law name (closed, intended, seed; '
                        'paper, integral, observer) or a label with force_controller '
                        'parameter overrides, e.g. "stiff:crossing.kf=3.0" (repeatable; '
                        "default: params.yaml's laws, labelled by its disturbance_law)")
    p.add_argument('--workers', type=int, default=os.cpu_count() or 1)
    p.add_argument('--seed', type=int, default=14, help='campaign seed')
    p.add_argument('--flow-noise', type=float, default=0.0, help='1/s, per flow component')
    p.add_argument('--bearing-noise', type=float, default=0.0, help='rad, per bearing')
    p.add_argument('--estimate-error', type=float, nargs=2, default=(0.0, 0.0),
                   metavar=('ROLL_DEG', 'PITCH_DEG'),
                   help="static error of the autopilot's attitude estimate, flown and read "
                        '(docs/design.md "Attitude-estimate error"), each within +-11 deg')
    p.add_argument('--estimate-noise', type=float, nargs=2, default=None,
                   metavar=('STD_DEG', 'TAU_S'),
                   help="wandering error of the autopilot's attitude estimate (Gauss-Markov per "
                        'axis: std in deg, within [0, 5.7], correlation time in s), flown and '
                        "read at both levels; default: the params file's sim "
                        'attitude_noise_std_rad / attitude_noise_tau_s (PX4 SIH fit)')
    p.add_argument('--camera-rate', type=float, default=50.0, metavar='HZ',
                   help='the camera (feature level: control) rate, e.g. 30, or 25 at feature '
                        'level for every second frame of a 50 Hz camera')
    p.add_argument('--command-delay', type=float, default=0.0, metavar='MS',
                   help='feature level: ms from a frame stamp to its setpoint at the vehicle '
                        '(camera delivery + the graph), on top of the sensors\' latency')
    p.add_argument('--flow-strides', type=int, nargs=2, default=(1, 1),
                   metavar=('FRONT', 'DOWN'),
                   help='feature level: each flow measured on every Nth frame and held on the '
                   'others (the graph shedding that flow on a slow computer)')
    p.add_argument('--accel-noise', type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=('X', 'Y', 'Z'),
                   help='feature level: m/s^2, std per body axis (FRD) of one accelerometer '
                        "sample at 100 Hz, white (PX4 SIH's as the bridge receives it: 0.28 "
                        '0.95 0.80); the observer reads the frame mean')
    p.add_argument('--sensors', default='ideal', choices=('ideal', 'realistic'),
                   help="each run draws its camera errors: 'realistic' = latency 15-40 ms, "
                        'mounts within 1 deg, focal 0.5 %%, principal point 2 px, lever arms '
                        'of 5 cm known within 5 mm, camera-IMU offset within 3 ms '
                        '(sensor_errors.py; feature level: latency, mounts, lever arms; image '
                        'level: all, the sim flying the true vehicle, the graph the '
                        'calibrated one)')
    p.add_argument('--sensor-set', action='append', default=[], metavar='FIELD=VALUE',
                   help='replace one range of the sensor profile (sensor_errors.SensorProfile), '
                        'e.g. mount_error_rad=0.035 or latency_s=0.06,0.06 (repeatable)')
    p.add_argument('--params-file', default=None, help='default: the installed params.yaml')
    p.add_argument('--results-root', default=DEFAULT_RESULTS_ROOT)
    p.add_argument('--no-plots', action='store_true')
    p.add_argument('--image-level', action='store_true',
                   help='fly the whole graph in lockstep (run_scenario subprocesses, one '
                        'ROS_DOMAIN_ID per worker; minutes per run)')
    p.add_argument('--autopilot', choices=('sim', 'px4', 'ardupilot'), default='sim',
                   help="image level: the sim's autopilot emulation, or a real firmware flying "
                        'the plant in lockstep (PX4 v1.16, ArduCopter 4.5.6; needs ../shared; '
                        'docs/firmware_lockstep.md); the same starts and wind for every choice')
    p.add_argument('--domain-base', type=int, default=100,
                   help='image level: worker w uses ROS_DOMAIN_ID base + w')
    p.add_argument('--run-timeout', type=float, default=900.0, metavar='S',
                   help='image level: wall-clock limit of one run')
    p.add_argument('--aggregate-only', action='store_true',
                   help='fly nothing: aggregate the stored runs')
    p.add_argument('--max-wall', type=float, default=None, metavar='S',
                   help='stop flying after S s of wall clock (resumable), then aggregate')
    a = p.parse_args(argv)
    if a.runs < 1 or a.workers < 1 or a.gust_components < 1 or a.gust_level < 0 \
            or any(x < 0 or not math.isfinite(x) for x in a.levels):
        p.error('--runs, --workers, --gust-components >= 1; levels and gust level >= 0')
    if not all(math.isfinite(x) and abs(x) <= 11.0 for x in a.estimate_error):
        p.error('--estimate-error: roll and pitch in degrees, each finite and within +-11')
    if a.estimate_noise is not None and not (
            all(math.isfinite(x) for x in a.estimate_noise)
            and 0.0 <= a.estimate_noise[0] <= 5.7 and a.estimate_noise[1] >= 0.0):
        p.error('--estimate-noise: std in degrees within [0, 5.7], time constant in s >= 0')
    if not all(c.isalnum() or c in '_.+-' for c in a.name) or a.name in ('', '.', '..'):
        p.error(f'bad --name {a.name!r}: use letters, digits, _ . + -')
    try:
        laws = [LawSpec.parse(x) for x in (a.crossing_law or [])] + \
            [LawSpec.parse(x) for x in a.law]
    except ValueError as exc:
        p.error(str(exc))
    if not laws:                  # the file's laws, labelled by its disturbance law
        import yaml
        from ibvs_harness.core_configs import controller_node_config
        _, text = read_params(a.params_file)
        try:
            ctrl = controller_node_config(yaml.safe_load(text))
        except ValueError as exc:
            p.error(f'force_controller parameters of {a.params_file or "params.yaml"}: {exc}')
        laws = [LawSpec(str(ctrl.disturbance_law))]
    if len({law.label for law in laws}) != len(laws):
        p.error('law labels must be unique')
    if min(a.flow_strides) < 1:
        p.error('--flow-strides must be >= 1')
    if not all(math.isfinite(x) and x >= 0.0 for x in a.accel_noise):
        p.error('--accel-noise: each std finite and >= 0')
    if a.image_level and any(a.accel_noise):
        p.error("--accel-noise is a feature-level model: the image level's IMU is the sim's "
                "autopilot's (or the firmware's)")
    if a.image_level and tuple(a.flow_strides) != (1, 1):
        p.error('--flow-strides is a feature-level model: the image level flies the graph')
    if a.autopilot != 'sim' and not a.image_level:
        p.error('--autopilot px4|ardupilot flies the graph: it needs --image-level')
    if a.autopilot != 'sim' and a.workers > FIRMWARE_MAX_WORKERS[a.autopilot]:
        p.error(f'--autopilot {a.autopilot}: at most {FIRMWARE_MAX_WORKERS[a.autopilot]} '
                'workers (one firmware instance each)')
    if a.image_level and a.command_delay:
        p.error('--command-delay is the feature level\'s model of the graph\'s delay: the '
                'image level flies the graph itself (--sensors for the cameras\' latency)')
    cfg = CampaignConfig(name=a.name, runs=a.runs, levels_mps2=tuple(sorted(set(a.levels))),
                         laws=tuple(laws), gust_level=a.gust_level,
                         vertical_factor=a.vertical_factor, gust_frequency_hz=a.gust_frequency,
                         gust_components=a.gust_components, flow_noise=a.flow_noise,
                         bearing_noise_rad=a.bearing_noise, seed=a.seed,
                         estimate_error_rad=tuple(math.radians(x) for x in a.estimate_error),
                         estimate_noise=None if a.estimate_noise is None else (
                             math.radians(a.estimate_noise[0]), a.estimate_noise[1]),
                         params_file=a.params_file, results_root=a.results_root,
                         image_level=a.image_level, domain_base=a.domain_base,
                         run_timeout_s=a.run_timeout, camera_rate_hz=a.camera_rate,
                         command_delay_s=a.command_delay / 1e3,
                         flow_strides=tuple(a.flow_strides), sensors=a.sensors,
                         accel_noise_std=tuple(a.accel_noise),
                         autopilot=a.autopilot,
                         sensor_overrides=checked_sensor_overrides(p, a.sensor_set))
    return cfg, a.workers, not a.no_plots, a.aggregate_only, a.max_wall


def main(argv: list | None = None) -> int:
    """Run (or aggregate) a campaign from the command line; 0 on success, 2 on a bad setup."""
    from ibvs_bringup.graph import ensure_ament_prefix_path
    ensure_ament_prefix_path()
    cfg, workers, plots, aggregate_only, max_wall_s = parse_args(argv)
    t0 = time.monotonic()
    try:
        if aggregate_only:
            from ibvs_sim.core.world import load_world
            summaries = [s for s in (read_summary(cfg, spec) for spec in
                                     run_specs(cfg, load_world().random_box)) if s]
            if not summaries:
                print(f'campaign: no stored runs in {cfg.out_dir}', file=sys.stderr)
                return 2
        else:
            summaries = run_campaign(cfg, workers, max_wall_s=max_wall_s)
    except (ValueError, OSError) as exc:
        print(f'campaign: {exc}', file=sys.stderr)
        return 2
    rows = write_outputs(cfg, summaries, plots)
    print(format_table(rows), end='')
    print(f'{len(summaries)} runs -> {cfg.out_dir} ({time.monotonic() - t0:.0f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
