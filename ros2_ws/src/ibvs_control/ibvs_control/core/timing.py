"""The flight path's timing model (docs/design.md, "Time"): one layer, ROS-free.

Clocks
    Every stamp is on the ROS clock: system time on a vehicle (camera drivers stamp images in
    system time, the MAVLink bridge maps the autopilot's IMU samples onto it with TIMESYNC),
    sim time in the simulator. Stamps are integer nanoseconds here. A lockstep simulator is
    only a ROS clock that stands still while the graph computes: nothing below knows about it.

Frames and the inputs a mode needs (:data:`MODE_INPUTS`)
    A frame is one image of one camera, named by its stamp. Its products are the window
    detection and the wall flow (front camera), the pad landmarks and the floor flow (down
    camera). Each mode is evaluated on the frames of one camera and names the products it
    needs: WINDOW needs the window and the front flow, CROSSING the down flow, LANDING the
    pad and the down flow; IDLE waits for the window (its cue to start); SHUTDOWN and
    FAILSAFE need nothing. The IMU is needed by every flying mode but never waited for.

Deadlines (:class:`FrameAssembler`)
    Nodes compute on arrival. A frame is released as soon as the products its mode needs are
    in, or when the ROS clock reaches ``stamp + deadline`` (``frame_deadline_s``), whichever
    comes first; then it is evaluated with what it has and a missing product counts as "not
    detected" (the supervisor's staleness timeouts turn a product missing for long into
    FAILSAFE). A product the mode does not need never delays a frame. Frames leave in stamp
    order. Onboard the deadline bounds the latency a late or dead input can add; in lockstep
    the ROS clock does not move while the graph computes, so a deadline cannot expire before
    an input that is coming, and runs repeat.

Attitude at a stamp (:class:`AttitudeBuffer`)
    Interpolated on SO(3) between the IMU samples around the stamp, or propagated from the
    newest sample with its body rate for at most ``max_extrapolation_s``: a frame never waits
    for a later IMU sample.
"""
from __future__ import annotations

import bisect
from collections import OrderedDict
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Callable

import numpy as np

from ibvs_control.core.frames import exp_so3, is_rotation, log_so3
from ibvs_control.core.modes import Mode

NS_PER_S = 1_000_000_000


def s_to_ns(t_s: float) -> int:
    """Seconds -> integer nanoseconds (rounded)."""
    return int(round(float(t_s) * NS_PER_S))


class Camera(str, Enum):
    """The two cameras whose frames the modes are evaluated on."""

    FRONT = 'front'
    DOWN = 'down'


class InputKind(Enum):
    """The products of one camera frame."""

    WINDOW = 'window'             # window/corners (front)
    PAD = 'pad'                   # pad/landmarks + pad/groups (down)
    FLOW_FRONT = 'flow_front'     # front_camera/translational_flow
    FLOW_DOWN = 'flow_down'       # down_camera/translational_flow


CAMERA_OF = {InputKind.WINDOW: Camera.FRONT, InputKind.FLOW_FRONT: Camera.FRONT,
             InputKind.PAD: Camera.DOWN, InputKind.FLOW_DOWN: Camera.DOWN}
EVALUATION_ORDER = (InputKind.WINDOW, InputKind.PAD, InputKind.FLOW_FRONT, InputKind.FLOW_DOWN)


@dataclass(frozen=True)
class ModeInputs:
    """The camera whose frames a mode is evaluated on and the products it waits for."""

    camera: Camera
    needed: frozenset


MODE_INPUTS = {
    Mode.IDLE: ModeInputs(Camera.FRONT, frozenset({InputKind.WINDOW})),
    Mode.WINDOW: ModeInputs(Camera.FRONT, frozenset({InputKind.WINDOW, InputKind.FLOW_FRONT})),
    Mode.CROSSING: ModeInputs(Camera.DOWN, frozenset({InputKind.FLOW_DOWN})),
    Mode.LANDING: ModeInputs(Camera.DOWN, frozenset({InputKind.PAD, InputKind.FLOW_DOWN})),
    Mode.SHUTDOWN: ModeInputs(Camera.DOWN, frozenset()),
    Mode.FAILSAFE: ModeInputs(Camera.DOWN, frozenset()),
}


