"""The window detector: the tracked window refined from its last outline, else a search.

:class:`WindowDetector` composes the stages: :class:`~.candidates.CandidateSearch` (the
whole-image search), :class:`~.edges.EdgeRefiner` (sub-pixel edges of a candidate) and
:class:`~.tracker.WindowTracker` (the track from frame to frame).
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.camera import CameraModel

from .candidates import CandidateSearch
from .config import WindowDetectorConfig
from .edges import EdgeRefiner
from .results import Reject, WindowResult
from .tracker import WindowTracker


class WindowDetector:
    """Detect and track the window aperture (stateful: one instance per camera stream)."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config
        self.search = CandidateSearch(config)
        self.edges = EdgeRefiner(config)
        self.tracker = WindowTracker(config)
        self.single_passes = 0                # tracked frames whose outer edges took one pass
        self.inner_single_passes = 0          # ... whose aperture edges took one pass

    def reset(self) -> None:
        """Forget the tracked window."""
        self.tracker.reset()

    def process(self, gray: np.ndarray, camera: CameraModel,
                rotation_C: np.ndarray | None = None) -> WindowResult:
        """Detect the window in a grey image (uint8, camera.height x camera.width).

        ``rotation_C``: the camera's rotation since the previous image, as the matrix M that
        maps a fixed direction's bearing in the previous optical frame to the current one,
        ``b_now = M b_prev`` (from the IMU: ``M = R_IC(now)^T R_IC(prev)``,
        ``R_IC = R_IB R_BC``). The tracked window (the outline the fast path starts from and
        the corners the jump gate compares with) is moved by it first: exact for a pure
        rotation, so the search and the ``max_corner_jump_px`` gate are left with the motion
        that translation causes. None: no prediction (the window is assumed still).
        """
        reason = Reject.NO_CANDIDATE          # the furthest stage a candidate reached
        if rotation_C is not None:
            self.tracker.rotate(camera, np.asarray(rotation_C, dtype=float))
        start = self.tracker.start_outline()
        if start is not None:
            # fast path: refine the tracked window from its predicted outline, no contour search
            refined = self.tracker.refine(self.edges, gray, camera, start)
            if not isinstance(refined, str):
                self.single_passes += refined.one_pass
                self.inner_single_passes += refined.aperture.one_pass
                return self.tracker.follow_tracked(refined, start)
            reason = Reject.furthest(reason, refined)
        self.tracker.forget_motion()
        found = []
        for ring in self.search.rings(gray, camera):
            # a component's first candidate that refines (its outer boundary's, else a hole's)
            for quad in ring:
                refined = self.edges.refine(gray, camera, quad)
                if not isinstance(refined, str):
                    found.append(refined)
                    break
                reason = Reject.furthest(reason, refined)
        return self.tracker.follow(found, reason)
