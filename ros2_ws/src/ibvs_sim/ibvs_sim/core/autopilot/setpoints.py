"""The companion's SET_ATTITUDE_TARGET: validation, the latest fields, the stream's timing.

``q`` is FRD in NED (w, x, y, z), ``thrust`` normalised 0..1. An ignored field (type_mask 64
thrust, 128 attitude) keeps its previous value; body rates are never used (counted when given).
An invalid setpoint (non-finite or non-unit quaternion, thrust outside [0, 1], NaN rates when
given) is counted and ignored entirely. Every well-formed one feeds the offboard stream, whose
health and loss are judged on sim time (``offboard_timeout_s``) and on the wall clock
(``offboard_timeout_wall_s``, for a lockstep stall where sim time stops).
"""
from __future__ import annotations

from collections import deque
from typing import Any, Callable

import numpy as np

from ibvs_sim.core.autopilot.config import (AutopilotConfig, AutopilotCounters, finite,
                                            RateLimitedLog, VehicleStateView)
from ibvs_sim.core.autopilot.protocol import (TYPEMASK_ATTITUDE_IGNORE, TYPEMASK_BODY_RATES_IGNORE,
                                              TYPEMASK_THROTTLE_IGNORE)

SETPOINT_LOG_LEN = 256        # new setpoints kept for latency readers (5 s at 50 Hz)


class OffboardSetpoints:
    """The latest well-formed SET_ATTITUDE_TARGET fields and the timing of their stream."""

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 warn: RateLimitedLog, wall_clock: Callable[[], float]) -> None:
        """Start with no setpoint (``wall_clock``: monotonic s)."""
        self.config = config
        self.counters = counters
        self._warn = warn
        self._wall = wall_clock
        self.q_wxyz: np.ndarray | None = None     # unit quaternion, FRD in NED (w, x, y, z)
        self.thrust: float | None = None           # normalised 0..1
        self.last_time_boot_ms: int | None = None  # time_boot_ms of the latest (sender's clock)
        # (time_boot_ms, wall s) of every valid SET_ATTITUDE_TARGET whose time_boot_ms is new,
        # for latency measurements (the sim's sim/stats, benchmarks); the reader pops them
        self.new_setpoints: deque = deque(maxlen=SETPOINT_LOG_LEN)
        self._last_t: float | None = None          # sim time of the latest well-formed setpoint
        self._last_wall: float | None = None       # wall clock of the same
        self._stream_start_t: float | None = None  # sim time the current stream started

    def receive(self, msg: Any, state: VehicleStateView) -> bool:
        """Take a SET_ATTITUDE_TARGET read at sim time ``state.t``; False when invalid (ignored).

        The caller has checked the target system and component.
        """
        mask = int(msg.type_mask)
        use_att = not mask & TYPEMASK_ATTITUDE_IGNORE
        use_thrust = not mask & TYPEMASK_THROTTLE_IGNORE
        rates_given = (mask & TYPEMASK_BODY_RATES_IGNORE) != TYPEMASK_BODY_RATES_IGNORE
        q = np.asarray(msg.q, dtype=float)
        problem = None
        if use_att and not finite(q):
            problem = f'non-finite quaternion {q}'
        elif use_att and abs(float(np.linalg.norm(q)) - 1.0) > self.config.quat_norm_tol:
            problem = f'non-unit quaternion (norm {np.linalg.norm(q):.4f})'
        elif use_thrust and not (finite(msg.thrust) and 0.0 <= msg.thrust <= 1.0):
            problem = f'thrust {msg.thrust} outside [0, 1]'
        elif rates_given and not finite(msg.body_roll_rate, msg.body_pitch_rate,
                                        msg.body_yaw_rate):
            problem = 'non-finite body rates'
        if problem is not None:
            self.counters.setpoints_invalid += 1
            self._warn.warning('setpoint', 'SET_ATTITUDE_TARGET ignored: %s', problem)
            return False
        self.counters.setpoints_received += 1
        if rates_given:
            self.counters.setpoints_rates_ignored += 1
        if use_att:
            self.q_wxyz = q / np.linalg.norm(q)
        if use_thrust:
            self.thrust = float(msg.thrust)
        now_wall = self._wall()
        if (self._last_t is None
                or state.t - self._last_t > self.config.offboard_timeout_s
                or now_wall - self._last_wall > self.config.offboard_timeout_wall_s):
            self._stream_start_t = state.t          # a new stream starts
        self._last_t = float(state.t)
        self._last_wall = now_wall
        if int(msg.time_boot_ms) != self.last_time_boot_ms:
            self.new_setpoints.append((int(msg.time_boot_ms), now_wall))
        self.last_time_boot_ms = int(msg.time_boot_ms)
        return True

    def healthy(self, t: float) -> bool:
        """Tell whether setpoints arrive within the time-outs and have for offboard_stream_min_s.

        ``t``: sim time now (s); the wall clock is read here.
        """
        if self._last_t is None or self._stream_start_t is None:
            return False
        c = self.config
        return (t - self._last_t <= c.offboard_timeout_s
                and self._wall() - self._last_wall <= c.offboard_timeout_wall_s
                and t - self._stream_start_t >= c.offboard_stream_min_s)

    def lost(self, t: float) -> tuple[bool, bool]:
        """Return (lost on sim time, lost on the wall clock) of the stream at sim time ``t`` (s).

        Lost = no setpoint yet, or the latest is older than the time-out on that clock.
        """
        c = self.config
        lost_sim = self._last_t is None or t - self._last_t > c.offboard_timeout_s
        lost_wall = (self._last_wall is None
                     or self._wall() - self._last_wall > c.offboard_timeout_wall_s)
        return lost_sim, lost_wall
