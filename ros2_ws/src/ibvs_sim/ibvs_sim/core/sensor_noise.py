"""Read noise of the simulated image sensors: deterministic, cheap, never the same twice in a row.

:class:`ReadNoise` adds zero-mean Gaussian noise of ``sigma`` grey levels (rounded, saturated)
to one camera's frames, from a bank of noise images drawn once per (seed, camera); frame ``k``
adds a window of one of them picked from (seed, camera, k). The same seed, camera and frame
give the same noise: lockstep runs repeat bit for bit. Why and how: docs/sim.md "Cameras".
"""
from __future__ import annotations

import zlib

import cv2
import numpy as np

BANK_SIZE = 4                 # noise images per camera, even (parity alternates per frame)
BANK_MARGIN_PX = 32           # px, each bank image is this much larger than the frame: offsets
#                               0..31 in each axis (BANK_SIZE x 32 x 32 = 4096 noise images)
_BANK_STREAM = 0              # rng key of the bank draw (the frames use 1)
_FRAME_STREAM = 1


def camera_key(name: str) -> int:
    """Stable integer key of a camera name (Python's hash() is salted per process)."""
    return zlib.crc32(name.encode('utf-8'))


class ReadNoise:
    """Zero-mean Gaussian read noise of one camera, ``sigma`` grey levels, saturating.

    ``shape`` is the frame's (height, width); ``sigma`` 0 disables it (:meth:`apply` returns
    the image unchanged). See the module documentation.
    """

    def __init__(self, sigma: float, shape: tuple[int, int], seed: int, camera: str) -> None:
        sigma = float(sigma)
        if not (np.isfinite(sigma) and 0.0 <= sigma <= 50.0):
            raise ValueError(f'read noise sigma must be in [0, 50] grey levels, got {sigma}')
        h, w = (int(x) for x in shape)
        if h <= 0 or w <= 0:
            raise ValueError(f'frame shape must be positive, got {shape}')
        self.sigma = sigma
        self.shape = (h, w)
        self.seed = int(seed)
        self.camera = camera_key(camera)
        self._pos: list[np.ndarray] = []
        self._neg: list[np.ndarray] = []
        if sigma == 0.0:
            return
        rng = np.random.default_rng((self.seed, self.camera, _BANK_STREAM))
        size = (h + BANK_MARGIN_PX, w + BANK_MARGIN_PX)
        for _ in range(BANK_SIZE):
            n = np.rint(rng.normal(0.0, sigma, size)).clip(-255, 255).astype(np.int16)
            self._pos.append(np.maximum(n, 0).astype(np.uint8))
            self._neg.append(np.maximum(-n, 0).astype(np.uint8))

    @property
    def enabled(self) -> bool:
        """Whether noise is added (sigma > 0)."""
        return self.sigma > 0.0

    def pick(self, frame_index: int) -> tuple[int, int, int]:
        """Return (bank, row offset, column offset) of frame ``frame_index``."""
        k = int(frame_index)
        r = np.random.default_rng((self.seed, self.camera, _FRAME_STREAM, k & 0xFFFFFFFF))
        half, dy, dx = (int(x) for x in r.integers(
            0, (BANK_SIZE // 2, BANK_MARGIN_PX, BANK_MARGIN_PX)))
        return 2 * half + (k & 1), dy, dx

    def apply(self, image: np.ndarray, frame_index: int) -> np.ndarray:
        """Return ``image`` (H, W uint8) with frame ``frame_index``'s noise, as a new array."""
        if not self.enabled:
            return image
        if image.shape != self.shape or image.dtype != np.uint8:
            raise ValueError(f'read noise for {self.shape} uint8 frames, got {image.shape} '
                             f'{image.dtype}')
        b, dy, dx = self.pick(frame_index)
        h, w = self.shape
        out = cv2.add(image, self._pos[b][dy:dy + h, dx:dx + w])
        return cv2.subtract(out, self._neg[b][dy:dy + h, dx:dx + w], dst=out)
