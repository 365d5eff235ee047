"""Frozen camera: the same image delivered again and again under new stamps.

A camera driver that hangs can keep publishing its last buffer with fresh stamps. By its
stamps such a stream looks alive, and a detector fed with it keeps reporting the window or
the pad where they were when the driver hung, so no staleness timeout would ever fire.
"""
from __future__ import annotations

import numpy as np

SAMPLE_STRIDE = 97            # pixels: a sparse comparison first (prime: no row alignment)


class FrozenImageCheck:
    """Detect a frozen image stream: ``frozen_after_frames`` consecutive bit-identical images.

    Feed every image of one camera to :meth:`check`. It returns True (frozen) once
    ``frozen_after_frames`` consecutive images were each bit-identical to their predecessor
    (with N = 3: the 4th image in a row with the same bytes), and as long as they keep
    repeating; the first image that differs in any byte, or in shape or type, resets it.

    Why it is sound: every live image sensor adds read noise (dark current, readout and
    photon shot noise, a few grey levels) to every pixel of every frame, so two consecutive
    frames of a working camera are never bit-identical, not even of a still scene; a repeated
    buffer is a driver (or a pipeline) delivering the same data again. Only an image clipped
    everywhere (all white, or all black without a black-level offset) could repeat, and such
    an image carries nothing to detect anyway. The simulator adds such noise for that reason
    (``ibvs_sim.core.sensor_noise``). Cost: the previous image is kept by reference (no
    copy; images are not modified in place downstream) and compared on a sparse sample of
    pixels first: a live frame differs there at once (microseconds), a repeated one is
    confirmed by a full comparison.
    """

    def __init__(self, frozen_after_frames: int) -> None:
        if isinstance(frozen_after_frames, bool) or \
                not isinstance(frozen_after_frames, (int, np.integer)) or frozen_after_frames < 1:
            raise ValueError(f'frozen_after_frames must be an integer >= 1, '
                             f'got {frozen_after_frames!r}')
        self.frozen_after_frames = int(frozen_after_frames)
        self.identical_frames = 0     # consecutive images bit-identical to their predecessor
        self._previous: np.ndarray | None = None

    @property
    def frozen(self) -> bool:
        """Whether the last image checked belongs to a frozen stream."""
        return self.identical_frames >= self.frozen_after_frames

    def check(self, image: np.ndarray) -> bool:
        """Note the next image of the stream; return whether the stream is frozen now."""
        image = np.asarray(image)
        previous, self._previous = self._previous, image
        if previous is not None and _identical(previous, image):
            self.identical_frames += 1
        else:
            self.identical_frames = 0
        return self.frozen

    def reset(self) -> None:
        """Forget the stream (e.g. after a camera change)."""
        self.identical_frames = 0
        self._previous = None


def _identical(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two arrays have the same shape, type and bytes (sparse sample first)."""
    if a is b:
        return True
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    fa, fb = a.reshape(-1), b.reshape(-1)
    if not np.array_equal(fa[::SAMPLE_STRIDE], fb[::SAMPLE_STRIDE]):
        return False
    return bool(np.array_equal(fa, fb))
