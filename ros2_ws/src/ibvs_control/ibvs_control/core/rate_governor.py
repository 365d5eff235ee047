"""The control rate the graph can hold: every frame, or every 2nd, 4th... (ROS-free).

The steps, cheapest loss first (:func:`ladder`): every frame; every frame with the
translational flows computed on every ``flow_shed_stride``-th frame of the grid and held
between (a flow at half rate costs the flight least: docs/design.md "Time"); then every 2nd,
4th... frame with every product on each.

A computer that cannot compute every camera frame in time skips frames (a product late or
lost: the frame is skipped, never flown on stale data). Skipped at random, the products of
one image rarely all come, and the control rate collapses. :class:`RateGovernor` watches the
frames of the mode's camera and, when the graph cannot hold their rate (several skipped in a
row: it fell behind; or many among the recent ones), doubles the frame stride, so that every
node computes the same frames (:class:`~ibvs_common.core.frame_grid.FrameGrid`); when none is
skipped for a while it tries half the stride again (judged from ``stride_down_lead_s`` after
the decision, when the nodes compute its frames; the old stride's frames before then say
nothing of the try), on probation for ``stride_try_s``: the first skipped frame of the try
within it ends it
(``stride_try_skipped``), or its first frame completed later than the frames before it and
than the try's first frame by half a frame period or more (``stride_try_lag_periods``: the
graph is falling behind; on a
slow computer a try that waits for a skipped frame has piled up a backlog of several frames,
and forces hundreds of ms old), and the next try waits twice as long. A lone
skipped frame (a late delivery, a busy moment of the computer) costs that frame; a doubled
stride costs half of them for seconds, so it does not double the stride. Nor do the frames of
a new camera skipped at a handover before its first complete one (``stride_handover_grace_s``).
:class:`SupervisorGrids` is the supervisor's view of which frames to expect. Times are frame
stamps (s, ROS clock).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ibvs_common.core.frame_grid import FrameGrid, MAX_STRIDE
from ibvs_common.core.params import param


@dataclass(frozen=True)
class GovernorConfig:
    """When the frame stride goes up and down."""

    max_frame_stride: int = param(
        4, 'frames: the largest stride the governor uses (4: 12.5 Hz of a 50 Hz camera), '
        '1 = every frame always', 1, MAX_STRIDE)
    flow_shed_stride: int = param(
        2, 'frames of the grid: the first step of an overload computes the translational '
        'flows on every this many grid frames only and holds each flow over the frames between '
        '(the control rate stays; ~30 % of the perception work per frame saved); the next '
        'steps double the frame stride; 1 = off (an overload doubles the stride at once)',
        1, MAX_STRIDE)
    stride_window_frames: int = param(
        10, 'frames: the recent frames of the mode\'s camera the governor looks at', 2, 100)
    stride_up_skipped: int = param(
        4, 'frames: this many skipped among the recent ones double the stride (an overload '
        'that lasts)', 1, 100)
    stride_up_in_a_row: int = param(
        3, 'frames: this many skipped in a row double the stride at once (a graph that fell '
        'behind)', 1, 100)
    stride_try_skipped: int = param(
        1, 'frames: this many skipped while a smaller stride is on trial end the trial at once '
        '(back to the stride that held): a trial that does not fit must not last until the '
        'overload rules see it, the graph falls behind meanwhile', 1, 100)
    stride_try_lag_periods: float = param(
        0.5, 'frame periods (of the stride on trial): a frame of the try completed this much '
        'later after its stamp (ROS clock) than the median of the frames before the try and '
        "than the try's first frame ends the try: the graph is falling behind (a backlog "
        'grows frame after frame; a constant extra lag of the busier stride does not); 0 = '
        'off (only skipped frames end a try)', 0.0)
    stride_try_s: float = param(
        0.5, 's (frame stamps): the probation of a try of a smaller stride, from its lead on: '
        'its first skipped or lagging frame within it ends the try (a stride that does not '
        'fit falls behind within a few frames); then the overload rules judge it, which a '
        'sporadic skip does not trip (a probation as long as the hold, up to 16 s, ended '
        'tries that held on their first sporadic skip)', 0.0)
    stride_down_hold_s: float = param(
        2.0, 's (frame stamps): no frame skipped for this long at a stride: try half of it '
        '(after a try that failed, twice as long each time, up to stride_down_hold_max_s)',
        0.0)
    stride_down_hold_max_s: float = param(
        16.0, 's (frame stamps): the longest wait before trying a smaller stride', 0.0)
    stride_handover_grace_s: float = param(
        0.2, "s (frame stamps): after the mode's camera changes (WINDOW -> CROSSING), its "
        'frames skipped before its first complete one, within this long, do not count: the '
        "new camera's products start (the floor flow's first pair, the pad's whole-image "
        'search); 0 = off', 0.0)
    stride_down_lead_s: float = param(
        0.1, 's (frame stamps): a smaller stride is expected only from this long after its '
        'decision (the perception nodes learn it from the frame status first), and its try is '
        'judged from then on', 0.0)

    def __post_init__(self) -> None:
        """Raise ValueError for thresholds that cannot work together."""
        for name in ('stride_up_skipped', 'stride_up_in_a_row', 'stride_try_skipped'):
            if getattr(self, name) > self.stride_window_frames:
                raise ValueError(f'{name} must be <= stride_window_frames, got '
                                 f'{getattr(self, name)} > {self.stride_window_frames}')
        if self.stride_down_hold_max_s < self.stride_down_hold_s:
            raise ValueError('stride_down_hold_max_s must be >= stride_down_hold_s')


class Level(NamedTuple):
    """One step of the governor: the frame stride and the flows' stride within its grid."""

    stride: int
    flow_stride: int = 1


