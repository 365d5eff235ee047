"""The flight path's timing model, ROS-free: frames, the products a mode needs, deadlines.

Stamps are integer nanoseconds on the ROS clock (system time onboard, sim time in the sim).
A frame is one image of one camera, named by its stamp; :class:`FrameAssembler` keeps each
kind of product by stamp and releases a frame when the products its mode needs
(:data:`ibvs_common.core.modes.MODE_INPUTS`) are in, when a newer product of a missing kind
shows this frame's will never come, or at its deadline (``frame_deadline_s`` after its first
product). A frame released without a needed product is skipped, never flown. A product
stamped well before the newest of its kind means the clock stepped back: everything is
dropped and the assembler starts again. A frame may take a product of another stamp where
the node says so at its opening (``held``: while the rate governor sheds the flows, a frame
between two flow frames takes the flow of the one before it: a product at its declared
rate, never an older one). The rules, and why (late cameras, a busy computer,
camera handover, clock steps): docs/design.md "Time".
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
    so this frame's never will); a frame with a missing product is skipped. ``held``: kind ->
    the stamp of the product taken from another frame (see :meth:`FrameAssembler.open`).
    """

    stamp_ns: int
    tag: Any
    inputs: dict
    missing: tuple = ()
    expired: bool = False
    extras: dict = field(default_factory=dict)
    passed: bool = False
    held: dict = field(default_factory=dict)

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
    held: dict = field(default_factory=dict)   # kind -> (lo_ns, hi_ns) of its product


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

    def open(self, stamp_ns: int, tag: Any, now_ns: int, held: dict | None = None) -> bool:
        """Open the frame of ``stamp_ns``; False if it is open, released, or older than one.

        Its deadline is ``frame_deadline_s`` from ``now_ns`` (its first product's arrival),
        and never before ``stamp + frame_deadline_s``. ``held``: kind -> (lo_ns, hi_ns): the
        frame takes that product from the newest stamp within lo ... hi (<= its own) instead
        of its own stamp; it is missing until one arrives, and can no longer come once a
        product of the kind newer than hi_ns did.
        """
        stamp_ns = int(stamp_ns)
        if (self.released_through_ns is not None and stamp_ns <= self.released_through_ns) \
                or self.is_pending(stamp_ns):
            return False
        deadline_ns = max(int(now_ns), stamp_ns) + self.deadline_ns
        held = {k: (int(lo), int(hi)) for k, (lo, hi) in (held or {}).items()}
        bisect.insort(self._pending, _Pending(stamp_ns, tag, deadline_ns, held),
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
            sources = {k: self._source(k, p) for k in needed}
            missing = tuple(k for k in EVALUATION_ORDER
                            if k in needed and sources[k] is None)
            expired = bool(missing) and int(now_ns) >= p.deadline_ns
            passed = bool(missing) and not expired and any(
                self._newest_ns.get(k, p.stamp_ns) > p.held.get(k, (0, p.stamp_ns))[1]
                for k in missing)
            if missing and not (expired or passed):
                break
            self._pending.pop(0)
            self.released_through_ns = p.stamp_ns
            self.expired += int(expired)
            self.passed += int(passed)
            if missing:
                self._skipped.append(p.stamp_ns)
            present = {k: self._inputs[k][p.stamp_ns] for k in EVALUATION_ORDER
                       if p.stamp_ns in self._inputs[k] and k not in p.held}
            inputs = {k: (self._inputs[k][sources[k]] if k in p.held else present[k])
                      for k in EVALUATION_ORDER if k in needed and sources[k] is not None}
            out.append(Frame(p.stamp_ns, p.tag, inputs, missing, expired,
                             {k: v for k, v in present.items() if k not in needed}, passed,
                             {k: sources[k] for k in p.held
                              if k in needed and sources[k] is not None}))
        return out

    def _source(self, kind: InputKind, p: _Pending) -> int | None:
        """Return the stamp of the product of ``kind`` frame ``p`` takes, or None (none yet)."""
        if kind not in p.held:
            return p.stamp_ns if p.stamp_ns in self._inputs[kind] else None
        lo, hi = p.held[kind]
        found = [s for s in self._inputs[kind] if lo <= s <= min(hi, p.stamp_ns)]
        return max(found) if found else None

    def next_deadline_ns(self) -> int | None:
        """Deadline of the oldest pending frame (the next one that can expire), or None."""
        return self._pending[0].deadline_ns if self._pending else None
