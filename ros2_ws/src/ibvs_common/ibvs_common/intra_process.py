"""IntraProcessTopic: one topic's messages handed between the nodes of one container.

rclcpp's component containers deliver a message between nodes of the same process without
the middleware (intra-process communication). rclpy has no such path: every subscription in a
process pays the middleware's take, a deserialisation and an executor dispatch for every
message. For the 100 Hz ``imu/data``, which five onboard nodes subscribe to, that was most of
the idle CPU of the composed graph (docs/performance.md, "Idle CPU").

The composed container (``ibvs_bringup.composed``) gives the bridge and the nodes beside it
one IntraProcessTopic for ``imu/data``. The bridge hands every message object to this topic
(first), and publishes it through DDS too whenever a DDS subscription is matched (recorders,
tools and nodes in other processes see no difference; with none, the serialisation is
skipped, as rclcpp's intra-process publish does); the co-located nodes subscribe here instead
of through DDS, so that a sample is never delivered to them twice. Subscribers must not modify
the message.

Delivery is pulled, not pushed. :meth:`IntraProcessTopic.publish` (any thread; the bridge's
MAVLink reader thread) only appends the message to a keep-last ring of ``depth`` messages: no
executor wake-up per message. A subscriber calls :meth:`IntraProcessSubscription.take` at the
start of each of its callbacks that reads what the messages carry (an image, a product, a
timer, a service): the subscription's callback then runs, in that thread, for every message
published since the last take, in order, exactly as if each had been delivered on its own
just before. A subscriber that takes nothing for longer than the ring holds gets the newest
``depth`` messages (``lost`` counts the others), as a keep-last subscription that fell behind.
The IMU is read only where an image or a product needs the attitude at its stamp, so a node
takes the samples of a frame when the frame comes, and an idle node (no images) never runs for
them. Through DDS (:func:`subscribe` without ``local``) the executor delivers as usual and
``take`` has nothing to do: a node's code is the same in both layouts.

Ordering: a message is in the ring before the bridge publishes it through DDS, so anything
that waits for its DDS copy (the lockstep sim holds a frame's images until its own
subscription has the IMU sample of their stamp) finds it taken by the nodes' next callback.
"""
from __future__ import annotations

import collections
import itertools
import threading
from typing import Any, Callable, TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from rclpy.subscription import Subscription

#: messages kept for a subscriber that has not taken them yet: 1 s of a 100 Hz IMU, the
#: attitude buffers' history (an idle node's first frame takes the newest second)
DEFAULT_DEPTH = 100


class IntraProcessTopic:
    """Keep-last in-process topic: published from any thread, taken by its subscribers."""

    def __init__(self, name: str, depth: int = DEFAULT_DEPTH) -> None:
        if depth < 1:
            raise ValueError(f'depth must be >= 1, got {depth}')
        self.name = name
        self._lock = threading.Lock()
        self._ring: collections.deque = collections.deque(maxlen=depth)
        self._subscriptions: list[IntraProcessSubscription] = []
        self.published = 0              # messages handed over, the newest one's number

    @property
    def subscriber_count(self) -> int:
        """Number of in-process subscribers."""
        return len(self._subscriptions)

    def subscribe(self, callback: Callable[[Any], None]) -> IntraProcessSubscription:
        """Return a subscription whose ``take`` calls ``callback(msg)`` from now on."""
        with self._lock:
            sub = IntraProcessSubscription(self, callback, self.published)
            self._subscriptions.append(sub)
        return sub

    def publish(self, msg: Any) -> None:
        """Keep ``msg`` for the subscribers' next take (any thread); no-op without them."""
        if not self._subscriptions:
            return
        with self._lock:
            self.published += 1
            self._ring.append(msg)

    def publish_lazy(self, make: Callable[[], Any]) -> None:
        """Keep a message that ``make()`` builds at its first take (any thread).

        For a publisher that builds the message only for the DDS publish otherwise: while no
        subscriber takes (an idle graph), the message is never built. ``make`` must be safe
        to call from the subscribers' thread and give equal messages if called twice.
        """
        if not self._subscriptions:
            return
        with self._lock:
            self.published += 1
            self._ring.append(_Deferred(make))

    def _since(self, number: int) -> tuple[list, int, int]:
        """(messages after message ``number`` still kept, the newest number, lost count)."""
        with self._lock:
            newest = self.published
            oldest = newest - len(self._ring) + 1       # the number of self._ring[0]
            start = max(number + 1, oldest)
            msgs = list(itertools.islice(self._ring, start - oldest, None))
        return ([m.message() if type(m) is _Deferred else m for m in msgs], newest,
                start - number - 1)


class _Deferred:
    """A message of :meth:`IntraProcessTopic.publish_lazy`, built once, when first taken."""

    __slots__ = ('_make', '_message')

    def __init__(self, make: Callable[[], Any]) -> None:
        self._make = make
        self._message = None

    def message(self) -> Any:
        if self._message is None:
            self._message = self._make()
        return self._message


class IntraProcessSubscription:
    """One subscriber of an :class:`IntraProcessTopic`: its callback and how far it took."""

    def __init__(self, topic: IntraProcessTopic, callback: Callable[[Any], None],
                 taken_up_to: int) -> None:
        self.topic = topic
        self._callback = callback
        self._taken_up_to = taken_up_to  # number of the last message taken (or skipped)
        self.taken = 0                  # messages handed to the callback
        self.lost = 0                   # messages that left the ring before a take

    def take(self) -> int:
        """Run the callback for every message published since the last take; return how many.

        Call it from the thread of the subscribing node's executor. Re-entrant: a take from
        within the callback hands over only what the outer take has not.
        """
        msgs, newest, lost = self.topic._since(self._taken_up_to)
        self.lost += lost
        count = 0
        for number, msg in enumerate(msgs, start=newest - len(msgs) + 1):
            if number <= self._taken_up_to:        # a nested take handed it over already
                continue
            self._taken_up_to = number
            self.taken += 1
            count += 1
            self._callback(msg)
        return count


class DdsInput:
    """A DDS subscription seen as an input with :meth:`take` (the executor delivers)."""

    def __init__(self, subscription: Subscription) -> None:
        self.subscription = subscription

    def take(self) -> int:
        """Nothing to take: the executor calls the callback for every message."""
        return 0


def subscribe(node: Node, msg_type: type, topic: str, callback: Callable[[Any], None],
              qos: QoSProfile, local: IntraProcessTopic | None = None
              ) -> IntraProcessSubscription | DdsInput:
    """Subscribe ``callback`` to ``topic``: from ``local`` when given, else through DDS.

    The node calls the returned input's ``take()`` at the start of every callback that reads
    what the messages carry (module doc); through DDS it is a no-op.
    """
    if local is not None:
        if local.name != topic:
            raise ValueError(f'in-process topic {local.name!r} given for {topic!r}')
        return local.subscribe(callback)
    return DdsInput(node.create_subscription(msg_type, topic, callback, qos))
