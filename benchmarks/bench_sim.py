"""Benchmark of ibvs_sim: both cameras at 50 Hz plus physics, against real time.

Runs the Simulation core (no ROS, no MAVLink: a constant hover reference stands in for the
autopilot) along a path from the start to the pad, and prints the ratio of simulated to wall
time (target >= 2) and the per-frame times: physics (10 substeps), and the frame's images as
the sim node makes them (``CameraRig.render``: both cameras, their read noise at the sim
node's default ``camera_read_noise_std``, 1.5 grey levels, the cameras on parallel threads;
``--serial``: one after the other, as before 2026-11-26; ``--no-noise``: noise-free) with
each camera's own render time. What the node adds per frame (ROS messages, publication,
MAVLink telemetry) is not counted:
``run_scenario``'s summary.json ``timing`` gives the node's whole budget (docs/sim.md).
"""
import argparse
import time

import numpy as np

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import rot_from_euler_zyx
from ibvs_common.core.params import defaults
from ibvs_sim.config import SimNodeConfig
from ibvs_sim.core.autopilot import AttitudeReference
from ibvs_sim.core.sim_core import SimConfig, Simulation

LEVEL_Q = np.array([1.0, 0.0, 0.0, 0.0])
READ_NOISE_STD = defaults(SimNodeConfig)['camera_read_noise_std']   # grey levels, the sim's


class HoverReference:
    """Stand-in autopilot: level attitude, hover thrust."""

    last_setpoint_time_boot_ms = None

    def __init__(self, hover_thrust: float) -> None:
        self.hover_thrust = hover_thrust

    def poll(self, state, receive: bool = True, telemetry: bool = True) -> None:
        """Nothing to receive or send (the physics.ReferenceSource protocol)."""

    def attitude_reference(self, state) -> AttitudeReference:
        return AttitudeReference(LEVEL_Q, self.hover_thrust, 'hold')

    def estimate_error(self, t: float) -> np.ndarray:
        """Return R_err = I: a perfect attitude estimate."""
        return np.eye(3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=250, help='camera frames (50 Hz)')
    parser.add_argument('--serial', action='store_true',
                        help='render the cameras one after the other (not in parallel)')
    parser.add_argument('--no-noise', action='store_true', help='noise-free renders')
    args = parser.parse_args()
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    config = SimConfig(parallel_render=not args.serial,
                       read_noise_std=0.0 if args.no_noise else READ_NOISE_STD)
    sim = Simulation(world, pad, vehicle, HoverReference(vehicle.hover_thrust), config)
    sim.step_frame()
    # Render along the reference path (start -> window -> pad) to cover every view.
    path = np.linspace(world.initial_position_I, [0.0, 0.0, -0.3], args.frames)
    render_ms = {name: [] for name in sim.cameras.renderers}
    physics_ms, images_ms = [], []
    for name, r in sim.cameras.renderers.items():       # each camera alone (not in the wall time)
        for k in range(args.frames):
            R_IB = rot_from_euler_zyx(0.05 * np.sin(k / 7), 0.05 * np.cos(k / 9), 0.0)
            t0 = time.perf_counter()
            r.render(R_IB, path[k])
            render_ms[name].append((time.perf_counter() - t0) * 1e3)
    wall0 = time.perf_counter()
    for k in range(args.frames):
        sim.state.xi_I = path[k].copy()
        sim.state.R_IB = rot_from_euler_zyx(0.05 * np.sin(k / 7), 0.05 * np.cos(k / 9), 0.0)
        t0 = time.perf_counter()
        renderers, sim.cameras.renderers = sim.cameras.renderers, {}
        sim.step_frame()                         # physics only
        sim.cameras.renderers = renderers
        physics_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        sim.cameras.render(sim.state.R_IB, sim.state.xi_I, k)
        images_ms.append((time.perf_counter() - t0) * 1e3)
    wall = time.perf_counter() - wall0
    sim.close()
    sim_time = args.frames / sim.config.camera_rate_hz
    mode = 'one after the other' if args.serial else 'in parallel'
    print(f'frames: {args.frames} ({sim_time:.1f} s of sim time), wall {wall:.2f} s')
    print(f'ratio to real time: {sim_time / wall:.2f} (target >= 2)')
    print(f'physics per frame ({sim.substeps} substeps): median '
          f'{np.median(physics_ms):.2f} ms, p99 {np.percentile(physics_ms, 99):.2f} ms')
    print(f'images per frame (both cameras {mode}, read noise {config.read_noise_std:g}): '
          f'median {np.median(images_ms):.2f} ms, p99 {np.percentile(images_ms, 99):.2f} ms')
    for name, ms in render_ms.items():
        print(f'render {name} alone: median {np.median(ms):.2f} ms, '
              f'p99 {np.percentile(ms, 99):.2f} ms')


if __name__ == '__main__':
    main()
