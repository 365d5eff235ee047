"""The mode supervisor as a pure state machine (paper section 4.3, docs/spec.md section 3).

Transitions and their image cues (no position or velocity estimate is used):

- 0 -> 1  ``start``: accepted when the full window is detected and the IMU is fresh.
- 1 -> 2  the forward camera no longer sees the full window, or the corners jump in a way
          incompatible with smooth motion, while the window was seen close: its angular height
          at least ``crossing_min_angular_height_rad``, or at least
          ``crossing_border_angular_height_rad`` with the last corners within
          ``crossing_border_margin_px`` of the image border (the window left the view early:
          the vehicle off the window's axis or tilted). A loss far from the window is not a
          crossing: it ends in failsafe after ``window_timeout_s`` (``window_loss_note`` says
          so once per loss, with the last corners' angular height and border margin, for the
          node's log).
- 2 -> 3  only once, when the down camera sees a complete pad group AFTER the window plane is
          crossed by ``crossing_margin_m``. The crossing length is measured from images only:
          d_o(T2) from the last corners and the known width r_w, the height d_t(T2) from the
          ratio of the wall and floor flows (same v: d_t = d_o |phi_w| / |phi_t|), then the
          travel d_t * integral(eta_w^T phi_t dt). phi_w is the last wall flow of WINDOW,
          phi_t the first floor flow of CROSSING (stamped T2 when it is valid: the floor flow
          is computed only from the switch on, docs/interfaces.md "Mode gating").
- 3 -> 4  the height estimated from the smallest complete pad group (known size c) is below
          ``shutdown_height_m`` (SPEC: an image criterion, -eta_t^T q_t of that group) on
          every pad frame for ``shutdown_confirm_s`` (one wrong frame cannot shut down).
          A frame without a complete group takes the height carried by the floor flow
          (pad_prediction.py, ``pad_prediction_s``), counted only while the carried pad
          centre is within ``shutdown_carried_offset_m`` sideways, or once it has stayed
          below the shutdown height for ``shutdown_carried_wait_s`` (at the floor). Checked
          when the frame is closed (:meth:`end_frame`), with the frame's pad and floor flow.
- any flying mode -> 5 (failsafe) when an input it needs is stale (timeouts), on ``abort``,
          when the crossing does not find the pad within ``crossing_timeout_s``, or when the
          node's clock stepped back (:meth:`clock_stepped_back`: no input's age can be
          measured across the step).
All times are seconds of the node clock (sim time in simulation).

The node feeds one camera frame's inputs together (``on_*`` with the frame's stamp, in a
fixed order, once the frame's inputs are in) and closes the frame with :meth:`end_frame`, so
that a transition happens at the frame whose inputs caused it, whatever their arrival order.
``auto_start_at_s`` >= 0 makes the supervisor start by itself at the first frame at or after
that time (repeatable simulation runs; on a vehicle ``ibvs/start`` starts it).
``ibvs/start`` (:meth:`request_start`) is checked at once and applied when the next frame is
closed, so that the perception's mode gating and the statuses agree on the first WINDOW frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ibvs_common.core.params import param
from ibvs_common.core.features import (
    centroid_feature, distance_to_window_plane, edge_normals, pad_feature,
    pad_height_estimate, window_axes, window_centre_offset, window_normal)
from ibvs_common.core.frames import e3
from ibvs_common.core.modes import FLYING_MODES, InputKind, Mode
from ibvs_control.core.pad_prediction import PadPrediction

__all__ = ['Mode', 'ModeSupervisor', 'SupervisorConfig', 'Transition']

#: the input (whose age the staleness rules watch) of each frame product, by InputKind value
PRODUCT_INPUTS = {InputKind.WINDOW.value: 'window', InputKind.FLOW_FRONT.value: 'front_flow',
                  InputKind.FLOW_DOWN.value: 'down_flow', InputKind.PAD.value: 'pad'}


@dataclass(frozen=True)
class SupervisorConfig:
    """Thresholds and timeouts of the supervisor (seconds, metres, radians)."""

    r_w: float = 1.2                               # m, known window width
    imu_timeout_s: float = param(
        0.2, 's (ROS clock), IMU older than this: failsafe (flying modes), > 0', 0.0)
    window_timeout_s: float = param(
        0.5, 's (ROS clock), mode 1: window lost far away this long -> failsafe, > 0', 0.0)
    front_flow_timeout_s: float = param(
        0.5, 's (ROS clock), mode 1: no wall flow this long -> failsafe, > 0', 0.0)
    down_flow_timeout_s: float = param(
        0.5, 's (ROS clock), modes 2-3: no floor flow this long -> failsafe, > 0', 0.0)
    pad_timeout_s: float = param(
        1.5, 's (ROS clock), mode 3: no pad this long -> failsafe, > 0', 0.0)
    crossing_min_angular_height_rad: float = param(
        0.85, 'rad, window lost while its angular height is this big -> mode 2 (crossing), > 0',
        0.0)
    crossing_border_angular_height_rad: float = param(
        0.72, 'rad: a window lost while its last corners lay within crossing_border_margin_px '
        'of the image border (it left the view: an offset or a tilt takes it out before '
        'crossing_min_angular_height_rad) and its angular height was this big -> mode 2 too; '
        'above the largest at a start in the spec box (0.70); >= '
        'crossing_min_angular_height_rad = off, > 0', 0.0)
    crossing_border_margin_px: float = param(
        60.0, 'px: the last corners this close to the image border (the closest one) count as '
        'leaving the view (the detector drops the window when its dark band reaches the '
        'border: 17-52 px at the losses measured; a centred window at 0.85 rad keeps ~74 px), '
        '> 0', 0.0)
    crossing_border_max_offset_m: float = param(
        0.4, 'm: ... and only while the window centre lay at most this far off the camera\'s '
        'axis through the window (in its plane, from the last corners and r_w): further off, '
        'a blind crossing hits the frame as often as not (feature-level campaign at 1 m/s^2 '
        'of wind), > 0', 0.0)
    window_jump_rad: float = param(
        0.1, 'rad, a corner jump this big between frames = window lost, > 0', 0.0)
    window_jump_max_gap_frames: float = param(
        5.0, 'computed frames (the camera period times the frame stride): corner jumps are '
        'judged only across shorter gaps, > 0', 0.0)
    crossing_margin_m: float = param(0.5, 'm, travel past the wall plane before mode 3, > 0', 0.0)
    crossing_fallback_travel: float = param(
        1.0, 'travel / height (dimensionless) when the height is unknown, > 0', 0.0)
    crossing_timeout_s: float = param(
        10.0, 's (ROS clock), mode 2 without a pad this long -> failsafe, > 0', 0.0)
    shutdown_height_m: float = param(
        0.14, 'm, pad-image height of the 3 -> 4 (shutdown) switch, > 0', 0.0)
    shutdown_confirm_s: float = param(
        0.02, 's (frame stamps, ROS clock): the pad-image height must stay at or below '
        'shutdown_height_m on every pad frame for this long (0.02: two 50 Hz frames) before the '
        '3 -> 4 switch, so that one wrong frame cannot shut the motors down in the air, > 0', 0.0)
    pad_prediction_s: float = param(
        1.5,
        "s (ROS clock, from the last pad frame's stamp): in mode 3, a frame without a complete "
        'pad group takes the pad centre carried by the floor flow this long (pad_prediction.py; '
        "the force_controller's landing.pad_prediction_s), for the 3 -> 4 switch only; 0 = pad "
        'frames only, >= 0', 0.0)
    shutdown_carried_offset_m: float = param(
        0.04,
        'm: a carried pad-image height at or below shutdown_height_m switches 3 -> 4 only while '
        'the carried pad centre is within this horizontal distance of the camera (where the '
        'smallest group would be in view), > 0', 0.0)
    shutdown_carried_wait_s: float = param(
        0.5, 's (frame stamps, ROS clock): a carried pad-image height that stayed at or below '
        'shutdown_height_m this long switches 3 -> 4 however far off the carried centre is (the '
        'vehicle is at the floor: the descent from 0.14 m takes ~0.7 s), > 0', 0.0)
    skipped_frames_timeout_s: float = param(
        0.2, 's (frame stamps, ROS clock): frames of the mode\'s camera skipped (a product the '
        'mode needs late or lost) with no complete frame for this long, and at least '
        'skipped_frames_in_a_row of them -> failsafe; shorter than the bridge\'s hold_last_s, '
        'so that the supervisor decides before the bridge hands the vehicle back, > 0', 0.0)
    skipped_frames_in_a_row: int = param(
        3, 'frames: the fewest skipped frames in a row that fail safe (with '
        'skipped_frames_timeout_s; at a frame stride of 4, 0.2 s is under 3 frames)', 1, 1000)
    auto_start_at_s: float = param(
        -1.0, 's (ROS clock); >= 0: start by itself at the first frame at or after this time (sim '
        'runs), < 0: only ibvs/start starts')
    group_half_sides: dict = field(default_factory=lambda: {
        'A': 0.36, 'B': 0.20, 'C': 0.10, 'D': 0.045})   # from pad_layout.yaml (c per group)

    def __post_init__(self) -> None:
        """Raise ValueError for a threshold or timeout that is not > 0 (see each field)."""
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == 'auto_start_at_s':
                if not np.isfinite(v):
                    raise ValueError(f'supervisor parameter {f.name} must be finite, got {v}')
            elif f.name == 'pad_prediction_s':
                if not (np.isfinite(v) and v >= 0.0):
                    raise ValueError(f'supervisor parameter {f.name} must be >= 0, got {v}')
            elif isinstance(v, float) and not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'supervisor parameter {f.name} must be > 0, got {v}')
            elif isinstance(v, int) and not isinstance(v, bool) and v < 1:
                raise ValueError(f'supervisor parameter {f.name} must be >= 1, got {v}')

    @classmethod
    def from_params(cls, params: dict) -> 'SupervisorConfig':
        """Build from a flat dict; unknown keys raise ValueError, missing keys keep defaults."""
        known = {f.name for f in fields(cls)}
        unknown = set(params) - known
        if unknown:
            raise ValueError(f'unknown supervisor parameter(s): {sorted(unknown)}')
        return cls(**params)


@dataclass(frozen=True)
class Transition:
    """One mode change, with the reason logged by the node."""

    from_mode: Mode
    to_mode: Mode
    t: float
    reason: str


def _angular_height(corners_I: np.ndarray) -> float:
    """Angle (rad) between the mid-points of the top and bottom edges' bearings."""
    top = corners_I[0] + corners_I[1]
    bottom = corners_I[2] + corners_I[3]
    c = top @ bottom / (np.linalg.norm(top) * np.linalg.norm(bottom))
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


