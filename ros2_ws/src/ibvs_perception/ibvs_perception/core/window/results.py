"""What the window detector returns per frame: status, rejection reason, detection."""
from __future__ import annotations

from dataclasses import dataclass
import enum

import numpy as np


class WindowStatus(enum.Enum):
    """Outcome of one frame."""

    DETECTED = 'detected'        # the tracked window, fully visible
    NOT_FOUND = 'not_found'      # no (fully visible) window in the image
    JUMP = 'jump'                # a window, but too far from the tracked one: reported as lost


class Reject:
    """Why a frame gave no window (``WindowResult.reason``): the furthest stage reached."""

    NO_CANDIDATE = 'no candidate'        # no dark convex quad of plausible size and shape
    OUTER_EDGES = 'outer edges'          # too few wall -> band edge points on a side
    OUTSIDE = 'outside image'            # the band is not fully border_margin_px inside
    INNER_EDGES = 'inner edges'          # aperture edges unusable and no band geometry fallback
    BAND_SHAPE = 'band shape'            # aperture / outer area ratio or proportions out of range
    JUMP = 'jump'                        # farther than max_corner_jump_px from the tracked one
    # the order of the stages, a reason later in it wins over an earlier one
    ORDER = (NO_CANDIDATE, OUTER_EDGES, OUTSIDE, INNER_EDGES, BAND_SHAPE)

    @staticmethod
    def furthest(reason: str, other: str) -> str:
        """Return the one of two reasons (of ``ORDER``) later in ``ORDER``, ``other`` on a tie."""
        return other if Reject.ORDER.index(other) >= Reject.ORDER.index(reason) else reason


@dataclass(frozen=True)
class WindowDetection:
    """One detected window in the optical frame of the camera."""

    corners_px: np.ndarray      # (4, 2) distorted pixels, TL, TR, BR, BL
    bearings_C: np.ndarray      # (4, 3) undistorted unit bearings, same order
    edge_normals_C: np.ndarray  # (4, 3) h_i = unit(p_i x p_(i+1)), edge i joins i and i+1


@dataclass(frozen=True)
class WindowResult:
    """What one frame gives: a status and, when DETECTED, the detection."""

    status: WindowStatus
    detection: WindowDetection | None = None
    reason: str = ''            # why not DETECTED (a Reject constant), '' when detected
