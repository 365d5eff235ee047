"""Take the messages already waiting behind the one a callback got: latest only at the reader.

rclpy's events executor queues one event per message that arrives, in arrival order, for every
subscription of the process, and runs them one after the other. When a process falls behind
(a slow or busy computer), that queue grows: each camera image event then takes the oldest
image still in its reader (a keep-last history of a few), while the events of every other
topic (the supervisor's status, the frame grid, the products) wait behind all of them. On a
third of a core the status that switched the wall flow on reached it 0.5-0.9 s late, with the
images taken ~100 ms old all the while (docs/journal/performance.md, 2026-12-04).

:func:`take_waiting` takes, from within a subscription's callback, every message that is
already in that subscription's reader, as rclpy's executors themselves take one (the
subscription's ``handle.take_message``), so that the callback sees the newest and can skip the
others; the queued events of the messages taken find nothing and cost nothing. In a lockstep
simulation nothing newer is ever waiting (the sim sends the next image after the answer), so
nothing changes there.
"""
from __future__ import annotations

from typing import Any

#: most messages taken at once (a reader holds its QoS depth; a bound against a fast writer)
MAX_WAITING = 16


def take_waiting(subscription: Any, limit: int = MAX_WAITING) -> list:
    """Take the messages waiting in ``subscription``'s reader now, oldest first (at most limit).

    Call it from the subscription's own callback (the executor's thread). Returns [] when the
    rclpy in use has no ``handle.take_message`` (nothing is taken; the executor delivers them).
    """
    take = getattr(getattr(subscription, 'handle', None), 'take_message', None)
    if take is None:
        return []
    out = []
    while len(out) < limit:
        taken = take(subscription.msg_type, subscription.raw)
        if taken is None:
            break
        out.append(taken[0])
    return out
