"""Tuning of the window detector: its dataclass and the specs of its ROS parameters."""
from __future__ import annotations

from dataclasses import dataclass

#: a tracked frame's outer edges take one search of the refine range when the outline
#: prediction was off by at most refine_half_width_px / this in the frame before, and the
#: result lies within that of the start (the tracker's single pass, `WindowTracker.refine`)
SINGLE_PASS_MARGIN = 2.0


@dataclass(frozen=True)
class WindowDetectorConfig:
    """Tuning of :class:`WindowDetector` (pixels are full-resolution pixels unless noted)."""

    detection_scale: float = 0.5            # image scale of the contour search, (0, 1]
    threshold_block_px: int = 31            # adaptive threshold window at detection scale, odd
    threshold_offset: float = 4.0           # grey levels, floor of the offset below
    #                                         the local mean counted as dark
    threshold_contrast_fraction: float = 0.15  # offset / local contrast (max - min in a block)
    min_area_fraction: float = 0.01         # outer quad area / image area, lower bound
    max_area_fraction: float = 0.98         # outer quad area / image area, upper bound
    min_aspect_ratio: float = 0.35          # aperture width / height (image), lower bound
    max_aspect_ratio: float = 3.0           # aperture width / height (image), upper bound
    min_hole_area_ratio: float = 0.5        # aperture area / outer area (thin dark band)
    max_hole_area_ratio: float = 0.93
    min_holes_fraction: float = 0.25        # light area inside the ring / outer area (search)
    max_band_fraction: float = 0.25         # band width / shortest outer side, upper bound
    approx_tolerance: float = 0.04          # approxPolyDP tolerance / contour perimeter
    border_margin_px: float = 4.0           # the band must stay this far from the image border
    samples_per_side: int = 40              # edge points searched per aperture side
    search_half_width_px: float = 8.0       # first-pass search range along the edge normal
    refine_half_width_px: float = 3.0       # second-pass search range
    single_pass_tracking: bool = True       # a well predicted track: one refine pass per edge
    min_edge_contrast: float = 6.0          # grey levels, floor of a valid edge step
    edge_contrast_fraction: float = 0.2     # valid edge step / the band's contrast to the wall
    min_edge_inlier_fraction: float = 0.5   # valid points per side, fraction of samples
    line_inlier_px: float = 1.0             # residual gate of the line fit, undistorted px
    max_corner_jump_px: float = 30.0        # largest corner displacement between frames
    reacquire_after_frames: int = 10        # frames without the tracked window before a search
    window_width_m: float = 1.2             # aperture width (world.yaml window.width), m
    window_height_m: float = 1.0            # aperture height, m
    frame_band_m: float = 0.08              # band width around the aperture, m
    max_band_deviation: float = 0.5         # measured inner side off its predicted line / band
    max_shape_error: float = 0.02           # band quad vs a view of its rectangle (fallback;
    #                                         sim views <= 0.003, a floor patch 0.097)

    def __post_init__(self) -> None:
        """Raise ValueError naming the parameter for what a range cannot check."""
        block = self.threshold_block_px
        if block % 2 != 1 or block < 3:    # cv2.adaptiveThreshold: else cv2.error per image
            raise ValueError(f'parameter threshold_block_px must be odd and >= 3, got {block}')
        for low, high in (('min_area_fraction', 'max_area_fraction'),
                          ('min_aspect_ratio', 'max_aspect_ratio'),
                          ('min_hole_area_ratio', 'max_hole_area_ratio')):
            if not getattr(self, low) <= getattr(self, high):
                raise ValueError(f'parameter {low} ({getattr(self, low)}) must be <= {high} '
                                 f'({getattr(self, high)})')


#: spec of each WindowDetectorConfig field as a ROS parameter (description with unit, inclusive
#: range; ibvs_common.param_descriptors); pixels are full-resolution pixels unless noted
PARAMETER_SPECS = {
    'detection_scale': ('image scale of the contour search, (0, 1]', 0.01, 1.0),
    'threshold_block_px': ('px at detection scale, odd, >= 3: adaptive threshold window',
                           3, 1001),
    'threshold_offset': ('grey levels (of 255): floor of the offset below the local mean '
                         'counted as dark', 0.0, 255.0),
    'threshold_contrast_fraction': ('offset below the local mean counted as dark / the local '
                                    'contrast (max - min in the threshold window)', 0.0, 1.0),
    'min_area_fraction': ('outer band quad area / image area, lower bound', 0.0, 1.0),
    'max_area_fraction': ('outer band quad area / image area, upper bound', 0.0, 1.0),
    'min_aspect_ratio': ('width / height of the quad in the image, lower bound', 0.0, None),
    'max_aspect_ratio': ('width / height of the quad in the image, upper bound', 0.0, None),
    'min_hole_area_ratio': ('aperture area / outer band area, lower bound', 0.0, 1.0),
    'max_hole_area_ratio': ('aperture area / outer band area, upper bound', 0.0, 1.0),
    'min_holes_fraction': ('light area inside a dark ring / its area (search), lower bound',
                           0.0, 1.0),
    'max_band_fraction': ('band width / shortest outer side, upper bound', 0.0, 1.0),
    'approx_tolerance': ('approxPolyDP tolerance / contour perimeter', 0.0, 1.0),
    'border_margin_px': ('px: the whole band must be this far inside the image', 0.0, None),
    'samples_per_side': ('edge points searched per aperture side, >= 2', 2, 10000),
    'search_half_width_px': ('px: first-pass search range along the edge normal', 0.0, None),
    'refine_half_width_px': ('px: second-pass search range along the edge normal', 0.0, None),
    'single_pass_tracking': ('a tracked frame whose outline (its last motion) and aperture '
                             "(the band's proportions) were predicted to within "
                             'refine_half_width_px / 2 in the frame before takes one refine '
                             'pass per edge instead of two passes / the aperture search',),
    'min_edge_contrast': ('grey levels (of 255): floor of the step of a valid edge point',
                          0.0, 255.0),
    'edge_contrast_fraction': ('step of a valid edge point / the band contrast to the wall',
                               0.0, 1.0),
    'min_edge_inlier_fraction': ('valid edge points per side / samples_per_side', 0.0, 1.0),
    'line_inlier_px': ('px (undistorted): residual gate of the line fit', 0.0, None),
    'max_corner_jump_px': ('px: a larger corner motion between frames is a loss', 0.0, None),
    'reacquire_after_frames': ('frames without the tracked window before a new search',
                               0, None),
    'window_width_m': ('m: aperture width (the world\'s window), for the band proportions',
                       0.0, None),
    'window_height_m': ('m: aperture height, for the band proportions', 0.0, None),
    'frame_band_m': ('m: width of the dark band around the aperture', 0.0, None),
    'max_band_deviation': ('measured aperture side off its line predicted from the band '
                           'proportions / predicted band width, upper bound', 0.0, None),
    'max_shape_error': ('band quad vs a perspective view of its known rectangle (relative); '
                        'checked when an aperture side is taken from the proportions',
                        0.0, None),
}
