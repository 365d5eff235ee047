"""Hover thrust: the autopilot's parameter as a seed, then estimated online (ROS-free, no I/O).

Every setpoint's thrust is ``|F| / (m g) * hover_thrust``. :class:`HoverThrustSeed` takes the
autopilot's MPC_THR_HOVER / MOT_THST_HOVER (else the configured value);
:class:`HoverThrustEstimator` estimates it from the IMU against the applied thrust (a
one-state EKF, as PX4's mc_hover_thrust_estimator); :class:`HoverThrust` is the value in use.
Model, filter, gates and determinism: docs/mavlink.md, "Hover thrust".
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math

from ibvs_common.core.frames import GRAVITY
from ibvs_common.core.params import param
from ibvs_common.core.stamps import NS_PER_S

HOVER_THRUST_RANGE = (0.05, 0.95)       # a hover thrust outside this is refused
THRUST_VALID_RANGE = (0.1, 0.9)         # applied thrust used by the estimator
THRUST_RATIO_RANGE = (0.6, 1.6)         # applied thrust / estimate used: far below hover is a
#                                         touchdown (ground contact carries the rest) or a drop
MAX_ACCEL_G = 3.0                       # |f| above this many g: not used
HISTORY_S = 3.0                         # estimates kept for value_at (s of boot time)


class HoverThrustSeed:
    """The hover thrust to start from: the autopilot's parameter if it answers, else config."""

    def __init__(self, configured: float, use_autopilot: bool) -> None:
        self.configured = configured
        self.use_autopilot = use_autopilot
        self.value: float | None = None if use_autopilot else configured
        self.source = 'pending' if use_autopilot else 'config'
        self.error = ''

    def on_param(self, name: str, value: float) -> None:
        """Take the autopilot's answer if it is in range (else keep the configured one)."""
        lo, hi = HOVER_THRUST_RANGE
        if not (math.isfinite(value) and lo <= value <= hi):
            self.error = f'{name} = {value} outside [{lo}, {hi}]: using the configured ' \
                         f'{self.configured}'
            self.value, self.source = self.configured, 'config (autopilot value refused)'
            return
        self.value, self.source = float(value), f'autopilot {name}'

    def on_timeout(self) -> None:
        """No answer: fall back to the configured value."""
        if self.value is None:
            self.value, self.source = self.configured, 'config (autopilot did not answer)'


