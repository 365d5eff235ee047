"""Tuning of the window detector: its dataclass and the specs of its ROS parameters."""
from __future__ import annotations

from dataclasses import dataclass
from ibvs_common.core.params import param

#: a tracked frame's outer edges take one search of the refine range when the outline
#: prediction was off by at most refine_half_width_px / this in the frame before, and the
#: result lies within that of the start (the tracker's single pass, `WindowTracker.refine`)
SINGLE_PASS_MARGIN = 2.0


@dataclass(frozen=True)
class WindowDetectorConfig:
    """Tuning of :class:`WindowDetector` (pixels are full-resolution pixels unless noted)."""

    detection_scale: float = param(0.5, 'image scale of the contour search, (0, 1]', 0.01, 1.0)
    threshold_block_px: int = param(
        31, 'px at detection scale, odd, >= 3: adaptive threshold window', 3, 1001)
    threshold_offset: float = param(
        4.0, 'grey levels (of 255): floor of the offset below the local mean counted as dark', 0.0,
        255.0)
    threshold_contrast_fraction: float = param(
        0.15, 'offset below the local mean counted as dark / the local contrast (max - min in the '
        'threshold window)', 0.0, 1.0)
    min_area_fraction: float = param(
        0.01, 'outer band quad area / image area, lower bound', 0.0, 1.0)
    max_area_fraction: float = param(
        0.98, 'outer band quad area / image area, upper bound', 0.0, 1.0)
    min_aspect_ratio: float = param(
        0.35, 'width / height of the quad in the image, lower bound', 0.0)
    max_aspect_ratio: float = param(
        3.0, 'width / height of the quad in the image, upper bound', 0.0)
    min_hole_area_ratio: float = param(
        0.5, 'aperture area / outer band area, lower bound', 0.0, 1.0)
    max_hole_area_ratio: float = param(
        0.93, 'aperture area / outer band area, upper bound', 0.0, 1.0)
    min_holes_fraction: float = param(
        0.25, 'light area inside a dark ring / its area (search), lower bound', 0.0, 1.0)
    max_band_fraction: float = param(
        0.25, 'band width / shortest outer side, upper bound', 0.0, 1.0)
    approx_tolerance: float = param(0.04, 'approxPolyDP tolerance / contour perimeter', 0.0, 1.0)
    border_margin_px: float = param(
        4.0, 'px: the whole band must be this far inside the image', 0.0)
    samples_per_side: int = param(40, 'edge points searched per aperture side, >= 2', 2, 10000)
    search_half_width_px: float = param(
        8.0, 'px: first-pass search range along the edge normal', 0.0)
    refine_half_width_px: float = param(
        3.0, 'px: second-pass search range along the edge normal', 0.0)
    single_pass_tracking: bool = param(
        True,
        "a tracked frame whose outline (its last motion) and aperture (the band's proportions) "
        'were predicted to within refine_half_width_px / 2 in the frame before takes one refine '
        'pass per edge instead of two passes / the aperture search')
    min_edge_contrast: float = param(
        6.0, 'grey levels (of 255): floor of the step of a valid edge point', 0.0, 255.0)
    edge_contrast_fraction: float = param(
        0.2, 'step of a valid edge point / the band contrast to the wall', 0.0, 1.0)
    min_edge_inlier_fraction: float = param(
        0.5, 'valid edge points per side / samples_per_side', 0.0, 1.0)
    line_inlier_px: float = param(1.0, 'px (undistorted): residual gate of the line fit', 0.0)
    max_corner_jump_px: float = param(
        30.0, 'px: a larger corner motion between frames is a loss', 0.0)
    reacquire_after_frames: int = param(
        10, 'frames without the tracked window before a new search', 0)
    window_width_m: float = 1.2             # aperture width (world.yaml window.width), m
    window_height_m: float = 1.0            # aperture height, m
    frame_band_m: float = 0.08              # band width around the aperture, m
    max_band_deviation: float = param(
        0.5, 'measured aperture side off its line predicted from the band proportions / predicted '
        'band width, upper bound', 0.0)
    max_shape_error: float = param(
        0.02, 'band quad vs a perspective view of its known rectangle (relative); checked when an '
        'aperture side is taken from the proportions', 0.0)

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
