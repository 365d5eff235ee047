"""IntraProcessTopic: one topic's messages handed between the nodes of one container.

rclcpp's component containers deliver a message between nodes of the same process without
the middleware (intra-process communication). rclpy has no such path: every subscription in a
process pays the middleware's take, a deserialisation and an executor dispatch for every
message. For the 100 Hz ``imu/data``, which five onboard nodes subscribe to, that is most of
the idle CPU of the composed graph (docs/performance.md, "CPU").

The composed container (``ibvs_bringup.composed``) gives the bridge and the nodes beside it
one IntraProcessTopic for ``imu/data``. The bridge hands every message object to this topic,
and publishes it through DDS too whenever a DDS subscription is matched (recorders, tools and
nodes in other processes see no difference; with none, the serialisation is skipped, as
rclcpp's intra-process publish does); the co-located nodes subscribe here instead of through
DDS, so that a sample is never delivered to them twice. Subscribers must not modify the
message.

Threading: :meth:`publish` may be called from any thread (the bridge's MAVLink reader thread
does). It queues the message and hands :meth:`_deliver` to the executor that spins the
publishing node (``Executor.create_task``, thread-safe; rclpy's EventsExecutor has no guard
conditions). The executor runs it in its own thread, where it calls every subscriber's
callback in subscription order, exactly where a subscription's callback would run. The queue
keeps the newest ``depth`` messages (keep-last, like the subscriptions' QoS it replaces): an
executor that falls behind loses the oldest samples, never delays the next. Before the
publishing node is added to an executor, messages are dropped (counted), as a subscription
does not exist before its node spins.
"""
from __future__ import annotations

import collections
from typing import Any, Callable, TYPE_CHECKING

from rclpy.node import Node

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile
    from rclpy.subscription import Subscription

#: messages queued for an executor that falls behind (100 ms of a 100 Hz IMU)
DEFAULT_DEPTH = 10


class IntraProcessTopic:
    """Keep-last in-process delivery of one topic from one publishing node to callbacks."""

    def __init__(self, name: str, depth: int = DEFAULT_DEPTH) -> None:
        if depth < 1:
            raise ValueError(f'depth must be >= 1, got {depth}')
        self.name = name
        self._queue: collections.deque = collections.deque(maxlen=depth)
        self._callbacks: list[Callable[[Any], None]] = []
        self._publisher_node: Node | None = None
        self.delivered = 0              # messages handed to the subscribers
        self.dropped = 0                # messages lost: queue full, or no executor yet

    @property
    def subscriber_count(self) -> int:
        """Number of in-process subscribers."""
        return len(self._callbacks)

    def attach_publisher(self, node: Node) -> None:
        """Deliver in the thread of the executor that spins ``node`` (the publishing node)."""
        if self._publisher_node is not None:
            raise RuntimeError(f'{self.name}: a publisher is already attached')
        self._publisher_node = node

    def subscribe(self, callback: Callable[[Any], None]) -> None:
        """Call ``callback(msg)`` for every message published from now on."""
        self._callbacks.append(callback)

    def publish(self, msg: Any) -> None:
        """Queue ``msg`` for the subscribers (any thread); no-op without subscribers."""
        if not self._callbacks or self._publisher_node is None:
            return
        executor = self._publisher_node.executor
        if executor is None:
            self.dropped += 1
            return
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append(msg)
        executor.create_task(self._deliver)

    def _deliver(self) -> None:
        while True:
            try:
                msg = self._queue.popleft()
            except IndexError:
                return
            self.delivered += 1
            for callback in self._callbacks:
                callback(msg)


def subscribe(node: Node, msg_type: type, topic: str, callback: Callable[[Any], None],
              qos: QoSProfile, local: IntraProcessTopic | None = None) -> Subscription | None:
    """Subscribe ``callback`` to ``topic``: from ``local`` when given, else through DDS.

    Returns the rclpy subscription, or None for an in-process one.
    """
    if local is not None:
        if local.name != topic:
            raise ValueError(f'in-process topic {local.name!r} given for {topic!r}')
        local.subscribe(callback)
        return None
    return node.create_subscription(msg_type, topic, callback, qos)