@dataclass(frozen=True)
class Frame:
    """A released frame: its stamp, the tag it was opened with and the products it got.

    ``inputs`` holds the needed products that arrived with exactly this stamp, by kind;
    ``extras`` the other products of this stamp that had arrived by the release (a node that
    uses them at all uses them only after the frame: see :class:`FrameAssembler`);
    ``missing`` the needed ones that had not arrived at release (``expired``: released by its
    deadline).
    """

    stamp_ns: int
    tag: Any
    inputs: dict
    missing: tuple = ()
    expired: bool = False
    extras: dict = field(default_factory=dict)

    def get(self, kind: InputKind):
        """Return the value of a product of this frame, or None."""
        return self.inputs.get(kind)


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
        self._inputs: dict[InputKind, OrderedDict] = {k: OrderedDict() for k in InputKind}
        self._pending: list[_Pending] = []    # in stamp order

    # --- inputs ------------------------------------------------------------------------
    def add_input(self, kind: InputKind, stamp_ns: int, value) -> bool:
        """Keep one product; False if this kind already has a value at this stamp."""
        store = self._inputs[kind]
        stamp_ns = int(stamp_ns)
        if stamp_ns in store:
            return False
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
    def is_pending(self, stamp_ns: int) -> bool:
        """Whether a frame with this stamp is open and not yet released."""
        return any(p.stamp_ns == int(stamp_ns) for p in self._pending)

    def open(self, stamp_ns: int, tag, now_ns: int) -> bool:
        """Open the frame of ``stamp_ns``; False if it is open, released, or older than one."""
        stamp_ns = int(stamp_ns)
        if (self.released_through_ns is not None and stamp_ns <= self.released_through_ns) \
                or self.is_pending(stamp_ns):
            return False
        bisect.insort(self._pending, _Pending(stamp_ns, tag, stamp_ns + self.deadline_ns),
                      key=lambda p: p.stamp_ns)
        return True

    def release(self, now_ns: int) -> list[Frame]:
        """Return, oldest first, the frames whose needed products are in or deadline passed.

        A frame never overtakes an older pending one.
        """
        out = []
        while self._pending:
            p = self._pending[0]
            needed = self.needed(p.tag)
            missing = tuple(k for k in EVALUATION_ORDER
                            if k in needed and not self.has(k, p.stamp_ns))
            expired = bool(missing) and int(now_ns) >= p.deadline_ns
            if missing and not expired:
                break
            self._pending.pop(0)
            self.released_through_ns = p.stamp_ns
            self.expired += int(expired)
            present = {k: self._inputs[k][p.stamp_ns] for k in EVALUATION_ORDER
                       if p.stamp_ns in self._inputs[k]}
            out.append(Frame(p.stamp_ns, p.tag,
                             {k: v for k, v in present.items() if k in needed}, missing,
                             expired, {k: v for k, v in present.items() if k not in needed}))
        return out

    def next_deadline_ns(self) -> int | None:
        """Deadline of the oldest pending frame (the next one that can expire), or None."""
        return self._pending[0].deadline_ns if self._pending else None


