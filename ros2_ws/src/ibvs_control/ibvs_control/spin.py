"""spin_guarded: rclpy.spin that survives a sample rclpy cannot convert.

Under load, a best-effort sample can reach rclpy in a state its Python message class refuses
(e.g. a string field that is not valid UTF-8, or a NaN where the class asserts): rclpy's
``take_message`` then raises ``RuntimeError: Unable to convert call argument '0' to Python
object`` from inside ``spin`` (ros2/rclpy#848), which would end the node. For flight software
one bad sample must cost one sample, not the node: the error is logged (throttled) and spinning
resumes. KeyboardInterrupt and ExternalShutdownException still end the spin as usual.
"""
from __future__ import annotations

import rclpy
from rclpy.node import Node

LOG_THROTTLE_S = 2.0


def spin_guarded(node: Node) -> int:
    """Spin ``node`` until shutdown; return the number of RuntimeErrors survived."""
    errors = 0
    while rclpy.ok(context=node.context):
        try:
            rclpy.spin(node)
            return errors
        except RuntimeError as exc:
            if not rclpy.ok(context=node.context):
                return errors
            errors += 1
            node.get_logger().error(
                f'dropped a message rclpy could not take ({exc}); {errors} so far',
                throttle_duration_sec=LOG_THROTTLE_S)
    return errors
