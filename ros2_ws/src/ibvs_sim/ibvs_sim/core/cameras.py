"""The simulated cameras: each renders the scene at a pose and adds its sensor's read noise.

:class:`CameraRig` holds one :class:`~ibvs_sim.core.render.SceneRenderer` and one
:class:`~ibvs_sim.core.sensor_noise.ReadNoise` per camera (deterministic per seed, camera and
frame, so that no two frames are bit-identical and lockstep runs repeat). ROS-free.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import time
from typing import Callable, Sequence

import numpy as np

from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_sim.core.render import SceneRenderer
from ibvs_sim.core.sensor_noise import ReadNoise
from ibvs_sim.core.world import WorldConfig


class CameraRig:
    """Render every camera's image of a frame, read noise added (none when ``render`` is off).

    With ``parallel`` the cameras but the last render on worker threads while the last
    renders on the caller's (OpenCV and most of numpy run without the GIL): the same images,
    sooner. ``wall_s`` is the wall clock (perf_counter, s) spent rendering frames, read noise
    included: the cameras' share of a run (``sim/stats``).
    """

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 cameras: Sequence[str], read_noise_std: float, noise_seed: int,
                 render: bool = True, parallel: bool = True) -> None:
        self.parallel = parallel
        self.renderers = ({name: SceneRenderer(world, pad, vehicle.cameras[name])
                           for name in cameras} if render else {})
        self._render_pool = None              # parallel: threads of all but one camera
        self.read_noise = {name: ReadNoise(
            read_noise_std, (vehicle.cameras[name].model.height,
                             vehicle.cameras[name].model.width),
            noise_seed, name) for name in self.renderers}
        self.wall_s = 0.0

    def frame(self, R_IB: np.ndarray, xi_I: np.ndarray, frame_index: int) -> dict:
        """Return the images of frame ``frame_index`` at a pose, counting the wall time."""
        t0 = time.perf_counter()
        images = self.render(R_IB, xi_I, frame_index)
        self.wall_s += time.perf_counter() - t0
        return images

    def render(self, R_IB: np.ndarray, xi_I: np.ndarray, frame_index: int) -> dict:
        """Return every camera's image (read noise of frame ``frame_index`` added) at a pose.

        In parallel the images are the same as one after the other (each camera has its own
        renderer and noise bank, and nothing they share is written).
        """
        def one(name: str) -> np.ndarray:
            return self.read_noise[name].apply(self.renderers[name].render(R_IB, xi_I),
                                               frame_index)
        return self._each(one, list(self.renderers))

    def render_clean(self, names: Sequence[str], R_IB: np.ndarray, xi_I: np.ndarray) -> dict:
        """Return the noise-free images of the cameras ``names`` (those that render) at a pose.

        One exposure sample of a frame (:mod:`~ibvs_sim.core.capture`); counts the wall time.
        """
        t0 = time.perf_counter()
        images = self._each(lambda name: self.renderers[name].render(R_IB, xi_I),
                            [n for n in names if n in self.renderers])
        self.wall_s += time.perf_counter() - t0
        return images

    def add_noise(self, name: str, image: np.ndarray, frame_index: int) -> np.ndarray:
        """Return ``image`` of camera ``name`` with the read noise of its frame ``frame_index``."""
        t0 = time.perf_counter()
        out = self.read_noise[name].apply(image, frame_index)
        self.wall_s += time.perf_counter() - t0
        return out

    def _each(self, one: Callable[[str], np.ndarray], names: list) -> dict:
        """Return ``{name: one(name)}``: in parallel, all but the last on the worker threads."""
        if not self.parallel or len(names) < 2:
            return {name: one(name) for name in names}
        if self._render_pool is None:
            self._render_pool = ThreadPoolExecutor(max_workers=len(self.renderers) - 1,
                                                   thread_name_prefix='render')
        futures = {name: self._render_pool.submit(one, name) for name in names[:-1]}
        last = one(names[-1])
        return {name: futures[name].result() if name in futures else last for name in names}

    def close(self) -> None:
        """Stop the render threads (idempotent; a later frame starts them again)."""
        pool, self._render_pool = self._render_pool, None
        if pool is not None:
            pool.shutdown(wait=True)