@dataclass(frozen=True)
class AttitudeBufferConfig:
    """Sizes and tolerances of :class:`AttitudeBuffer` (seconds of the stamps' clock)."""

    history_s: float = 1.0              # samples older than newest - history_s are dropped
    max_extrapolation_s: float = 0.05   # propagation beyond the newest sample, at most
    max_interpolation_gap_s: float = 0.2  # two samples farther apart are not interpolated

    def __post_init__(self) -> None:
        for name in ('history_s', 'max_extrapolation_s', 'max_interpolation_gap_s'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')


#: spec of each AttitudeBufferConfig field as a ROS parameter, declared as ``imu_<field>``
#: (description with unit, inclusive range; ibvs_control.param_descriptors)
ATTITUDE_BUFFER_SPECS = {
    'history_s': ('s (IMU stamps, ROS clock), IMU attitudes kept, > 0', 0.0, None),
    'max_extrapolation_s': ('s (IMU stamps, ROS clock), the attitude is propagated with the '
                            'gyro at most this far beyond the newest sample, > 0', 0.0, None),
    'max_interpolation_gap_s': ('s (IMU stamps, ROS clock), two IMU samples farther apart are '
                                'not interpolated, > 0', 0.0, None),
}


@dataclass
class AttitudeBuffer:
    """Time-ordered IMU attitudes R_IB with interpolation or propagation to any stamp.

    Attitudes are the paper's R_IB (body FRD -> {I}); rates Omega are body FRD (rad/s), so
    that ``R_dot = R S(Omega)`` (paper eq:R). Between two samples the attitude is interpolated
    on SO(3) (geodesic: ``R_a exp(s log(R_a^T R_b))``); after the newest sample it is
    propagated with its rate, ``R_n exp(Omega_n dt)``, for at most ``max_extrapolation_s``.
    Stamps are seconds on the ROS clock (images and IMU share it).
    """

    config: AttitudeBufferConfig = field(default_factory=AttitudeBufferConfig)
    _stamps: list = field(default_factory=list)
    _R: list = field(default_factory=list)
    _omega: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_stamp(self) -> float | None:
        """Stamp (s) of the newest sample, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_s: float, R_IB: np.ndarray, omega_B: np.ndarray) -> None:
        """Insert a sample; raises ValueError for non-finite values or a non-rotation."""
        R_IB = np.asarray(R_IB, dtype=float)
        omega_B = np.asarray(omega_B, dtype=float).reshape(3)
        if not np.isfinite(stamp_s) or not np.all(np.isfinite(omega_B)) \
                or not is_rotation(R_IB, tol=1e-4):
            raise ValueError('IMU sample with a non-finite stamp/rate or an invalid attitude')
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i > 0 and self._stamps[i - 1] == stamp_s:
            self._R[i - 1], self._omega[i - 1] = R_IB, omega_B
            return
        self._stamps.insert(i, float(stamp_s))
        self._R.insert(i, R_IB)
        self._omega.insert(i, omega_B)
        cutoff = self._stamps[-1] - self.config.history_s
        drop = bisect.bisect_left(self._stamps, cutoff)
        if drop > 0:
            del self._stamps[:drop], self._R[:drop], self._omega[:drop]

    def attitude_at(self, stamp_s: float) -> np.ndarray | None:
        """R_IB at ``stamp_s`` or None when the buffer does not cover it."""
        if not self._stamps or not np.isfinite(stamp_s):
            return None
        cfg = self.config
        i = bisect.bisect_right(self._stamps, stamp_s)
        if i == len(self._stamps):
            dt = stamp_s - self._stamps[-1]
            if dt > cfg.max_extrapolation_s:
                return None
            return self._R[-1] @ exp_so3(self._omega[-1] * dt)
        if i == 0:
            return None
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        if t1 - t0 > cfg.max_interpolation_gap_s:
            return None
        s = (stamp_s - t0) / (t1 - t0)
        R0 = self._R[i - 1]
        return R0 @ exp_so3(s * log_so3(R0.T @ self._R[i]))

    def gyro_rotation(self, t0: float, t1: float) -> np.ndarray | None:
        """Body rotation dR from t0 to t1 integrated from the buffered rates (R(t1) = R(t0) dR).

        Rates are trapezoid-averaged between consecutive samples and held after the newest one
        (for at most ``max_extrapolation_s``); None when the buffer does not cover [t0, t1].
        """
        cfg = self.config
        if not self._stamps or not (np.isfinite(t0) and np.isfinite(t1)) or t1 < t0 \
                or t0 < self._stamps[0] or t1 - self._stamps[-1] > cfg.max_extrapolation_s:
            return None
        dR = np.eye(3)
        n = len(self._stamps)
        for k in range(bisect.bisect_right(self._stamps, t0) - 1, n):
            a = max(self._stamps[k], t0)
            b = min(self._stamps[k + 1], t1) if k + 1 < n else t1
            if b <= a:
                if a >= t1:
                    break
                continue
            if k + 1 < n and self._stamps[k + 1] - self._stamps[k] > cfg.max_interpolation_gap_s:
                return None
            omega = self._omega[k] if k + 1 == n else 0.5 * (self._omega[k] + self._omega[k + 1])
            dR = dR @ exp_so3(omega * (b - a))
        return dR
