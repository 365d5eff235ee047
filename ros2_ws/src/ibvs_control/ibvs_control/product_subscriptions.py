"""The perception products of a camera frame, subscribed once for the supervisor and controller.

:class:`FrameProductSubscriptions` subscribes ``window/corners``, ``pad/landmarks`` +
``pad/groups`` and both ``<camera>_camera/translational_flow`` (``PRODUCT_QOS``: best effort,
keep last 2), validates each message (:func:`~ibvs_control.core.frame_inputs.check_bearings`,
:func:`~ibvs_control.core.frame_inputs.check_flow`), pairs the two pad halves by stamp
(:class:`~ibvs_control.core.frame_inputs.PadPairing`) and hands every product to the node's
``add(kind, stamp_ns, value, err)``:

- WINDOW: the 4 corner bearings (optical frame, rows) or None (not detected / refused);
- PAD: (landmark bearings or None, group names), or None when the landmarks were refused;
- FLOW_FRONT / FLOW_DOWN: the flow phi = v/d in {I} (1/s) or None (no flow at that stamp /
  refused).

``err`` is '' or why the message was refused (the product then counts as "not detected").
What a product means for a frame is the node's business; this piece only converts messages.

:meth:`FrameProductSubscriptions.take_waiting` hands over the products already waiting in the
readers, for a frame deadline to judge what has arrived: in a busy process (composed, a slow
computer) a product's event can wait behind image callbacks until after its frame's deadline,
and the frame was skipped with its product in the reader (a third of a core: the first floor
flows of CROSSING, 2026-12-04).
"""
from __future__ import annotations

from typing import Callable

from geometry_msgs.msg import PolygonStamped, Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from ibvs_common.core.modes import InputKind
from ibvs_common.node_common import (
    pad_group_names, pad_group_weights, polygon_points, PRODUCT_QOS, stamp_to_ns, vector3)
from ibvs_common.waiting_messages import take_waiting
from ibvs_control.core.frame_inputs import check_bearings, check_flow, PadPairing

LANDMARKS_PER_GROUP = 4
AddProduct = Callable[[InputKind, int, object, str], None]


class FrameProductSubscriptions:
    """Subscriptions of the frame products, each handed to ``add`` (see the module doc)."""

    def __init__(self, node: Node, add: AddProduct) -> None:
        self._add = add
        self.pad_pairing = PadPairing(LANDMARKS_PER_GROUP)
        self.taken_waiting = 0              # products handed over by take_waiting
        topics = [(PolygonStamped, 'window/corners', self._on_window),
                  (PolygonStamped, 'pad/landmarks', self._on_landmarks),
                  (JointState, 'pad/groups', self._on_groups)]
        for kind, camera in ((InputKind.FLOW_FRONT, 'front'), (InputKind.FLOW_DOWN, 'down')):
            topics.append((Vector3Stamped, f'{camera}_camera/translational_flow',
                           lambda msg, kind=kind: self._on_flow(kind, msg)))
        self._subscriptions = [(node.create_subscription(msg_type, topic, handler, PRODUCT_QOS),
                                handler) for msg_type, topic, handler in topics]

    def take_waiting(self) -> None:
        """Hand over every product already waiting in the readers (call on the node's thread)."""
        for subscription, handler in self._subscriptions:
            for msg in take_waiting(subscription):
                self.taken_waiting += 1
                handler(msg)

    def _on_window(self, msg: PolygonStamped) -> None:
        bearings, err = check_bearings(polygon_points(msg), expected=4)
        self._add(InputKind.WINDOW, stamp_to_ns(msg.header.stamp), bearings, err)

    def _on_landmarks(self, msg: PolygonStamped) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        bearings, err = check_bearings(polygon_points(msg))
        if err:                                  # "no pad" for this stamp
            self.pad_pairing.drop(stamp_ns)
            self._add(InputKind.PAD, stamp_ns, None, err)
        else:                                    # the PAD input waits for its groups
            self._add_pad(self.pad_pairing.add_landmarks(stamp_ns, bearings))

    def _on_groups(self, msg: JointState) -> None:
        self._add_pad(self.pad_pairing.add_groups(stamp_to_ns(msg.header.stamp),
                                                  pad_group_names(msg), pad_group_weights(msg)))

    def _add_pad(self, pair: tuple | None) -> None:
        if pair is not None:                     # (stamp_ns, bearings, groups, weights)
            self._add(InputKind.PAD, pair[0], pair[1:], '')

    def _on_flow(self, kind: InputKind, msg: Vector3Stamped) -> None:
        phi_I, err = check_flow(vector3(msg.vector), msg.header.frame_id)
        self._add(kind, stamp_to_ns(msg.header.stamp), phi_I, err)
