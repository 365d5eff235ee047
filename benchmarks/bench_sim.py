"""Benchmark of ibvs_sim: both cameras at 50 Hz plus physics, against real time.

Runs the Simulation core (no ROS, no MAVLink: a constant hover reference stands in for the
autopilot) along a path from the start to the pad, and prints the ratio of simulated to wall
time (target >= 2) and the per-frame render time (median, p99) of each camera.
"""
import argparse
import time

import numpy as np

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.frames import rot_from_euler_zyx
from ibvs_sim.core.autopilot import AttitudeReference
from ibvs_sim.core.sim_core import SimConfig, Simulation

LEVEL_Q = np.array([1.0, 0.0, 0.0, 0.0])


class HoverReference:
    """Stand-in autopilot: level attitude, hover thrust."""

    last_setpoint_time_boot_ms = None

    def __init__(self, hover_thrust: float) -> None:
        self.hover_thrust = hover_thrust

    def poll(self, state, receive: bool = True, telemetry: bool = True) -> None:
        """Nothing to receive or send (the sim_core.ReferenceSource protocol)."""

    def attitude_reference(self, state) -> AttitudeReference:
        return AttitudeReference(LEVEL_Q, self.hover_thrust, 'hold')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--frames', type=int, default=250, help='camera frames (50 Hz)')
    args = parser.parse_args()
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()
    sim = Simulation(world, pad, vehicle, HoverReference(vehicle.hover_thrust), SimConfig())
    sim.step_frame()
    # Render along the reference path (start -> window -> pad) to cover every view.
    path = np.linspace(world.initial_position_I, [0.0, 0.0, -0.3], args.frames)
    render_ms = {name: [] for name in sim.renderers}
    physics_ms = []
    wall0 = time.perf_counter()
    for k in range(args.frames):
        sim.state.xi_I = path[k].copy()
        sim.state.R_IB = rot_from_euler_zyx(0.05 * np.sin(k / 7), 0.05 * np.cos(k / 9), 0.0)
        t0 = time.perf_counter()
        renderers, sim.renderers = sim.renderers, {}
        sim.step_frame()                         # physics only
        sim.renderers = renderers
        physics_ms.append((time.perf_counter() - t0) * 1e3)
        for name, r in sim.renderers.items():
            t0 = time.perf_counter()
            r.render(sim.state.R_IB, sim.state.xi_I)
            render_ms[name].append((time.perf_counter() - t0) * 1e3)
    wall = time.perf_counter() - wall0
    sim_time = args.frames / sim.config.camera_rate_hz
    print(f'frames: {args.frames} ({sim_time:.1f} s of sim time), wall {wall:.2f} s')
    print(f'ratio to real time: {sim_time / wall:.2f} (target >= 2)')
    print(f'physics per frame ({sim.substeps} substeps): median '
          f'{np.median(physics_ms):.2f} ms, p99 {np.percentile(physics_ms, 99):.2f} ms')
    for name, ms in render_ms.items():
        print(f'render {name}: median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms')


if __name__ == '__main__':
    main()
