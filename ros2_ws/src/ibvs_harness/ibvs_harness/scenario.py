"""What every scenario run shares: its options, its start, its results directory and its end.

Used by :mod:`~ibvs_harness.run_scenario` (the sim), :mod:`~ibvs_harness.px4_scenario` (PX4
SIH) and the campaigns: the options of one run, the random initial condition, a free UDP port
for the sim's autopilot, ``results/<run>/``, the ``run`` block of summary.json, the closing
line, and the supervisor's transitions read from its log.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
import re
import shutil
from typing import Iterable

from ibvs_bringup import graph
from ibvs_bringup.runner import process_names
from ibvs_harness import plots, report
from ibvs_sim.core.world import load_world, WorldConfig
import numpy as np

MAX_SIM_TIME_S = 60.0
SHUTDOWN_GRACE_S = 3.0        # sim s after touchdown in mode 4 to wait for the disarm
IDLE_MODE = 0
FAILSAFE_MODE = 5
SHUTDOWN_MODE = 4
DEFAULT_IMAGE_EVERY = 5       # bag: every 5th camera frame (10 Hz), all other topics in full
AUTOPILOTS = ('sim', 'px4-sih', 'px4', 'ardupilot')   # --autopilot: the first is the default


@dataclass
class RunOptions:
    """Everything one run needs (from the command line or a test)."""

    run_name: str
    results_root: str = 'results'
    initial_position: tuple | None = None
    wind: tuple | None = None
    crossing_law: str | None = None
    bag: bool = True
    image_every: int = DEFAULT_IMAGE_EVERY
    feature_level: bool = False
    timeout_s: float = 900.0            # wall clock, whole run
    preflight_timeout_s: float = 120.0  # wall clock
    mavlink_port: int | None = None     # None: a free port
    params_file: str | None = None
    real_time_factor: float | None = None   # free-running sim at this factor (None: lockstep)
    kill_node: str | None = None        # fault injection: SIGKILL this node ...
    kill_at_s: float = 2.0              # ... at this sim time (perception nodes come back)
    kill_once_engaged: bool = False     # ... and not before the bridge reports 'engaged'
    # fault injection: camera -> [start, end, start, end, ...] (sim s), one or more windows
    camera_off: dict = field(default_factory=dict)
    camera_freeze: dict = field(default_factory=dict)
    imu_off: tuple | None = None        # fault injection: [start, end] sim s without IMU
    imu_nan: tuple | None = None        # fault injection: [start, end] sim s of NaN IMU
    plots: bool = True
    extra: dict = field(default_factory=dict)
    autopilot: str = 'sim'              # 'sim' | 'px4-sih' (PX4 SITL is plant and autopilot)
    px4_instance: int | None = None     # px4-sih, px4, ardupilot: the firmware's instance
    px4_flight_s: float | None = None   # px4-sih: stop this long after ibvs/start (None: 60 s)
    px4_no_mocap: bool = False          # px4-sih: PX4 on SIH's GPS / baro / mag, no mocap
    pilot_switch: bool = False          # started by the pilot's RC switch (the sim's radio)
    pilot_switch_off_s: float | None = None   # ... and aborted by it at this sim time
    layout: str = 'processes'           # runner.LAYOUTS: 'processes' | 'composed' | 'grouped'
    max_sim_time_s: float = MAX_SIM_TIME_S  # sim s after the start, then the run stops
    follow_failsafe: bool = False       # after FAILSAFE, watch the autopilot land and disarm
    # the sim's camera model: sim parameter -> value (camera_latency_s, camera_rate_hz, ...)
    camera_model: dict = field(default_factory=dict)
    true_vehicle: str | None = None     # the vehicle the sim flies and renders (None: onboard's)
    onboard_vehicle: str | None = None  # the onboard nodes' calibration (None: installed)

    @property
    def out_dir(self) -> str:
        return os.path.join(self.results_root, self.run_name)


def random_initial_position(seed: int, world: WorldConfig | None = None) -> tuple:
    """Draw an initial position uniformly from world.yaml's random box (docs/spec.md section 2)."""
    box = (world or load_world()).random_box
    rng = np.random.default_rng(seed)
    return tuple(float(rng.uniform(*box[k])) for k in ('x', 'y', 'z'))


