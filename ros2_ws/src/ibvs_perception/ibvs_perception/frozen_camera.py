"""The frozen-camera guard of the perception nodes (parameter, check, log; no maths).

Every node that consumes a camera's images has ``frozen_after_frames`` (config.py) and asks
:meth:`FrozenCameraGuard.drop` before processing an image: an image of a frozen stream
(:class:`~ibvs_perception.core.freeze.FrozenImageCheck`) is neither processed nor answered, as
if the camera had delivered nothing, so that the supervisor's frame deadline and staleness
timeouts treat the camera as the dead camera it is (docs/design.md "Failure behaviour").
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from rclpy.node import Node

from ibvs_perception.core.freeze import FrozenImageCheck
from ibvs_perception.messages import stamp_to_s
from ibvs_common.throttled_log import ThrottledLog

if TYPE_CHECKING:
    from builtin_interfaces.msg import Time

THROTTLE_S = 2.0


class FrozenCameraGuard:
    """Check each image, log and count the dropped ones."""

    def __init__(self, node: Node, camera: str, log_prefix: str, frozen_after_frames: int
                 ) -> None:
        self.check = FrozenImageCheck(frozen_after_frames)   # ValueError for a bad value
        self.camera = camera
        self.prefix = log_prefix
        self.logger = node.get_logger()
        self.log = ThrottledLog(self.logger)
        self.dropped = 0              # images dropped as frozen since the start

    def drop(self, gray: np.ndarray, stamp: Time) -> bool:
        """Check the image of ``stamp`` (builtin_interfaces/Time); True: drop it (frozen)."""
        was_frozen = self.check.frozen
        if not self.check.check(gray):
            if was_frozen:
                self.logger.warning(f'{self.prefix}: {self.camera} camera live again '
                                    f'(image stamped {stamp_to_s(stamp):.3f} s)')
            return False
        self.dropped += 1
        self.log.error(
            f'{self.prefix}: {self.camera} camera frozen: {self.check.identical_frames} '
            f'consecutive images bit-identical to their predecessor (the last stamped '
            f'{stamp_to_s(stamp):.3f} s): dropped, nothing published ({self.dropped} '
            'dropped so far)', THROTTLE_S)
        return True
