"""The flight path's timing model (docs/design.md, "Time"): one layer, ROS-free.

Clocks
    Every stamp is on the ROS clock: system time on a vehicle (camera drivers stamp images in
    system time, the MAVLink bridge maps the autopilot's IMU samples onto it with TIMESYNC),
    sim time in the simulator. Stamps are integer nanoseconds here. A lockstep simulator is
    only a ROS clock that stands still while the graph computes: nothing below knows about it.

Frames and the inputs a mode needs (:data:`ibvs_common.core.modes.MODE_INPUTS`)
    A frame is one image of one camera, named by its stamp. Its products are the window
    detection and the wall flow (front camera), the pad landmarks and the floor flow (down
    camera). Each mode is evaluated on the frames of one camera and names the products it
    needs: WINDOW needs the window and the front flow, CROSSING the down flow, LANDING the
    pad and the down flow; IDLE waits for the window (its cue to start); SHUTDOWN and
    FAILSAFE need nothing. The IMU is needed by every flying mode but never waited for.

Deadlines (:class:`FrameAssembler`)
    Nodes compute on arrival. A frame opens when its first product arrives and is released
    as soon as the products its mode needs are in, or when the ROS clock reaches its deadline,
    ``frame_deadline_s`` after it opened (never before ``stamp + frame_deadline_s``),
    whichever comes first; a frame whose missing product can no longer come (a newer product
    of that kind arrived: products of a kind come in stamp order) is released at once. A
    camera delivers its images 20-40 ms after their stamp, and a
    busy computer computes them later still: the wait counts from the first product, so it
    holds whatever the delivery latency. A frame released without every product it needs is
    *skipped*: no evaluation, no force (the products that do come later are dropped, never
    applied to a frame they missed); the supervisor fails safe when frames are skipped for
    long. A product the mode does not need never delays a frame. Frames leave in stamp order.
    In lockstep the ROS clock does not move while the graph computes, so a deadline cannot
    expire before an input that is coming, and runs repeat.

Camera handover
    A switch to a mode of the other camera (WINDOW -> CROSSING: front to down) is decided on
    a frame of the old camera; the supervisor's status of that frame names its camera. The
    controller flies the new mode at that stamp only with the new camera's products of the
    same stamp (synchronised cameras, as in the simulator by default). Cameras that are not
    synchronised have none: the frame is *handed over* (released when the new camera's next
    product passes it; not answered, not counted as skipped) and the new camera's next frame
    is the first the new mode flies.

Attitude at a stamp (:class:`ibvs_common.core.attitude_buffer.AttitudeBuffer`)
    Interpolated on SO(3) between the IMU samples around the stamp, or propagated from the
    newest sample with its body rate for at most ``max_extrapolation_s``: a frame never waits
    for a later IMU sample.

Clock steps (:mod:`ibvs_common.core.clock_step`)
    The products of one kind come from one publisher, in stamp order. When a kind's stamps go
    back by more than ``MAX_BACKSTEP_S``, the ROS clock stepped back: the assembler drops
    its frames and products (``clock_steps`` counts it) and starts again from that product,
    instead of refusing every frame up to the newest one already released, i.e. for the
    length of the step. A reset (also one by a node that saw its clock step) restarts every
    kind's watch, so the other kinds' first products after the step are no second step. One
    still on its way from before the step may open a frame or two more; the go-back of its
    kind after it then clears them (and the frame at hand) in turn.
"""
from __future__ import annotations

import bisect
from collections import deque, OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ibvs_common.core.clock_step import BackstepWatch
from ibvs_common.core.modes import InputKind
from ibvs_common.core.stamps import s_to_ns


EVALUATION_ORDER = (InputKind.WINDOW, InputKind.PAD, InputKind.FLOW_FRONT, InputKind.FLOW_DOWN)


@dataclass(frozen=True)
class Frame:
    """A released frame: its stamp, the tag it was opened with and the products it got.

    ``inputs`` holds the needed products that arrived with exactly this stamp, by kind;
    ``extras`` the other products of this stamp that had arrived by the release (a node that
    uses them at all uses them only after the frame: see :class:`FrameAssembler`);
    ``missing`` the needed ones that had not arrived at release (``expired``: released by its
    deadline; ``passed``: released before it because a newer product of a missing kind came,
    so this frame's never will); a frame with a missing product is skipped.
    """

    stamp_ns: int
    tag: Any
    inputs: dict
    missing: tuple = ()
    expired: bool = False
    extras: dict = field(default_factory=dict)
    passed: bool = False

    def get(self, kind: InputKind) -> Any:
        """Return the value of a product of this frame, or None."""
        return self.inputs.get(kind)

    @property
    def complete(self) -> bool:
        """Whether every product the frame's mode needs came by its deadline."""
        return not self.missing


@dataclass
class _Pending:
    stamp_ns: int
    tag: Any
    deadline_ns: int


