"""The track of one window from frame to frame: where a frame starts, how far it may move.

A tracked frame refines the window from its last outline, moved by the camera's rotation
(gyro) and by the outline's last motion, instead of searching the whole image; a well
predicted track takes one refine pass per edge. A corner jump above ``max_corner_jump_px`` is
a loss, not followed; after ``reacquire_after_frames`` frames without the window the largest
window found is taken anew.
"""
from __future__ import annotations

import numpy as np

from ibvs_common.core.camera import CameraModel

from .config import SINGLE_PASS_MARGIN, WindowDetectorConfig
from .edges import Aperture, EdgeRefiner, Refined
from .geometry import _largest_distance, _quad_area, N_CORNERS
from .results import Reject, WindowResult, WindowStatus


class WindowTracker:
    """The tracked window: its predicted outline, the passes it allows, the jump gate."""

    def __init__(self, config: WindowDetectorConfig) -> None:
        self.config = config
        self._last_px: np.ndarray | None = None
        self._last_bearings: np.ndarray | None = None
        self._last_outer_u: np.ndarray | None = None
        self._rotation_since = np.eye(3)      # camera rotation not yet applied to the track
        self._frames_since_seen = 0
        self._motion_u: np.ndarray | None = None  # the outline's last motion (4, 2), undist. px
        self._prediction_error_px: float | None = None  # how far the last start was off
        # the tracked aperture: what its last refine read (each side's polarity and the band's
        # level per sample, for one refine pass) and how far it was from where the band's
        # proportions put it (undistorted px)
        self._aperture: Aperture | None = None
        self._inner_error_px: float | None = None

    def reset(self) -> None:
        """Forget the tracked window."""
        self._last_px = None
        self._last_bearings = None
        self._last_outer_u = None
        self._rotation_since = np.eye(3)
        self._frames_since_seen = 0
        self.forget_motion()

    def forget_motion(self) -> None:
        """Drop the outline's last motion and the aperture: both passes and its search next."""
        self._motion_u = self._prediction_error_px = None
        self._aperture = self._inner_error_px = None

    def rotate(self, camera: CameraModel, M: np.ndarray) -> None:
        """Move the tracked corners and outline by the camera rotation M (WindowDetector.process).

        Only when the rotation moves a corner by more than half the first-pass search range
        (``search_half_width_px``): below that the search finds the edges from the unmoved
        outline, and the result, whose sub-pixel noise depends on where the search starts,
        stays what it was without the IMU (a replayed bag then reproduces it whatever the
        order in which an IMU sample and the image of the same stamp arrived).
        """
        if self._last_bearings is None:
            return
        M = M @ self._rotation_since             # with the rotations not applied yet
        b = self._last_bearings @ M.T
        uv, valid = camera.bearings_to_pixels(b)
        if not np.all(valid):                    # rotated out of view: search the image
            self.reset()
            return
        if np.max(np.linalg.norm(uv - self._last_px, axis=1)) \
                <= 0.5 * self.config.search_half_width_px:
            self._rotation_since = M             # kept for when it adds up
            return
        self._rotation_since = np.eye(3)
        self._last_bearings, self._last_px = b, uv
        # the outline moved by the rotation: its last motion and how well it was predicted
        # say nothing of this frame (both passes and the aperture's search, then new motions)
        self.forget_motion()
        if self._last_outer_u is not None:
            K = camera.K
            rays = np.column_stack([(self._last_outer_u - K[:2, 2]) / np.diag(K)[:2],
                                    np.ones(N_CORNERS)]) @ M.T
            if np.all(rays[:, 2] > 0.0):
                self._last_outer_u = rays[:, :2] / rays[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
            else:
                self._last_outer_u = None

    def start_outline(self) -> np.ndarray | None:
        """Outer quad (undistorted px) a tracked frame starts from; None: no track (search).

        The last outline, moved on by its last motion when the frame before was detected too.
        """
        last, gap = self._last_outer_u, self._frames_since_seen
        if last is None:
            return None
        return last + self._motion_u if self._motion_u is not None and not gap else last

    def refine(self, edges: EdgeRefiner, gray: np.ndarray, camera: CameraModel,
               start_u: np.ndarray) -> Refined | str:
        """:meth:`EdgeRefiner.refine` of the tracked window from its predicted outline.

        One outer pass of the refine range when the last prediction was good and its result
        stays near the start; else the two passes. Likewise the aperture: one refine pass from
        where the band's proportions put it, with the polarity and band level of its last
        search, when it lay near there last frame; else its search. Returns the window, or the
        furthest :class:`Reject` reason of the refines.
        """
        cfg = self.config
        reach = cfg.refine_half_width_px / SINGLE_PASS_MARGIN
        inner_pass = cfg.single_pass_tracking and self._inner_error_px is not None \
            and self._inner_error_px <= reach and self._aperture.sign is not None
        last_aperture = self._aperture if inner_pass else None
        reason = Reject.NO_CANDIDATE
        if cfg.single_pass_tracking and self._prediction_error_px is not None \
                and self._prediction_error_px <= reach:
            refined = edges.refine(gray, camera, start_u, True, last_aperture)
            if isinstance(refined, str):
                reason = refined
            elif _largest_distance(refined.outer_u, start_u) <= reach:
                return refined
        refined = edges.refine(gray, camera, start_u, False, last_aperture)
        return Reject.furthest(reason, refined) if isinstance(refined, str) else refined

    def follow(self, refined: list[Refined], reason: str) -> WindowResult:
        """Follow the same window; a jump above max_corner_jump_px is a loss, not followed.

        ``refined``: each candidate of the frame that refined into a window; ``reason``: why
        the frame has none, when it has none.
        """
        cfg = self.config
        if self._last_px is not None and self._frames_since_seen >= cfg.reacquire_after_frames:
            self.reset()
        if not refined:
            # the tracked outline is kept: the fast path tries it again next frame (a noisy or
            # blurred frame loses one frame, not the track) until reacquire_after_frames
            self._frames_since_seen += 1
            return WindowResult(WindowStatus.NOT_FOUND, reason=reason)
        if self._last_px is None:
            best = max(refined, key=lambda r: _quad_area(r.outer_u))
        else:
            jumps = [float(np.max(np.linalg.norm(r.detection.corners_px - self._last_px, axis=1)))
                     for r in refined]
            best = refined[int(np.argmin(jumps))]
            if min(jumps) > cfg.max_corner_jump_px:
                self._frames_since_seen += 1
                self._last_outer_u = None
                return WindowResult(WindowStatus.JUMP, reason=Reject.JUMP)
        self._last_px, self._last_outer_u = best.detection.corners_px, best.outer_u
        self._last_bearings = best.detection.bearings_C
        self._rotation_since = np.eye(3)
        self._frames_since_seen = 0
        return WindowResult(WindowStatus.DETECTED, best.detection)

    def follow_tracked(self, refined: Refined, start_u: np.ndarray) -> WindowResult:
        """:meth:`follow` of the window refined from ``start_u``; when detected, its motion.

        The outline's motion over this frame, how far it was from its start, and the aperture
        with how far it was from its prediction: what the next frame's start and passes use.
        """
        last, gap = self._last_outer_u, self._frames_since_seen
        result = self.follow([refined], Reject.NO_CANDIDATE)
        if result.status == WindowStatus.DETECTED:
            outer, aperture = refined.outer_u, refined.aperture
            self._motion_u = None if gap else outer - last    # per frame only
            self._prediction_error_px = _largest_distance(outer, start_u)
            self._inner_error_px = _largest_distance(aperture.quad_u, aperture.predicted_u)
            self._aperture = aperture
        return result