@dataclass(frozen=True)
class EstimatorConfig:
    """Settings of :class:`HoverThrustEstimator` (node parameters ``hover_estimator_*``)."""

    enabled: bool = param(True, 'estimate the hover thrust online (IMU vs applied thrust)')
    process_noise: float = param(0.0036, '1/sqrt(s), hover thrust random walk', 0.0, None)
    #                                (PX4 HTE_HT_NOISE)
    accel_noise: float = param(2.0, 'm/s^2, accelerometer noise of one sample', 0.0, None)
    initial_std: float = 0.1        # std of the seed (PX4 HTE_HT_ERR_INIT)
    gate: float = 3.0               # innovation gate, std (PX4 HTE_ACC_GATE)
    max_deviation: float = param(0.3, 'the estimate stays within seed * (1 -/+ this)',
                                 0.0, 1.0)
    max_pairing_s: float = 0.1      # thrust sample at most this older than the IMU sample
    margin_s: float = 0.1           # value_at(t) uses samples at least this older than t

    def __post_init__(self):
        for name in ('process_noise', 'accel_noise', 'initial_std', 'gate', 'max_pairing_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'hover estimator {name} must be finite and > 0, got {v}')
        if not 0.0 < self.max_deviation < 1.0:
            raise ValueError('hover estimator max_deviation must be in (0, 1)')
        if not (math.isfinite(self.margin_s) and self.margin_s >= 0.0):
            raise ValueError('hover estimator margin_s must be >= 0')


class HoverThrustEstimator:
    """Online hover-thrust estimate from specific force vs applied thrust (see the module doc)."""

    def __init__(self, config: EstimatorConfig = EstimatorConfig()) -> None:
        self.config = config
        self.seed: float | None = None
        self.theta: float | None = None       # estimate
        self.var = 0.0                        # its variance
        self.accepted = 0
        self.rejected = 0
        self._t_ns: int | None = None         # boot time of the last update
        self._history: deque = deque()        # (boot ns, theta) after each accepted sample
        self._base: float | None = None       # the latest estimate dropped from the history
        self._bounds = HOVER_THRUST_RANGE

    @property
    def std(self) -> float | None:
        """Standard deviation of the estimate (None before the seed)."""
        return None if self.theta is None else math.sqrt(self.var)

    def start(self, seed: float) -> None:
        """Start (or restart) from ``seed`` with the initial uncertainty."""
        c = self.config
        self.seed = self.theta = float(seed)
        self.var = c.initial_std ** 2
        lo, hi = HOVER_THRUST_RANGE
        self._bounds = (max(lo, seed * (1.0 - c.max_deviation)),
                        min(hi, seed * (1.0 + c.max_deviation)))
        self._history.clear()
        self._base = self.seed
        self._t_ns = None

    def update(self, boot_ns: int, f_z: float, f_norm: float, thrust: float, boost: float,
               airborne: bool) -> bool:
        """One accelerometer sample (boot time, body-z specific force f_z, |f|, m/s^2).

        ``thrust``: the applied thrust in effect; ``boost``: the autopilot's own tilt factor
        (1 or 1/cos tilt); ``airborne``: armed and not on the ground. Returns whether the sample
        was used.
        """
        c = self.config
        if self.theta is None or not c.enabled or not airborne:
            return False
        ratio = thrust * boost / self.theta
        if not (THRUST_VALID_RANGE[0] <= thrust <= THRUST_VALID_RANGE[1]) \
                or not THRUST_RATIO_RANGE[0] <= ratio <= THRUST_RATIO_RANGE[1] \
                or not math.isfinite(f_z) or f_norm > MAX_ACCEL_G * GRAVITY:
            return False
        if self._t_ns is not None and boot_ns > self._t_ns:
            dt = (boot_ns - self._t_ns) / NS_PER_S
            self.var += c.process_noise ** 2 * min(dt, 1.0)
        self._t_ns = int(boot_ns) if self._t_ns is None else max(self._t_ns, int(boot_ns))
        u = thrust * boost
        a = -f_z
        h = GRAVITY * u / self.theta
        H = -GRAVITY * u / self.theta ** 2
        y = a - h
        S = H * H * self.var + c.accel_noise ** 2
        if y * y > c.gate ** 2 * S:
            self.rejected += 1
            return False
        K = self.var * H / S
        self.theta = min(max(self.theta + K * y, self._bounds[0]), self._bounds[1])
        self.var = max((1.0 - K * H) * self.var, 1e-10)
        self.accepted += 1
        self._history.append((int(boot_ns), self.theta))
        while self._history and self._history[0][0] < boot_ns - HISTORY_S * NS_PER_S:
            self._base = self._history.popleft()[1]
        return True

    def value_at(self, boot_ns: int | None) -> float | None:
        """Estimate from the samples at least ``margin_s`` before ``boot_ns`` (None: latest).

        Before any used sample that old: the latest estimate dropped from the history (older
        than ``HISTORY_S``), else the seed.
        """
        if self.theta is None:
            return None
        if boot_ns is None or not self.config.enabled:
            return self.theta if self.config.enabled else self.seed
        limit = int(boot_ns) - int(self.config.margin_s * NS_PER_S)
        value = self._base
        for t, theta in self._history:
            if t > limit:
                break
            value = theta
        return value


class HoverThrust:
    """The hover thrust the setpoints use: the online estimate, else the seed, else configured."""

    def __init__(self, configured: float, from_autopilot: bool,
                 config: EstimatorConfig) -> None:
        self.configured = configured
        self.seed = HoverThrustSeed(configured, from_autopilot)
        self.estimator = HoverThrustEstimator(config)

    def now(self) -> float | None:
        """Return the estimate now, else the seed (None: neither known yet)."""
        v = self.estimator.value_at(None)
        return self.seed.value if v is None else v

    def current(self) -> float:
        """Return the value now, the configured one while none is known."""
        return self.now() or self.configured

    def at_boot_ns(self, boot_ns: int | None) -> float:
        """Return the estimate of the samples at least ``margin_s`` older than ``boot_ns``.

        None (unsynced, unknown): the latest; no seed yet: the configured value.
        """
        v = self.estimator.value_at(boot_ns)
        if v is None:
            v = self.seed.value
        return self.configured if v is None else v
