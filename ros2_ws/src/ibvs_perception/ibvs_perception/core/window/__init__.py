"""Window detection in the forward image: the four aperture corners as unit bearings.

The window is a dark frame band on the wall around the aperture. :class:`WindowDetector`
finds it in the whole image (:mod:`.candidates`), measures its outer and aperture edges to
sub-pixel accuracy (:mod:`.edges`) and follows it from frame to frame (:mod:`.tracker`).

Outputs are in the camera optical frame (x right, y down, z along the optical axis); corners
are ordered top-left, top-right, bottom-right, bottom-left as seen in the image (clockwise in
the image); edge i joins corner i and i+1 and h_i = unit(p_i x p_(i+1)) (paper, Fig. window).
"""
from .candidates import _dark_mask, _without_small_components  # noqa: F401 (unit tests)
from .config import SINGLE_PASS_MARGIN, WindowDetectorConfig
from .detector import WindowDetector
from .edges import _robust_lines  # noqa: F401 (unit tests)
from .geometry import _distort_px, _edge_normals  # noqa: F401 (unit tests)
from .geometry import N_CORNERS, order_corners_clockwise
from .results import Reject, WindowDetection, WindowResult, WindowStatus

__all__ = ['N_CORNERS', 'Reject', 'SINGLE_PASS_MARGIN', 'WindowDetection',
           'WindowDetector', 'WindowDetectorConfig', 'WindowResult', 'WindowStatus',
           'order_corners_clockwise']
