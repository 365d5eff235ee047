"""Throttled logging that costs nothing while it is throttled.

rclpy's ``logger.error(text, throttle_duration_sec=T)`` finds its caller with
``inspect.getframeinfo`` (which reads the source file) before its throttle filter runs:
0.16 ms per call, throttled or not (``benchmarks/bench_log_throttle.py``: median 155 us,
against 0.7 us here). On the flight path a per-frame message (a frame released at its
deadline, no window for the front flow) then costs a node ~0.8 % of a core at 50 Hz per call
site, when it is already short of time. This wrapper keeps rclpy's rule, one message per call
site per period on the steady clock, but decides it first from the caller's code object and
line (``sys._getframe``) and calls the rclpy logger only for the messages that go out.
"""
from __future__ import annotations

import re
import sys
import time
from typing import Callable, Hashable

_NUMBER = re.compile(r'[-+]?\d+(\.\d+)?([eE][-+]?\d+)?')


def message_kind(text: str) -> str:
    """Return ``text`` with its numbers replaced by ``#``: a key for messages of one kind.

    'imu/data: 3 sample(s) dropped (40 in all)' and '... 5 ... (45 in all)' are one kind and
    share a throttle; a message of another text is never held back by them.
    """
    return _NUMBER.sub('#', text)


class ThrottledLog:
    """A node's logger with a cheap per-call-site throttle on the steady (wall) clock.

    ``log.error(text, period_s)``: logs ``text`` unless this call site logged less than
    ``period_s`` seconds ago (monotonic clock, so it also throttles while a lockstep sim's
    ROS clock stands still). Returns True when the message went out. ``key``: throttle by it
    instead of the call site, for one call site that relays messages of many kinds (the
    MAVLink bridge's events: :func:`message_kind`).
    """

    def __init__(self, logger, clock: Callable[[], float] = time.monotonic) -> None:
        self._logger = logger
        self._clock = clock
        self._last_s: dict[tuple, float] = {}

    def _due(self, period_s: float, key: Hashable | None) -> bool:
        if key is None:
            caller = sys._getframe(2)       # 0: _due, 1: info/warning/error, 2: the call site
            key = (caller.f_code, caller.f_lineno)
        now = self._clock()
        last = self._last_s.get(key)
        if last is not None and now - last < period_s:
            return False
        self._last_s[key] = now
        return True

    def info(self, text: str, period_s: float, key: Hashable | None = None) -> bool:
        """Log ``text`` at INFO unless this call site (or ``key``) logged within ``period_s``."""
        return self._due(period_s, key) and self._logger.info(text) is not False

    def warning(self, text: str, period_s: float, key: Hashable | None = None) -> bool:
        """Log ``text`` at WARN unless this call site (or ``key``) logged within ``period_s``."""
        return self._due(period_s, key) and self._logger.warning(text) is not False

    def error(self, text: str, period_s: float, key: Hashable | None = None) -> bool:
        """Log ``text`` at ERROR unless this call site (or ``key``) logged within ``period_s``."""
        return self._due(period_s, key) and self._logger.error(text) is not False