def ladder(config: GovernorConfig) -> tuple[Level, ...]:
    """Return the governor's steps, cheapest loss first (module doc).

    Every frame; then, unless ``flow_shed_stride`` is 1, every frame with the flows on every
    ``flow_shed_stride``-th one; then strides 2, 4, ... up to ``max_frame_stride``.
    """
    levels = [Level(1)]
    if config.flow_shed_stride > 1:
        levels.append(Level(1, config.flow_shed_stride))
    stride = 2
    while stride <= config.max_frame_stride:
        levels.append(Level(stride))
        stride *= 2
    return tuple(levels)


class RateGovernor:
    """Choose the step (frame stride, flow stride) from which frames were skipped."""

    def __init__(self, config: GovernorConfig) -> None:
        self.config = config
        self.levels = ladder(config)
        self.level = 0                  # index in self.levels
        self.changes = 0
        self.reason = ''                # why the stride last changed, for the log
        self._recent: deque[bool] = deque(maxlen=config.stride_window_frames)
        self._t_change: float | None = None
        self._hold_s = config.stride_down_hold_s
        self._probing = False           # a try of a smaller stride on probation
        self._trying = False            # the last change was a try, within its hold
        self._lags: deque[float] = deque(maxlen=config.stride_window_frames)
        self._lag_before: float | None = None   # median lag of the frames before the try
        self._lag_first: float | None = None    # lag of the try's first complete frame
        self._grace_until = float('-inf')       # handover: skips before then may not count
        self._try_from = float('-inf')  # the first stamp a try of a smaller stride is judged on
        self._camera: object = None     # the camera of the frames seen last (a handover)

    @property
    def stride(self) -> int:
        """Return the frame stride of the current step (1: every camera frame)."""
        return self.levels[self.level].stride

    @property
    def flow_stride(self) -> int:
        """Return the flows' stride within the frame grid of the current step (1: each)."""
        return self.levels[self.level].flow_stride

    @property
    def counts_lone_skips(self) -> bool:
        """Whether a lone frame a node skipped for a newer one should count (see below).

        At every frame, when the next step only sheds the flows: a node that supersedes one
        image now and then (a third of a core: a third of the frames lost one by one, never
        three in a row) is short of CPU, and shedding costs the flight nothing measurable,
        where doubling the stride halves every product. Above it a lone skip costs that frame
        only, as before.
        """
        return self.level == 0 and len(self.levels) > 1 and self.levels[1].flow_stride > 1

    def observe(self, t: float, complete: bool, lag_s: float | None = None,
                period_s: float | None = None, camera: object = None) -> Level | None:
        """Take one frame of the current grid (stamp t); return the new step if it changed.

        ``lag_s``: for a complete frame, the time from its stamp to its completion (s, ROS
        clock: camera delivery and the graph's processing); ``period_s``: the camera's frame
        period (s). Without them only skipped frames end a try. ``camera``: the camera the
        frame is of (the mode's); a frame of another camera than the last one is a
        :meth:`handover` at its stamp.
        """
        cfg = self.config
        if camera is not None and camera != self._camera:
            if self._camera is not None:
                self.handover(t)        # the mode's camera changed
            self._camera = camera
        if self._t_change is None:
            self._t_change = t
        if self._probing and t < self._try_from:
            return None     # a frame of the old stride: the try has not started (its lead)
        if complete:
            self._grace_until = float('-inf')   # the new camera's first complete frame
        elif t < self._grace_until:
            return None     # the new camera's products are starting (handover)
        self._recent.append(bool(complete))
        skipped = sum(1 for ok in self._recent if not ok)
        lagging = self._probing and self._lagging(lag_s, period_s)
        if self._probing and (skipped >= cfg.stride_try_skipped or lagging):
            self._hold_s = min(2.0 * self._hold_s, cfg.stride_down_hold_max_s)
            self.reason = 'the try fell behind' if lagging else 'frames were skipped'
            return self._change(t, self.level + 1, probing=False)
        if self._overloaded(skipped) and self.level + 1 < len(self.levels):
            if self._trying:        # the smaller stride did not hold: wait longer next time
                self._hold_s = min(2.0 * self._hold_s, cfg.stride_down_hold_max_s)
            self.reason = 'frames were skipped'
            return self._change(t, self.level + 1, probing=False)
        if self._probing and t - self._try_from >= cfg.stride_try_s:
            self._probing = False   # probation passed: the overload rules judge the try now
        if self._trying and t - self._t_change >= self._hold_s:
            self._trying = False    # the try held: the next one waits the shortest time
            self._hold_s = cfg.stride_down_hold_s
        if complete and lag_s is not None and not self._probing:
            self._lags.append(float(lag_s))
        if self.level > 0 and skipped == 0 and t - self._t_change >= self._hold_s:
            self._lag_before = float(np.median(self._lags)) if self._lags else None
            self.reason = 'none skipped: a try'
            return self._change(t, self.level - 1, probing=True)
        return None

    def handover(self, t: float) -> None:
        """Note that the mode's camera changed at stamp t (skips wait for its first frame).

        For ``stride_handover_grace_s`` the new camera's skipped frames do not count until one
        completes (at a handover on a third of a core, the floor flow's first frames missed
        their deadline and the stride doubled to 4 for the rest of the flight).
        """
        self._recent.clear()
        self._grace_until = t + self.config.stride_handover_grace_s

    def _lagging(self, lag_s: float | None, period_s: float | None) -> bool:
        """Whether a frame of the try completed later than those before it (module doc).

        The reference is the later of the frames before the try (median) and the try's first
        complete frame: a backlog grows frame after frame, while a busier stride may hold a
        constant extra lag (a third of a core: 4 -> 2 tries ended at their second frame, and
        the graph kept 12.5 Hz where it holds 25).
        """
        cfg = self.config
        if lag_s is None or period_s is None or self._lag_before is None \
                or cfg.stride_try_lag_periods <= 0.0:
            return False
        if self._lag_first is None:
            self._lag_first = float(lag_s)
            return False
        ref = max(self._lag_before, self._lag_first)
        return lag_s - ref >= cfg.stride_try_lag_periods * self.stride * period_s

    def _overloaded(self, skipped: int) -> bool:
        """Whether the recent frames say the graph cannot hold this stride."""
        cfg = self.config
        in_a_row = 0
        for ok in reversed(self._recent):
            if ok:
                break
            in_a_row += 1
        return skipped >= cfg.stride_up_skipped or in_a_row >= cfg.stride_up_in_a_row

    def _change(self, t: float, level: int, probing: bool) -> Level:
        level = min(max(int(level), 0), len(self.levels) - 1)
        self.level, self._t_change, self._probing, self._trying = level, t, probing, probing
        self._lag_first = None
        self._try_from = t + self.config.stride_down_lead_s if probing else float('-inf')
        self._recent.clear()
        self._lags.clear()
        self.changes += 1
        return self.levels[level]


