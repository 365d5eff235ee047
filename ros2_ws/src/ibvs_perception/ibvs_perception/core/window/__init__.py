"""Window detection in the forward image: the four aperture corners as unit bearings.

Algorithm (paper section Experiments: "ArUco border detection", made sub-pixel):

1. Candidates. Adaptive threshold (dark = foreground) of a down-scaled image, the offset
   below the local mean a fraction of the local contrast (so it follows the exposure), at
   most half the mean's depth above the local minimum (beside a black brick and a dim room
   the contrast's fraction left the band itself above the threshold: a gap in the ring),
   then ``findContours`` with a two-level hierarchy, every boundary pixel kept
   (``CHAIN_APPROX_NONE``: with ``CHAIN_APPROX_SIMPLE`` an axis-aligned side, as in a level
   hover, shrinks to its two end points and no line can be fitted to it). The window is a
   dark *ring* (the frame band on the wall face): an outer contour (band/wall border) with
   one large hole (the aperture).
   Both are approximated by convex quadrilaterals (``approxPolyDP``); area, aspect-ratio and
   hole/outer area-ratio checks reject markers, door-like shapes and texture. Dark texture
   touching the band (the dark bricks of a light-mortar wall) joins its component, whose outer
   contour is then no quadrilateral; the hole stays one, so a large quadrilateral hole gives a
   candidate too: the outer quad that the band's proportions predict around it (a
   homography, the inverse of the aperture prediction below), tried when the component's
   outer contour gives no window.
2. Sub-pixel refinement. A straight 3-D edge is straight only in *undistorted* coordinates,
   so each aperture side is parametrised in undistorted pixels (the ideal pinhole image
   ``K [x/z, y/z, 1]``), sampled, projected into the distorted image, and searched for the
   dark-to-light step along the local image normal (centroid of the intensity gradient).
   Each profile is the mean of 3 parallel ones (noise), and a motion-blurred step's centroid
   spans its whole ramp. Valid steps exceed a fraction of the band's contrast to the wall.
   The step must lead into the band: its dark side reaches the band's level (the darkest of
   the profile) within ``_BAND_REACH_PX``. A texture step beside the band (a brick row, a
   mortar joint parallel to the side, as in a level view of a brick wall) is steeper than the
   band's blurred edge but does not, and is not taken for it.
   The edge points are undistorted again, a line is fitted to each side (Huber, then
   residual gating) and adjacent lines are intersected. Two passes.
   The aperture (inner) edges: the band and the aperture are one known rectangle pair
   (``window_*_m``, ``frame_band_m``), so the outer quad predicts the aperture by a
   homography. Inwards of each outer side the band's level is read and the inner edge is the
   first departure from it, lighter *or darker* (the room beyond may be dim). A side with too
   few points or off its predicted line by more than ``max_band_deviation`` band widths (a post
   beyond the window beside the band) is taken from the prediction, if the outer quad is a true
   perspective view of the band's rectangle (``max_shape_error``).
3. Tracking. The same window is followed frame to frame: a corner displacement above
   ``max_corner_jump_px`` is reported as a loss (``JUMP``), not followed. A tracked frame
   starts from the last outline moved on by its last motion (constant image velocity of the
   outer corners over one frame, when the two frames before were both detected and the gyro
   prediction did not move the track). When that prediction was off by no more than
   ``refine_half_width_px / 2`` in the frame before (:data:`SINGLE_PASS_MARGIN`), the outer
   edges take one search of the refine range from it instead of the two passes (the first
   one's wide range is for motion nobody predicted), and the result is kept if it lies within
   that half range of the start; otherwise both passes run from the start as before. The
   aperture likewise: when it lay within that half range of where the band's proportions put
   it in the frame before (and its search had measured all four sides), its edges take one
   refine pass from this frame's prediction, with the polarity and band level of its last
   search, instead of the search; any failed check and the search runs
   (``single_pass_tracking``). The starts and the choices depend on the detections alone, not
   on the IMU's timing; the aperture's start is this frame's prediction, not its own last
   position, so that its sub-pixel noise does not carry the track's history. After
   ``reacquire_after_frames`` frames without a consistent window the tracker searches again;
   until then a frame that fails (noise, blur) keeps the tracked outline for the next one.
   Every frame without a window says why (``WindowResult.reason``, a :class:`Reject`).

Outputs are in the camera optical frame (x right, y down, z along the optical axis); corners
are ordered top-left, top-right, bottom-right, bottom-left as seen in the image (clockwise in
the image); edge i joins corner i and i+1 and h_i = unit(p_i x p_(i+1)) (paper, Fig. window).
"""
from .candidates import _dark_mask, _without_small_components  # noqa: F401 (unit tests)
from .config import PARAMETER_SPECS, SINGLE_PASS_MARGIN, WindowDetectorConfig
from .detector import WindowDetector
from .edges import _robust_lines  # noqa: F401 (unit tests)
from .geometry import _distort_px, _edge_normals  # noqa: F401 (unit tests)
from .geometry import N_CORNERS, order_corners_clockwise
from .results import Reject, WindowDetection, WindowResult, WindowStatus

__all__ = ['N_CORNERS', 'PARAMETER_SPECS', 'Reject', 'SINGLE_PASS_MARGIN', 'WindowDetection',
           'WindowDetector', 'WindowDetectorConfig', 'WindowResult', 'WindowStatus',
           'order_corners_clockwise']