class FrameAssembler:
    """Products by stamp, frames opened by the node, released by need or deadline.

    ``needed(frame_tag)`` gives the set of products a frame waits for (the node decides: the
    supervisor from its current mode and the frame's camera, the controller from the mode the
    supervisor reported for the frame). Inputs are kept per kind for the last ``depth``
    stamps; a frame can be opened before or after its products arrive.

    A released frame's ``inputs`` are only its needed products: whether a product the mode
    does not wait for arrived before or after the release depends on scheduling, so it goes
    to ``extras``, which a node may apply only after the frame (the supervisor does, as if it
    had arrived late). The evaluation of a frame then depends on its needed products alone,
    on a vehicle as in a lockstep simulator.
    """

    def __init__(self, deadline_s: float, needed: Callable[[Any], frozenset],
                 depth: int = 16) -> None:
        if not (np.isfinite(deadline_s) and deadline_s > 0.0) or int(depth) < 1:
            raise ValueError(f'need deadline_s > 0 and depth >= 1, got {deadline_s}, {depth}')
        self.deadline_ns = s_to_ns(deadline_s)
        self.needed = needed
        self.depth = int(depth)
        self.released_through_ns: int | None = None
        self.expired = 0                      # frames released by their deadline
        self.passed = 0                       # released early: a missing product was passed
        self._newest_ns: dict[InputKind, int] = {}     # kind -> its newest product's stamp
        self._skipped: deque[int] = deque(maxlen=self.depth)   # stamps of frames expired
        self._inputs: dict[InputKind, OrderedDict] = {k: OrderedDict() for k in InputKind}
        self._pending: list[_Pending] = []    # in stamp order
        self._backsteps = {k: BackstepWatch() for k in InputKind}

    @property
    def clock_steps(self) -> int:
        """Resets after a product kind's stamps went back (not those :meth:`reset` was told)."""
        return sum(watch.steps for watch in self._backsteps.values())

    def reset(self) -> None:
        """Forget every frame and product (the ROS clock stepped back)."""
        self.released_through_ns = None
        self._pending.clear()
        self._skipped.clear()
        self._newest_ns.clear()
        for store in self._inputs.values():
            store.clear()
        for watch in self._backsteps.values():
            watch.forget()

    # --- inputs ------------------------------------------------------------------------
    def add_input(self, kind: InputKind, stamp_ns: int, value: Any) -> bool:
        """Keep one product; False if this kind already has a value at this stamp.

        A product stamped more than ``MAX_BACKSTEP_S`` before the newest of its kind first
        resets the assembler (module doc, "Clock steps").
        """
        store = self._inputs[kind]
        stamp_ns = int(stamp_ns)
        if self._backsteps[kind].observe(stamp_ns):
            self.reset()
            self._backsteps[kind].observe(stamp_ns)
        if stamp_ns in store:
            return False
        self._newest_ns[kind] = max(stamp_ns, self._newest_ns.get(kind, stamp_ns))
        store[stamp_ns] = value
        if len(store) > self.depth:
            store.popitem(last=False)
        return True

    def has(self, kind: InputKind, stamp_ns: int) -> bool:
        """Whether a product of this kind arrived with exactly this stamp."""
        return int(stamp_ns) in self._inputs[kind]

    def latest_before(self, kind: InputKind, stamp_ns: int, max_age_ns: int
                      ) -> tuple[int, Any] | None:
        """Return (stamp, value) of the newest product strictly older than the stamp.

        None if there is none within ``max_age_ns``.
        """
        best = None
        for s, v in self._inputs[kind].items():
            if s < stamp_ns and stamp_ns - s <= max_age_ns and (best is None or s > best[0]):
                best = (s, v)
        return best

    # --- frames ------------------------------------------------------------------------
    @property
    def has_pending(self) -> bool:
        """Whether any frame is open (if not, :meth:`release` has nothing to do)."""
        return bool(self._pending)

    def is_pending(self, stamp_ns: int) -> bool:
        """Whether a frame with this stamp is open and not yet released."""
        return any(p.stamp_ns == int(stamp_ns) for p in self._pending)

    def was_skipped(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` was released without a product it needed."""
        return int(stamp_ns) in self._skipped

    def open(self, stamp_ns: int, tag: Any, now_ns: int) -> bool:
        """Open the frame of ``stamp_ns``; False if it is open, released, or older than one.

        Its deadline is ``frame_deadline_s`` from ``now_ns`` (its first product's arrival),
        and never before ``stamp + frame_deadline_s``.
        """
        stamp_ns = int(stamp_ns)
        if (self.released_through_ns is not None and stamp_ns <= self.released_through_ns) \
                or self.is_pending(stamp_ns):
            return False
        deadline_ns = max(int(now_ns), stamp_ns) + self.deadline_ns
        bisect.insort(self._pending, _Pending(stamp_ns, tag, deadline_ns),
                      key=lambda p: p.stamp_ns)
        return True

    def release(self, now_ns: int) -> list[Frame]:
        """Return, oldest first, the frames whose needed products are in or can no longer come.

        A missing product can no longer come when the frame's deadline passed, or when a newer
        product of its kind arrived (each kind comes from one publisher in stamp order: a
        camera that is not synchronised with the mode's, a product lost on the way). A frame
        never overtakes an older pending one.
        """
        out = []
        while self._pending:
            p = self._pending[0]
            needed = self.needed(p.tag)
            missing = tuple(k for k in EVALUATION_ORDER
                            if k in needed and not self.has(k, p.stamp_ns))
            expired = bool(missing) and int(now_ns) >= p.deadline_ns
            passed = bool(missing) and not expired and any(
                self._newest_ns.get(k, p.stamp_ns) > p.stamp_ns for k in missing)
            if missing and not (expired or passed):
                break
            self._pending.pop(0)
            self.released_through_ns = p.stamp_ns
            self.expired += int(expired)
            self.passed += int(passed)
            if missing:
                self._skipped.append(p.stamp_ns)
            present = {k: self._inputs[k][p.stamp_ns] for k in EVALUATION_ORDER
                       if p.stamp_ns in self._inputs[k]}
            out.append(Frame(p.stamp_ns, p.tag,
                             {k: v for k, v in present.items() if k in needed}, missing,
                             expired, {k: v for k, v in present.items() if k not in needed},
                             passed))
        return out

    def next_deadline_ns(self) -> int | None:
        """Deadline of the oldest pending frame (the next one that can expire), or None."""
        return self._pending[0].deadline_ns if self._pending else None