def _after_lead(ref_ns: int, lead_ns: int, step_ns: int) -> int:
    """Return the first frame ``k step_ns`` after ``ref_ns`` at least ``lead_ns`` later."""
    return int(ref_ns) + -(-int(lead_ns) // int(step_ns)) * int(step_ns)


class SupervisorGrids:
    """The frames of each camera the supervisor expects, and those its flows are computed on.

    The frame grid: a larger stride is expected at once (the nodes just stop computing frames
    the supervisor no longer waits for); a smaller one only ``lead_ns`` after the decision,
    once the nodes have it. The flow grid (the optical-flow nodes compute only its frames):
    the frame grid itself, or, while the governor sheds the flows (``flow_stride`` > 1),
    every ``flow_stride``-th frame of it, starting at the grid frame after the decision (a
    frame between two of its frames holds the flow of the one before: :meth:`flow_source_ns`).
    It changes only when its own stride does, with the same lead for a smaller one; when the
    frame stride grows to the flow grid's, the frame grid takes the flow grid's frames, so
    that no frame is left with a flow one frame older.
    """

    def __init__(self, periods_ns: dict) -> None:
        self._grid = {cam: FrameGrid(p) for cam, p in periods_ns.items()}
        self._flow = dict(self._grid)
        self._before: dict = {}         # camera -> (grid until from_ns, from_ns)
        self._flow_before: dict = {}    # camera -> (flow grid until from_ns, from_ns)

    def stride(self, camera) -> int:
        """Return the camera's current stride."""
        return self._grid[camera].stride

    def flow_stride(self, camera) -> int:
        """Return the flows' stride within the camera's frame grid (1: a flow every frame)."""
        return self._flow[camera].stride // self._grid[camera].stride

    def period_ns(self, camera) -> int:
        """Return the camera's frame period (ns)."""
        return self._grid[camera].period_ns

    def ref_ns(self, camera) -> int:
        """Return the stamp of the camera's reference frame (a frame on its grid)."""
        return self._grid[camera].ref_ns

    def flow_grid(self, camera) -> FrameGrid:
        """Return the camera's flow grid (its stride in camera frames and reference frame)."""
        return self._flow[camera]

    def on_grid(self, camera, stamp_ns: int) -> bool:
        """Whether the supervisor expects the frame of ``stamp_ns`` of ``camera``."""
        before = self._before.get(camera)
        if before is not None and stamp_ns < before[1]:
            return before[0].on_grid(stamp_ns)
        return self._grid[camera].on_grid(stamp_ns)

    def flow_source_ns(self, camera, stamp_ns: int) -> int:
        """Return the stamp of the flow frame a frame of ``stamp_ns`` takes its flows from.

        The frame itself when it is on the flow grid, else the newest flow-grid frame before
        it (a nominal stamp: a camera's stamps jitter, match it within half a period).
        """
        before = self._flow_before.get(camera)
        grid = before[0] if before is not None and stamp_ns < before[1] else \
            self._flow[camera]
        return int(stamp_ns) - (grid.index(stamp_ns) % grid.stride) * grid.period_ns

    def set_stride(self, camera, stride: int, ref_ns: int, lead_ns: int,
                   flow_stride: int = 1, first_frame: bool = False) -> None:
        """Use ``stride`` (and flows on every ``flow_stride``-th frame of it) from ``ref_ns`` on.

        A smaller stride's reference is its first frame at least ``lead_ns`` after ``ref_ns``
        (:meth:`ref_ns`, published on ibvs/frame_grid): the perception nodes keep the old grid
        until that frame too, instead of computing frames the supervisor does not expect yet
        (on a slow computer they cost the try its margin). The same holds for the flow grid.
        Shed flows start at the grid frame after ``ref_ns`` (a decision on a frame already
        evaluated), or at ``ref_ns`` itself with ``first_frame`` (the mode's camera changed:
        the new camera's first frame has no flow frame before it to hold).
        """
        old, old_flow = self._grid[camera], self._flow[camera]
        period = old.period_ns
        if stride != old.stride:
            self._before.pop(camera, None)
            if stride < old.stride:
                ref_ns_grid = _after_lead(ref_ns, lead_ns, int(stride) * period)
                self._before[camera] = (old, ref_ns_grid)
            elif stride == old_flow.stride:     # the frames the flows were computed on
                ref_ns_grid = self.flow_source_ns(camera, ref_ns)
            else:
                ref_ns_grid = int(ref_ns)
            self._grid[camera] = old.with_stride(stride, ref_ns_grid)
        flow_every = int(stride) * int(flow_stride)
        if flow_every == old_flow.stride:
            return
        self._flow_before.pop(camera, None)
        if flow_every < old_flow.stride:
            flow_ref = _after_lead(ref_ns, lead_ns, flow_every * period)
            self._flow_before[camera] = (old_flow, flow_ref)
        elif flow_stride > 1:
            flow_ref = int(ref_ns) + (0 if first_frame else int(stride) * period)
        else:
            flow_ref = self._grid[camera].ref_ns
        self._flow[camera] = old_flow.with_stride(flow_every, flow_ref)

    def reset(self) -> None:
        """Every frame again (the clock stepped back: old references mean nothing)."""
        self._grid = {cam: FrameGrid(g.period_ns) for cam, g in self._grid.items()}
        self._flow = dict(self._grid)
        self._before.clear()
        self._flow_before.clear()


class SupersededFrames:
    """The grid images the perception nodes reported skipping for a newer one (latest only).

    A grid frame that no product came for is the computer's doing only when a node had its
    image and skipped it (``ibvs/frames_superseded``); a frame the camera never delivered (a
    dropout, a camera below its rate) is not, and must not make the governor halve the control
    rate (a 0.2 s dropout of the floor camera held stride 2 for 2 s). Stamps are integer ns on
    the ROS clock; a frame matches a report within ``tolerance_ns`` (camera stamps jitter).
    """

    def __init__(self, keep: int = 64) -> None:
        self._stamps: dict = {}         # camera -> deque of reported stamps (ns), newest last
        self._keep = int(keep)

    def note(self, camera, stamp_ns: int) -> None:
        """Take one report: ``camera``'s image of ``stamp_ns`` was skipped by a node."""
        self._stamps.setdefault(camera, deque(maxlen=self._keep)).append(int(stamp_ns))

    def reported(self, camera, stamp_ns: int, tolerance_ns: int) -> bool:
        """Whether a node skipped ``camera``'s image of ``stamp_ns`` (within the tolerance)."""
        return any(abs(t - int(stamp_ns)) <= tolerance_ns for t in self._stamps.get(camera, ()))

    def count_in_gap(self, camera, base_ns: int, step_ns: int, n: int,
                     tolerance_ns: int) -> int:
        """Return how many of the frames ``base_ns + k step_ns`` (k = 1 ... n) were reported."""
        found = set()
        for t in self._stamps.get(camera, ()):
            k = (t - int(base_ns) + step_ns // 2) // step_ns
            if 1 <= k <= n and abs(t - (int(base_ns) + k * step_ns)) <= tolerance_ns:
                found.add(k)
        return len(found)

    def clear(self) -> None:
        """Forget every report (the clock stepped back: old stamps mean nothing)."""
        self._stamps.clear()