def prepare_out_dir(opts: RunOptions) -> str:
    """Create an empty results/<run>/ (a previous run of the same name is replaced)."""
    if not re.fullmatch(r'[A-Za-z0-9_.+-]+', opts.run_name) or opts.run_name in ('.', '..'):
        raise ValueError(f'bad run name {opts.run_name!r}: use letters, digits, _ . + -')
    out = opts.out_dir
    if os.path.isdir(out):
        shutil.rmtree(out)
    os.makedirs(out)
    return out


def run_block(opts: RunOptions, initial_position, **more) -> dict:
    """Return the ``run`` block of summary.json: the options that made the run, and ``more``."""
    return {'name': opts.run_name, 'layout': opts.layout,
            'initial_position_I': list(initial_position),
            'wind_N': list(opts.wind) if opts.wind else [0.0, 0.0, 0.0],
            'crossing_law': opts.crossing_law or 'params.yaml',
            'feature_level': opts.feature_level, **opts.extra, **more}


def finish(opts: RunOptions, summary: dict, data: plots.RunData | None) -> int:
    """Write summary.json and the plots, print the closing line; return the exit code."""
    report.write_json(os.path.join(opts.out_dir, 'summary.json'), summary)
    if data is not None and opts.plots:
        plots.plot_run(data, opts.out_dir)
    w, ld = summary.get('window', {}), summary.get('landing', {})
    why = failure_explanation(summary)
    print(f"run {opts.run_name}: success={summary.get('success')} "
          f"crossed={w.get('crossed')} clearance={w.get('min_clearance_m')} "
          f"landed={ld.get('landed')} error={ld.get('error_m')} "
          f"td_speed={ld.get('touchdown_speed_mps')} duration={summary.get('duration_s')} "
          f"-> {opts.out_dir}" + (f'; failed: {why}' if why else ''), flush=True)
    if summary.get('run', {}).get('error'):
        return 2
    return 0 if summary.get('success') else 1


TRANSITION_LINE = re.compile(r'\]: (mode \w+ -> \w+ at t = .*)$')


def failure_explanation(summary: dict) -> str | None:
    """Say why a run failed in one phrase (None: a success), for its closing console line.

    The run's error if it has one; else the campaign's failure cause (docs/spec.md section 5,
    ``campaign_stats.failure_cause``), with the supervisor's own reason when it failed safe
    (the last '-> FAILSAFE' transition of summary.json's ``run.transitions``).
    """
    from ibvs_harness.campaign_stats import failure_cause
    if summary.get('success'):
        return None
    run = summary.get('run', {})
    if run.get('error'):
        return f"error: {run['error']}"
    cause = failure_cause(summary) or 'other'
    if cause.startswith('failsafe'):
        reasons = [t.split(': ', 1)[1] for t in run.get('transitions', [])
                   if '-> FAILSAFE' in t and ': ' in t]
        if reasons:
            return f'{cause} ({reasons[-1]})'
    return cause


def supervisor_log(out_dir: str) -> str:
    """Return the log holding the supervisor's lines: its own, or its container's.

    The first of runner.process_names that exists (the last one when none does).
    """
    logs = [os.path.join(out_dir, 'logs', f'{name}.log')
            for name in process_names('mode_supervisor')]
    return next((log for log in logs if os.path.exists(log)), logs[-1])


def supervisor_transitions(log_path: str) -> list[str]:
    """Return the mode supervisor's transition lines ('mode A -> B at t = ... s: reason')."""
    try:
        with open(log_path, errors='replace') as f:
            return [m.group(1) for m in map(TRANSITION_LINE.search, f) if m]
    except OSError:
        return []


def missing_executables(specs: Iterable[graph.NodeSpec]) -> list[str]:
    """Return why nodes of ``specs`` cannot start here (empty: all present)."""
    from ibvs_bringup.ros2run import unavailable_reason
    return [r for r in (unavailable_reason(s.package, s.executable) for s in specs) if r]
