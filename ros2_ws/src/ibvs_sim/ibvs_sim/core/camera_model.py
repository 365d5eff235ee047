"""A camera's timing like a real one's: exposure, stamp, delivery latency and jitter, drops.

:class:`CameraTiming` is one camera's timing (sim time). :class:`FrameClock` plans the frames
of the cameras that share one (the same rate, exposure and delivery; their time offsets may
differ): frame k's stamp instant on the physics grid, its exposure's render instants, each
camera's header stamp (``instant - time_offset_s``, kalibr's timeshift_cam_imu), which camera
dropped it (seeded), and its delivery (``instant + latency + jitter``, seeded, on the
physics grid, never before the exposure ended or a previous frame of the clock). ROS-free;
docs/sim.md "Camera model".
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import enum
import math
from typing import Mapping

import numpy as np

from ibvs_common.core.stamps import NS_PER_S
from ibvs_sim.core.sensor_noise import camera_key

MAX_EXPOSURE_SAMPLES = 64
_JITTER_STREAM = 2            # rng keys (sensor_noise uses 0 and 1 with the camera's key)
_DROP_STREAM = 3


class StampAt(str, enum.Enum):
    """Which instant of the exposure a frame's stamp refers to."""

    START = 'start'
    MID = 'mid'
    END = 'end'

    @property
    def fraction(self) -> float:
        """Return where the instant lies in the exposure: 0 start, 0.5 middle, 1 end."""
        return {StampAt.START: 0.0, StampAt.MID: 0.5, StampAt.END: 1.0}[self]


class Jitter(str, enum.Enum):
    """The distribution of the delivery jitter."""

    UNIFORM = 'uniform'       # uniform in [-jitter_s, +jitter_s]
    NORMAL = 'normal'         # normal, standard deviation jitter_s


@dataclass(frozen=True)
class CameraTiming:
    """One camera's timing, in seconds of sim time (defaults: the ideal camera at 50 Hz).

    ``time_offset_s`` is the camera's true camera-IMU offset: an image exposed at sim time
    tau is stamped ``tau - time_offset_s``.
    """

    rate_hz: float = 50.0
    latency_s: float = 0.0            # delivery after the stamp's instant
    jitter_s: float = 0.0             # uniform half-width or normal standard deviation
    jitter: Jitter = Jitter.UNIFORM
    drop_probability: float = 0.0     # each frame of this camera, independently
    exposure_s: float = 0.0           # 0: an instant (one render)
    exposure_samples: int = 1         # renders averaged over the exposure (motion blur)
    stamp_at: StampAt = StampAt.MID
    time_offset_s: float = 0.0

    def __post_init__(self) -> None:
        """Raise ValueError for a timing no camera has."""
        values = (self.rate_hz, self.latency_s, self.jitter_s, self.drop_probability,
                  self.exposure_s, self.time_offset_s)
        if not all(math.isfinite(float(v)) for v in values):
            raise ValueError(f'camera timing must be finite, got {self}')
        if not 0.0 < self.rate_hz <= 1000.0:
            raise ValueError(f'camera rate must be in (0, 1000] Hz, got {self.rate_hz}')
        if self.latency_s < 0.0 or self.jitter_s < 0.0:
            raise ValueError(f'camera latency and jitter must be >= 0 s, got '
                             f'{self.latency_s}, {self.jitter_s}')
        if not 0.0 <= self.drop_probability < 1.0:
            raise ValueError(f'drop probability must be in [0, 1), got {self.drop_probability}')
        if not 0.0 <= self.exposure_s <= 1.0 / self.rate_hz:
            raise ValueError(f'exposure must be in [0, one frame period {1.0 / self.rate_hz} '
                             f's], got {self.exposure_s}')
        if not 1 <= int(self.exposure_samples) <= MAX_EXPOSURE_SAMPLES:
            raise ValueError(f'exposure samples must be in 1 ... {MAX_EXPOSURE_SAMPLES}, got '
                             f'{self.exposure_samples}')
        if abs(self.time_offset_s) >= 1.0:
            raise ValueError(f'|time_offset_s| must be < 1 s, got {self.time_offset_s}')
        Jitter(self.jitter)
        StampAt(self.stamp_at)

    def shared(self) -> CameraTiming:
        """Return the timing without the camera's own time offset.

        Cameras equal in it share one :class:`FrameClock`: exposed and delivered together.
        """
        return replace(self, time_offset_s=0.0)


@dataclass(frozen=True)
class PlannedFrame:
    """Frame ``index`` of a :class:`FrameClock` (times: sim time, integer ns since boot)."""

    index: int
    instant_ns: int                   # the exposure instant the stamp refers to (grid)
    samples_ns: tuple                 # render instants across the exposure, >= 0
    stamps_ns: dict                   # camera -> header stamp (instant - its time offset)
    cameras: tuple                    # the cameras that deliver it (not dropped)
    dropped: tuple                    # the cameras that lost it
    delivery_ns: int                  # when its images are published (grid)


