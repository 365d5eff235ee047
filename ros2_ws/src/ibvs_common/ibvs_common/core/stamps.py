"""Times of the flight path as integer nanoseconds on the ROS clock (docs/design.md, "Time").

Stamps, deadlines and clock readings are kept as ``int`` nanoseconds, as rclpy's
``Time.nanoseconds`` and a header stamp's ``sec * NS_PER_S + nanosec``: exact, and ordered
without the rounding of float seconds (a float64 of today's system time in seconds resolves
~0.2 us). Seconds appear only at the boundary with the maths (``t_ns / NS_PER_S``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from builtin_interfaces.msg import Time

#: nanoseconds per second
NS_PER_S = 1_000_000_000


def s_to_ns(t_s: float) -> int:
    """Seconds -> integer nanoseconds (rounded to the nearest)."""
    return int(round(float(t_s) * NS_PER_S))


def stamp_to_ns(stamp: Time) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time`` (anything with sec and nanosec)."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)
