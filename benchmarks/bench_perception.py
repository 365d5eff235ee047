"""Per-frame cost of the perception cores at 752x480 on rendered frames of the reference run.

Prints median and p99 (ms) of: window detection (front camera, approach) and pad detection (down
camera, descent from 1.8 m to 0.15 m), each tracked and with the whole-image search that the
tracker falls back to on a loss forced on every frame (issue 15 item 7), and translational
flow (down camera, tracking + solve, frames 20 ms apart with |v| = 0.5 m/s and |Omega| = 1
rad/s; front camera along the approach at 1 m/s with the floor as a second plane), and the
frozen-camera check on live frames (every node runs it on every image). Rendering is not
timed (benchmarks/bench_sim.py times it, with the read noise and without).
Run: AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python benchmarks/bench_perception.py
"""
import argparse
import time

import cv2
import numpy as np

from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_perception.core.flow import FlowConfig, FlowEstimator, wall_normal_from_corners
from ibvs_perception.core.freeze import FrozenImageCheck
from ibvs_perception.core.pad import PadDetector, PadDetectorConfig
from ibvs_perception.core.window import WindowDetector, WindowDetectorConfig
from ibvs_sim.core.render import SceneRenderer

N_FRAMES = 150
DT = 0.02
START = np.array([-2.0, 0.1, -1.82])
WINDOW_CENTRE = np.array([-0.5, 0.0, -1.6])


def report(name: str, seconds: list) -> None:
    ms = 1e3 * np.asarray(seconds)
    print(f'{name:10s} median {np.median(ms):6.2f} ms   p99 {np.percentile(ms, 99):6.2f} ms   '
          f'({len(ms)} frames)')


def approach_attitude(s: float) -> np.ndarray:
    """R_IB of the approach sway at the fraction s of the way to the window."""
    return frames.rot_from_euler_zyx(0.03 * np.sin(s * 9), 0.02, 0.04 * np.sin(s * 5))


def timed(fn, frames_):
    out = []
    for args in frames_:
        t0 = time.perf_counter()
        fn(*args)
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=N_FRAMES, help='frames per core timed')
    n_frames = parser.parse_args().frames
    world, vehicle, pad = load_world(), load_vehicle(), load_pad_layout()
    front, down = vehicle.cameras['front'], vehicle.cameras['down']
    r_front = SceneRenderer(world, pad, front)
    r_down = SceneRenderer(world, pad, down)

    window = WindowDetector(WindowDetectorConfig())
    imgs = [r_front.render(approach_attitude(s), START + s * (WINDOW_CENTRE - START))
            for s in np.linspace(0.0, 0.22, n_frames)]
    report('window', timed(lambda im: window.process(im, front.model), [(im,) for im in imgs]))

    def window_full_search(im):
        window.reset()                       # no track: the whole-image candidate search
        window.process(im, front.model)
    report('window full', timed(window_full_search, [(im,) for im in imgs]))

    pad_detector = PadDetector(pad, PadDetectorConfig())
    imgs = [r_down.render(frames.rot_from_euler_zyx(0.04 * np.sin(k / 5), 0.03, 0.1),
                          np.array([0.01, -0.02, -h]))
            for k, h in enumerate(np.linspace(1.8, 0.15, n_frames))]
    report('pad', timed(lambda im: pad_detector.process(im, down.model), [(im,) for im in imgs]))

    def full_search(im):
        pad_detector.reset()
        pad_detector.process(im, down.model)
    report('pad full', timed(full_search, [(im,) for im in imgs]))

    flow = FlowEstimator(FlowConfig(), down.model, down.R_BC)
    v = np.array([0.4, 0.2, 0.2])
    omega = np.array([0.6, -0.6, 0.5])
    omega /= np.linalg.norm(omega)
    R, xi, args = np.eye(3), np.array([0.0, 0.0, -1.2]), []
    for k in range(n_frames):
        args.append((r_down.render(R, xi), k * DT, R.copy(), frames.e3))
        R = R @ cv2.Rodrigues(omega * DT * np.sin(k / 10.0))[0]
        xi = xi + v * DT
    report('flow', timed(flow.process, args))

    # front flow along the window-timing approach above (0.11 m/s, the same sway): the wall
    # plane from each frame's window corners, the floor as a second plane (two-plane model)
    flow = FlowEstimator(FlowConfig(), front.model, front.R_BC)
    window.reset()
    args = []
    for k, s in enumerate(np.linspace(0.0, 0.22, n_frames)):
        R = approach_attitude(s)
        img = r_front.render(R, START + s * (WINDOW_CENTRE - START))
        detection = window.process(img, front.model).detection
        if detection is not None:
            eta, exclude = wall_normal_from_corners(detection.bearings_C, R, front.R_BC)
            args.append((img, k * DT, R, eta, exclude, frames.e3))
    report('front flow', timed(flow.process, args))

    check = FrozenImageCheck(3)
    report('frozen chk', timed(check.check, [(a[0],) for a in args]))


if __name__ == '__main__':
    main()