class ModeSupervisor:
    """Modes and triggers of docs/spec.md section 3; feed it with on_* and call update(t)."""

    def __init__(self, config: SupervisorConfig) -> None:
        self.config = config
        self.mode = Mode.IDLE
        self.transitions: list[Transition] = []
        self._last: dict[str, float] = {}              # input name -> last fresh time
        self._pending: list[tuple[Mode, str]] = []       # requested (mode, reason)
        self._corners: np.ndarray | None = None         # last full-window corners, {I}
        self._window_close = False
        self._window_angular_height: float | None = None    # of the last accepted corners
        self._window_border_margin_px: float | None = None  # theirs in the image (None: unknown)
        self._window_loss_noted = False                 # this loss of the window was noted
        # a loss of the window in WINDOW while it was not close (no crossing), for the log:
        # the node logs and clears it (once per loss)
        self.window_loss_note = ''
        self._eta_w: np.ndarray | None = None
        # the wall normal at T2: the blind crossing's travel is measured along it (a window
        # detection after T2, the window leaving the view, does not move it)
        self._eta_w_T2: np.ndarray | None = None
        self._d_o_T2: float | None = None
        self._phi_front_T2: np.ndarray | None = None    # wall flow at T2, until phi_t comes
        self._phi_front: np.ndarray | None = None
        self._travel_norm = 0.0                         # integral of eta_w^T phi_t dt
        self._travel_needed: float | None = None        # same units
        self._t_flow_down: float | None = None
        self._t_mode = 0.0
        self._pad_seen = False
        self._landing_entered = False
        self._height_est: float | None = None
        self._t_below_shutdown: float | None = None     # first frame of the current run below
        self._pad_prediction = PadPrediction(config.pad_prediction_s, e3)
        self._frame_pad: tuple[np.ndarray, float | None] | None = None   # this frame's q_t, h
        self._frame_phi_down: np.ndarray | None = None  # this frame's floor flow
        self._t_carried_below: float | None = None      # first carried frame below, off-centre
        self.frame_period_s = 0.02    # s between two computed front frames (the node sets it)
        self.auto_start_refusal = ''                    # why the last auto-start was refused
        # the blind crossing's length as measured at the first floor flow, for the log (the
        # node logs and clears it)
        self.crossing_note = ''
        self.start_refusal = ''                         # why the last start request was dropped
        self._start_requested_at: float | None = None   # t of an accepted ibvs/start request
        self._start_source = 'ibvs/start'               # who asked (the transition's reason)
        self._t_complete: float | None = None           # stamp of the last complete frame
        self._skipped_run: list[tuple[float, tuple]] = []   # frames skipped since, (t, missing)
        self._late_in_run: set[str] = set()             # products that came late in that run
        self._seen_in_mode: set[str] = set()            # products that came since the mode began
        self.skipped_frames = 0                         # frames skipped in all

    # --- commands ---------------------------------------------------------------------------
    def start(self, t: float, reason: str = 'start requested') -> tuple[bool, str]:
        """Leave IDLE for WINDOW if the window and the IMU are fresh."""
        ok, message = self._start_checks(t)
        if not ok:
            return False, message
        self._switch(t, Mode.WINDOW, f'{reason}, window detected')
        return True, 'started: window approach (mode 1)'

    def _start_checks(self, t: float) -> tuple[bool, str]:
        if self.mode != Mode.IDLE:
            return False, f'cannot start from mode {self.mode.name}'
        if not self._fresh('imu', t, self.config.imu_timeout_s):
            return False, 'IMU attitude is stale or missing'
        if self._corners is None or not self._fresh('window', t, self.config.window_timeout_s):
            return False, 'the full window is not detected'
        return True, ''

    def request_start(self, t: float, source: str = 'ibvs/start') -> tuple[bool, str]:
        """Accept a start (``ibvs/start``) for the next frame if :meth:`start` would now.

        The checks of :meth:`start` are made at ``t`` and again when :meth:`end_frame` applies
        the request; it lapses if that frame's stamp is more than ``window_timeout_s`` after
        ``t`` (frames stopped meanwhile), on :meth:`abort` and on a clock step. ``source``
        (``ibvs/start``, ``pilot switch``) names the start in its transition.
        """
        ok, message = self._start_checks(t)
        if not ok:
            return False, message
        self._start_requested_at = t
        self._start_source = source
        return True, 'start accepted: window approach (mode 1) from the next frame'

    def cancel_start(self) -> bool:
        """Drop a start accepted by :meth:`request_start` and not applied yet; whether one was."""
        pending, self._start_requested_at = self._start_requested_at, None
        return pending is not None

    def abort(self, t: float, reason: str = 'abort requested') -> tuple[bool, str]:
        """Go to FAILSAFE from any mode except SHUTDOWN (already landing the motors)."""
        self._start_requested_at = None
        if self.mode in (Mode.FAILSAFE, Mode.SHUTDOWN):
            return False, f'already in {self.mode.name}'
        self._switch(t, Mode.FAILSAFE, reason)
        return True, 'aborted: failsafe'

    def clock_stepped_back(self, t: float, back_s: float) -> list[Transition]:
        """Take a step back of the node's clock by ``back_s`` (s), to ``t``.

        An input's age, ``t`` minus its stamp, can no longer be measured for the inputs taken
        before the step (they would look fresh for the length of the step), so every input
        counts as missing until it comes again. In a flying mode this is FAILSAFE, as for a
        stale input; in IDLE a start then needs inputs taken after the step.
        """
        self._last.clear()
        self._t_flow_down = None
        self._t_below_shutdown = None
        self._start_requested_at = None
        if self.mode not in FLYING_MODES:
            return []
        return [self._switch(t, Mode.FAILSAFE, f'the clock went back by {back_s:.3f} s (a step '
                             'of the system clock): input ages cannot be measured')]

    # --- inputs -----------------------------------------------------------------------------
    def on_imu(self, t: float, R_IB: np.ndarray | None = None) -> None:
        """Note a valid IMU sample at t (its attitude R_IB is not needed: only its age is)."""
        self._last['imu'] = t

    def on_window(self, t: float, corner_bearings_I: np.ndarray | None,
                  border_margin_px: float | None = None) -> None:
        """Full-window corners in {I} (TL, TR, BR, BL), or None when not fully detected.

        ``border_margin_px``: how far the corners lie from the image border, the closest one
        (``CameraModel.border_margin_px`` of the camera-frame corners; None: not known, a loss
        then counts as a crossing only at ``crossing_min_angular_height_rad``).
        """
        cfg = self.config
        if corner_bearings_I is not None:
            p = np.asarray(corner_bearings_I, dtype=float).reshape(4, 3)
            jumped = self._corners is not None and \
                self._fresh('window', t, cfg.window_jump_max_gap_frames * self.frame_period_s) \
                and \
                float(np.max(np.arccos(np.clip(np.sum(p * self._corners, axis=1), -1, 1)))) \
                > cfg.window_jump_rad
            if not jumped:
                self._corners = p
                self._last['window'] = t
                self._window_angular_height = _angular_height(p)
                self._window_border_margin_px = border_margin_px
                self._window_loss_noted = False
                try:
                    h = edge_normals(p)
                    u_w, rho_w = window_axes(h, p)
                    self._eta_w = window_normal(u_w, rho_w, centroid_feature(p), self._eta_w)
                except ValueError:
                    pass
                self._window_close = self._close_enough(p, border_margin_px)
                return
            reason = 'window corners jumped (incompatible with smooth motion)'
        else:
            reason = 'forward camera lost the full window'
        if self.mode == Mode.WINDOW and self._window_close:
            self._request(Mode.CROSSING, reason)
        elif self.mode == Mode.WINDOW and not self._window_loss_noted:
            self._window_loss_noted = True
            height = 'none' if self._window_angular_height is None \
                else f'{self._window_angular_height:.3f} rad'
            margin = 'unknown' if self._window_border_margin_px is None \
                else f'{self._window_border_margin_px:.0f} px'
            self.window_loss_note = (
                f'{reason} at t = {t:.3f} s while not close: the last accepted corners\' '
                f'angular height {height} < {cfg.crossing_min_angular_height_rad:g} rad '
                f'(or < {cfg.crossing_border_angular_height_rad:g} rad at the image border: '
                f'their margin {margin}, border <= {cfg.crossing_border_margin_px:g} px), so no '
                f'crossing (stale after {cfg.window_timeout_s:g} s unless it comes back)')

    def _close_enough(self, corners_I: np.ndarray, border_margin_px: float | None) -> bool:
        """Whether a loss of the window after these corners would be a crossing (1 -> 2)."""
        cfg = self.config
        height = self._window_angular_height
        if height >= cfg.crossing_min_angular_height_rad:
            return True
        if height < cfg.crossing_border_angular_height_rad or border_margin_px is None \
                or border_margin_px > cfg.crossing_border_margin_px or self._eta_w is None:
            return False
        try:       # at the border: near enough to the window's axis for a blind crossing?
            offset = window_centre_offset(corners_I, self._eta_w, cfg.r_w)
        except (ValueError, ZeroDivisionError, FloatingPointError):
            return False
        return bool(np.linalg.norm(offset) <= cfg.crossing_border_max_offset_m)

    def on_pad(self, t: float, landmark_bearings_I: np.ndarray | None,
               groups: list[str], weights: tuple | None = None) -> None:
        """Landmarks of complete pad groups in {I} (4 per group, groups in ``groups`` order).

        ``weights``: the groups' weights in q_t (pad/groups; None: equal).
        """
        if landmark_bearings_I is None or len(groups) == 0:
            return
        p = np.asarray(landmark_bearings_I, dtype=float).reshape(-1, 3)
        if len(p) != 4 * len(groups):
            return
        self._last['pad'] = t
        self._pad_seen = True
        sizes = [(self.config.group_half_sides.get(g), i) for i, g in enumerate(groups)]
        sizes = [(c, i) for c, i in sizes if c is not None]
        height = None
        if sizes:
            c, i = min(sizes)
            try:
                height = pad_height_estimate(p[4 * i:4 * i + 4], c)
            except ValueError:                  # a marker not towards the floor: no estimate
                pass
        self._height_est = height
        if self.mode == Mode.LANDING:           # the frame's pad for _landing_frame
            try:
                self._frame_pad = (pad_feature(p, weights=weights), height)
            except ValueError:                  # no usable group: as no pad this frame
                self._frame_pad = None
        if self.mode == Mode.CROSSING and not self._landing_entered and self._crossed():
            self._request(Mode.LANDING, 'pad group seen after crossing the window plane')

    def _landing_frame(self, t: float) -> None:
        """Mode 3, at the end of frame t: the pad-image height, measured or carried; 3 -> 4.

        A carried height counts only while the carried centre is within
        ``shutdown_carried_offset_m`` sideways (where the smallest group would be in view);
        a carried frame farther off waits, unless the carried height has been below the
        shutdown height for ``shutdown_carried_wait_s`` (the vehicle is then at the floor).
        """
        q_t, height = self._frame_pad if self._frame_pad is not None else (None, None)
        pad = self._pad_prediction.step(t, q_t, height, self._frame_phi_down)
        if pad is None or pad.height_m is None:
            self._t_carried_below = None
            return
        self._height_est = pad.height_m
        offset = None
        if pad.predicted:
            offset = float(np.hypot(pad.r_I[0], pad.r_I[1]))
            below = pad.height_m <= self.config.shutdown_height_m
            if not below:
                self._t_carried_below = None
            elif self._t_carried_below is None:
                self._t_carried_below = t
            waited = below and t - self._t_carried_below >= \
                self.config.shutdown_carried_wait_s - 1e-9
            if offset > self.config.shutdown_carried_offset_m and not waited:
                self._t_below_shutdown = None
                return
        else:
            self._t_carried_below = None
        self._check_shutdown(t, offset)

    def _check_shutdown(self, t: float, carried_offset: float | None) -> None:
        """3 -> 4 once the height stayed <= shutdown_height_m for shutdown_confirm_s."""
        if self._height_est > self.config.shutdown_height_m:
            self._t_below_shutdown = None
            return
        if self._t_below_shutdown is None:
            self._t_below_shutdown = t
        if t - self._t_below_shutdown >= self.config.shutdown_confirm_s - 1e-9:
            how = ('pad-image' if carried_offset is None else
                   f'carried (pad {100 * carried_offset:.1f} cm off, on the floor flow)')
            self._request(Mode.SHUTDOWN,
                          f'{how} height {self._height_est:.3f} m <= shutdown height '
                          f'since {self._t_below_shutdown:.3f} s')

    def on_flow(self, t: float, camera: str, phi_I: np.ndarray | None) -> None:
        """Note the translational flow of 'front' (wall) or 'down' (floor) in {I}, or None."""
        if phi_I is None:
            return
        phi = np.asarray(phi_I, dtype=float)
        if camera == 'front':
            self._phi_front = phi
            self._last['front_flow'] = t
        elif camera == 'down':
            if self.mode == Mode.CROSSING and self._phi_front_T2 is not None:
                self._measure_crossing(self._phi_front_T2, phi)
                self._phi_front_T2 = None
            if self.mode == Mode.CROSSING and self._eta_w_T2 is not None \
                    and self._t_flow_down is not None:
                dt = max(t - self._t_flow_down, 0.0)
                self._travel_norm += float(self._eta_w_T2 @ phi) * dt
            self._t_flow_down = t
            self._last['down_flow'] = t
            self._frame_phi_down = phi

    # --- evaluation -------------------------------------------------------------------------
    def end_frame(self, t: float) -> list[Transition]:
        """Close the frame of stamp t (its inputs were given): auto-start, then :meth:`update`.

        The auto-start is tried at each frame from ``auto_start_at_s`` on until it is accepted
        (``auto_start_refusal`` says why it was not), never again after. An accepted
        :meth:`request_start` is applied here, once (``start_refusal`` says why it lapsed).
        """
        done = []
        self._t_complete = t
        self._skipped_run.clear()
        self._late_in_run.clear()
        if self.mode == Mode.LANDING:
            self._landing_frame(t)
        self._frame_pad = self._frame_phi_down = None
        self.auto_start_refusal = self.start_refusal = ''
        requested, self._start_requested_at = self._start_requested_at, None
        if requested is not None and self.mode == Mode.IDLE:
            if t - requested > self.config.window_timeout_s:
                self.start_refusal = (f'no frame within {self.config.window_timeout_s:g} s of '
                                      'the request')
            else:
                self.start_refusal = self._start_at_frame(t, self._start_source, done)
        start_at = self.config.auto_start_at_s
        if 0.0 <= start_at <= t and self.mode == Mode.IDLE and not self.transitions:
            self.auto_start_refusal = self._start_at_frame(t, f'auto-start at {start_at:g} s',
                                                           done)
        return done + self.update(t)

    def _start_at_frame(self, t: float, reason: str, done: list) -> str:
        """:meth:`start` at the frame t; its transition appended to ``done``, or the refusal."""
        ok, message = self.start(t, reason)
        if ok:
            done.append(self.transitions[-1])
            return ''
        return message

    def frame_skipped(self, t: float, missing: tuple[str, ...]) -> list[Transition]:
        """Take a frame of stamp t skipped for want of ``missing`` products; return changes.

        Nothing of the frame is used. Frames skipped with no complete frame for
        ``skipped_frames_timeout_s`` end a flying mode in FAILSAFE (:meth:`update`).
        """
        self.skipped_frames += 1
        self._skipped_run.append((t, tuple(missing)))
        return self.update(t, apply_requests=False)

    def product_seen(self, name: str, t: float) -> None:
        """Note that a product (``name``) of the frame of stamp t came: its node is alive.

        During a run of skipped frames, a product of one of them (it came late) or of a newer
        frame (its node, behind, skipped the older images for the newest) shows that the
        product is not lost: a computer that falls behind delivers its products late or for
        other frames, and lowers its frame rate (the rate governor). Only products that do
        not come at all (a dead camera or node) end a mode by the skipped-frames rule; the
        staleness timeouts still bound how long frames may be skipped for want of CPU.
        """
        if self._skipped_run and t >= self._skipped_run[0][0]:
            self._late_in_run.add(name)
        if t > self._t_mode:               # a frame of this mode (not the one that began it)
            self._seen_in_mode.add(name)

    def update(self, t: float, apply_requests: bool = True) -> list[Transition]:
        """Apply requested transitions, then the staleness rules; return what changed.

        ``apply_requests`` False (the node's staleness watchdog between frames): only the
        staleness rules; a transition requested by an image cue waits for the next frame, so
        that it happens at a frame whatever the timing of the watchdog.
        """
        done = []
        if apply_requests:
            for to_mode, reason in self._pending:
                if self._allowed(to_mode):
                    done.append(self._switch(t, to_mode, reason))
            self._pending.clear()
        stale = self._stale_input(t)
        if stale is not None and self.mode in FLYING_MODES:
            done.append(self._switch(t, Mode.FAILSAFE, stale))
        return done

    @property
    def height_estimate(self) -> float | None:
        """Last pad-image height estimate (m), for diagnostics."""
        return self._height_est

    # --- internals --------------------------------------------------------------------------
    def _fresh(self, name: str, t: float, timeout: float) -> bool:
        return name in self._last and t - self._last[name] <= timeout

    def _request(self, to_mode: Mode, reason: str) -> None:
        self._pending.append((to_mode, reason))

    def _allowed(self, to_mode: Mode) -> bool:
        allowed = {Mode.WINDOW: (Mode.CROSSING,), Mode.CROSSING: (Mode.LANDING,),
                   Mode.LANDING: (Mode.SHUTDOWN,)}
        if to_mode == Mode.LANDING and self._landing_entered:
            return False
        return to_mode in allowed.get(self.mode, ())

    def _switch(self, t: float, to_mode: Mode, reason: str) -> Transition:
        tr = Transition(self.mode, to_mode, t, reason)
        if to_mode == Mode.CROSSING:
            self._enter_crossing()
        if to_mode == Mode.LANDING:
            self._landing_entered = True
            self._pad_prediction.reset()
        self.mode = to_mode
        self._t_mode = t
        self._seen_in_mode.clear()
        self.transitions.append(tr)
        return tr

    def _enter_crossing(self) -> None:
        """At T2: d_o from the last corners; the travel waits for the first floor flow."""
        self._travel_norm = 0.0
        self._travel_needed = self.config.crossing_fallback_travel
        self._t_flow_down = None          # the travel integral starts at the first floor flow
        self._phi_front_T2 = None
        self._eta_w_T2 = self._eta_w
        fallback = (f'blind crossing: {{}}: the fallback travel '
                    f'{self.config.crossing_fallback_travel:.3f} of floor flow')
        if self._corners is None or self._eta_w is None:
            self.crossing_note = fallback.format('no window corners or wall normal at T2')
            return
        try:
            self._d_o_T2 = distance_to_window_plane(self._corners, self._eta_w, self.config.r_w)
        except (ValueError, ZeroDivisionError, FloatingPointError):
            self.crossing_note = fallback.format('no distance to the window plane at T2')
            return
        self._phi_front_T2 = self._phi_front
        if self._phi_front is None:
            self.crossing_note = fallback.format('no wall flow at T2')

    def _measure_crossing(self, phi_front: np.ndarray | None, phi_down: np.ndarray) -> None:
        """Blind-crossing length from d_o(T2) and the two flows (same v at T2)."""
        if phi_front is None or self._d_o_T2 is None:
            return
        n_front, n_down = np.linalg.norm(phi_front), np.linalg.norm(phi_down)
        if n_front < 1e-3 or n_down < 1e-3:
            return
        d_t = self._d_o_T2 * n_front / n_down          # same velocity seen by both cameras
        self._travel_needed = (self._d_o_T2 + self.config.crossing_margin_m) / d_t
        self.crossing_note = (f'blind crossing: d_o(T2) {self._d_o_T2:.3f} m, |phi_front| '
                              f'{n_front:.3f} 1/s, first |phi_down| {n_down:.3f} 1/s: floor '
                              f'{d_t:.3f} m below, {self._travel_needed:.3f} of floor-flow '
                              'travel to the window plane plus the margin')

    @property
    def crossing_progress(self) -> tuple[float, float | None]:
        """(floor-flow travel since the first floor flow of CROSSING, travel needed or None)."""
        return self._travel_norm, self._travel_needed

    def _crossed(self) -> bool:
        return self._travel_needed is not None and self._travel_norm >= self._travel_needed

    def _skipped_for_long(self, t: float) -> str | None:
        """Return why to fail safe when frames have been skipped for too long, else None."""
        if not self._skipped_run:
            return None
        since = max(self._t_complete if self._t_complete is not None else -np.inf,
                    self._t_mode)
        if t - since <= self.config.skipped_frames_timeout_s \
                or len(self._skipped_run) < self.config.skipped_frames_in_a_row:
            return None
        missing = sorted(k for k in {k for _, m in self._skipped_run for k in m}
                         if k not in self._late_in_run and self._came_in_mode(k))
        if not missing:   # behind, or not started yet: the staleness timeouts judge it
            return None
        return (f'{len(self._skipped_run)} frames skipped in a row without '
                f'{", ".join(missing)} (lost: none came since) for more than '
                f'{self.config.skipped_frames_timeout_s} s in {self.mode.name}')

    def _came_in_mode(self, product: str) -> bool:
        """Whether ``product`` came since the mode began: only then can it be lost.

        A product the mode has just switched on (the front flow at WINDOW's start) has its
        first frames to compute, primer included; on a slow computer that takes longer than
        ``skipped_frames_timeout_s``. The staleness timeout gives it one timeout to appear.
        """
        last = self._last.get(PRODUCT_INPUTS.get(product, product))
        return product in self._seen_in_mode or (last is not None and last > self._t_mode)

    def _stale_input(self, t: float) -> str | None:
        cfg = self.config
        if not self._fresh('imu', t, cfg.imu_timeout_s):
            return 'IMU stale'
        needs = {Mode.WINDOW: (('window', cfg.window_timeout_s),
                               ('front_flow', cfg.front_flow_timeout_s)),
                 Mode.CROSSING: (('down_flow', cfg.down_flow_timeout_s),),
                 Mode.LANDING: (('down_flow', cfg.down_flow_timeout_s),
                                ('pad', cfg.pad_timeout_s))}.get(self.mode, ())
        skipped = self._skipped_for_long(t)
        if skipped is not None:
            return skipped
        for name, timeout in needs:
            # an input counts from the mode's start: give it one timeout to appear
            last = max(self._last.get(name, -np.inf), self._t_mode)
            if t - last > timeout:
                return f'{name} stale for more than {timeout} s in {self.mode.name}'
        if self.mode == Mode.CROSSING and t - self._t_mode > cfg.crossing_timeout_s:
            return f'no pad after {cfg.crossing_timeout_s} s of blind crossing'
        return None