def ceil_to(t_ns: int, step_ns: int) -> int:
    """Return the first multiple of ``step_ns`` at or after ``t_ns``."""
    return -(-int(t_ns) // step_ns) * step_ns


def round_to(t_ns: int | float, step_ns: int) -> int:
    """Return the multiple of ``step_ns`` nearest ``t_ns`` (halves up)."""
    return int(math.floor(t_ns / step_ns + 0.5)) * step_ns


class FrameClock:
    """The frames of cameras that share one timing (see the module doc); ``seed``: jitter, drops.

    Frame k's instant is ``k / rate_hz`` rounded to the physics grid (``step_ns``): a 50 Hz
    camera on a 2 ms grid stamps exactly every 20 ms, a 30 Hz one 34, 32, 34 ms apart (the
    +-1 ms a real camera's stamps jitter by). Frame 0 is never dropped (it shows the initial
    condition every node starts from). :meth:`next` gives the frames in order.
    """

    def __init__(self, timings: Mapping[str, CameraTiming], step_ns: int, seed: int) -> None:
        if not timings:
            raise ValueError('a frame clock needs a camera')
        shared = {t.shared() for t in timings.values()}
        if len(shared) != 1:
            raise ValueError(f'cameras of one frame clock must share their timing, got '
                             f'{dict(timings)}')
        self.timing = shared.pop()
        self.cameras = tuple(timings)
        self.offsets_ns = {c: int(round(t.time_offset_s * NS_PER_S)) for c, t in timings.items()}
        self.step_ns = int(step_ns)
        self.seed = int(seed)
        self.period_ns = int(round(NS_PER_S / self.timing.rate_hz))
        self._steps_per_frame = NS_PER_S / (self.timing.rate_hz * self.step_ns)
        self._exposure_ns = int(round(self.timing.exposure_s * NS_PER_S))
        self._next = 0
        self._last_delivery_ns: int | None = None

    def instant_ns(self, k: int) -> int:
        """Return frame k's stamp instant: k periods, rounded to the physics grid."""
        return int(math.floor(k * self._steps_per_frame + 0.5)) * self.step_ns

    def exposure_ns(self, k: int) -> tuple[int, int]:
        """Return frame k's exposure [start, end] (ns; may start before 0 for frame 0)."""
        start = self.instant_ns(k) - int(round(self.timing.stamp_at.fraction
                                               * self._exposure_ns))
        return start, start + self._exposure_ns

    def samples_ns(self, k: int) -> tuple:
        """Return frame k's render instants: the midpoints of equal parts of its exposure.

        One render at the stamp's instant for an instant exposure; never before t = 0 (the
        vehicle stands still at its initial condition before).
        """
        if self._exposure_ns == 0:
            return (self.instant_ns(k),)
        start, _ = self.exposure_ns(k)
        n = int(self.timing.exposure_samples)
        return tuple(max(0, start + int(round((i + 0.5) * self._exposure_ns / n)))
                     for i in range(n))

    def jitter_ns(self, k: int) -> int:
        """Return frame k's delivery jitter (ns; seeded by the clock's first camera and k)."""
        t = self.timing
        if t.jitter_s == 0.0:
            return 0
        rng = np.random.default_rng((self.seed, camera_key(self.cameras[0]), _JITTER_STREAM,
                                     k & 0xFFFFFFFF))
        draw = rng.uniform(-t.jitter_s, t.jitter_s) if t.jitter is Jitter.UNIFORM \
            else rng.normal(0.0, t.jitter_s)
        return int(round(draw * NS_PER_S))

    def dropped(self, k: int) -> tuple:
        """Return the cameras that lose frame k (seeded by camera and k; never frame 0)."""
        p = self.timing.drop_probability
        if p == 0.0 or k == 0:
            return ()
        return tuple(c for c in self.cameras if np.random.default_rng(
            (self.seed, camera_key(c), _DROP_STREAM, k & 0xFFFFFFFF)).random() < p)

    def delivery_ns(self, k: int, previous_ns: int | None) -> int:
        """Return frame k's delivery: instant + latency + jitter, on the physics grid.

        Not before its exposure ended, nor before its latest stamp (an image is not published
        before the time it says), nor before one step after the previous frame's delivery
        (``previous_ns``: a driver delivers in order).
        """
        instant = self.instant_ns(k)
        raw = instant + int(round(self.timing.latency_s * NS_PER_S)) + self.jitter_ns(k)
        latest_stamp = max(instant - off for off in self.offsets_ns.values())
        due = max(round_to(raw, self.step_ns), ceil_to(self.exposure_ns(k)[1], self.step_ns),
                  ceil_to(latest_stamp, self.step_ns))
        if previous_ns is not None:
            due = max(due, previous_ns + self.step_ns)
        return due

    def plan(self, k: int, previous_ns: int | None) -> PlannedFrame:
        """Return frame k, delivered after a previous one at ``previous_ns`` (None: first)."""
        instant = self.instant_ns(k)
        dropped = self.dropped(k)
        return PlannedFrame(k, instant, self.samples_ns(k),
                            {c: instant - off for c, off in self.offsets_ns.items()},
                            tuple(c for c in self.cameras if c not in dropped), dropped,
                            self.delivery_ns(k, previous_ns))

    def next(self) -> PlannedFrame:
        """Return the next frame of the clock (its first call: frame 0)."""
        frame = self.plan(self._next, self._last_delivery_ns)
        self._next += 1
        if frame.cameras:                   # a frame every camera lost is never delivered
            self._last_delivery_ns = frame.delivery_ns
        return frame


def frame_clocks(timings: Mapping[str, CameraTiming], step_ns: int, seed: int
                 ) -> list[FrameClock]:
    """Return one :class:`FrameClock` per group of cameras that share a timing, in order."""
    groups: dict[CameraTiming, dict] = {}
    for name, timing in timings.items():
        groups.setdefault(timing.shared(), {})[name] = timing
    return [FrameClock(group, step_ns, seed) for group in groups.values()]
