"""Per-image-stamp synchronisation of the force controller's inputs (ROS-free).

Every camera frame produces, with the frame's capture stamp, one ``window/corners`` (front
image), one ``pad/landmarks`` (down image), when valid the two translational flows, and the
supervisor's mode evaluated at that stamp (``ibvs/supervisor_status``). The force controller
must answer EVERY stamp exactly once (the sim's lockstep waits for the answer), and the
supervisor must evaluate every stamp on the same inputs whatever their arrival order, so
:class:`StampSynchronizer` gathers the inputs of one stamp and releases the bundle

- as soon as the ``required`` inputs (window and pad detections) are there, plus each
  ``optional`` input (flows, supervisor mode) that is *expected* (an optional input is
  expected from the start, until it has been missing for ``flow_patience`` released stamps in
  a row; one
  arriving, even late, makes it expected again. The flow nodes publish one message per image
  (all-NaN when there is no valid flow, :func:`is_no_flow`), so in a healthy graph every
  optional input comes at every stamp and none is ever skipped by a race; the patience only
  bounds the cost of a flow node that died or a lost link to a few timeouts, not one every
  frame, while one late flow under load does not make the next frames go without it);
- and, with ``wait_for_imu``, once the IMU samples reach the stamp (:meth:`note_imu`), so that
  the attitude "at or before the stamp" is the same whatever arrived first;
- or when ``timeout_s`` (wall clock) has passed since the first input of that stamp arrived.

Bundles leave in stamp order: releasing stamp S first releases every older pending stamp.
An input for a stamp already released (out of order, late) or a second input of the same kind
for a pending stamp (duplicate) is dropped and reported.

:class:`AttitudeHistory` keeps the recent IMU attitudes and returns the one at, or just
before, a stamp.
"""
from __future__ import annotations

from bisect import bisect_right
from collections import deque
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from ibvs_control.core.controller import (
    ControlOutput, FeatureSnapshot, IbvsController, Measurements)
from ibvs_control.core.frames import (
    e3, GRAVITY, MAP_FRAME, quat_from_rot, quat_ned_frd_to_enu_flu, rot_z, vec_map_to_I)
from ibvs_control.core.modes import Mode

NS_PER_S = 1_000_000_000


class InputKind(Enum):
    """The inputs of one frame."""

    WINDOW = 'window'
    PAD = 'pad'
    FLOW_FRONT = 'flow_front'
    FLOW_DOWN = 'flow_down'
    MODE = 'mode'                 # the supervisor's mode after evaluating this stamp


REQUIRED = (InputKind.WINDOW, InputKind.PAD)
FLOWS = (InputKind.FLOW_FRONT, InputKind.FLOW_DOWN)


@dataclass
class FrameBundle:
    """Inputs gathered for one image stamp (a missing input is absent from ``values``)."""

    stamp_ns: int
    first_arrival: float                 # monotonic s
    values: dict = field(default_factory=dict)   # InputKind -> value (None = "empty")
    timed_out: bool = False
    missing: tuple = ()                  # what it was released without ('imu' or kind values)

    def get(self, kind: InputKind):
        """Return the value of an input, or None if it did not come (or was empty)."""
        return self.values.get(kind)


class StampSynchronizer:
    """Gather per-stamp inputs; see the module docstring for the release rules."""

    def __init__(self, timeout_s: float, max_pending: int = 20, flow_patience: int = 3,
                 wait_for_imu: bool = False, required: tuple = REQUIRED,
                 optional: tuple = FLOWS) -> None:
        if not timeout_s > 0.0 or flow_patience < 1:
            raise ValueError(f'need timeout_s > 0 and flow_patience >= 1, got {timeout_s}, '
                             f'{flow_patience}')
        if set(required) & set(optional):
            raise ValueError(f'an input cannot be both required and optional: {required}, '
                             f'{optional}')
        self.required = tuple(required)
        self.optional = tuple(optional)
        self.timeout_s = timeout_s
        self.max_pending = max_pending
        self.flow_patience = flow_patience
        self.wait_for_imu = wait_for_imu
        self.imu_through_ns: int | None = None       # newest IMU stamp seen
        self.last_released_ns: int | None = None
        self.dropped = 0
        self._pending: dict[int, FrameBundle] = {}
        self._missing = {k: 0 for k in self.optional}   # released stamps without it in a row

    def _expected(self, kind: InputKind) -> bool:
        return self._missing[kind] < self.flow_patience

    def add(self, kind: InputKind, stamp_ns: int, value, now: float
            ) -> tuple[list[FrameBundle], str]:
        """Add one input; return (bundles released now, '' or why the input was dropped)."""
        stamp_ns = int(stamp_ns)
        if self.last_released_ns is not None and stamp_ns <= self.last_released_ns:
            if kind in self.optional:
                self._missing[kind] = 0          # it comes, just later: wait for it next time
            self.dropped += 1
            return [], (f'{kind.value} for stamp {stamp_ns} ns arrived after stamp '
                        f'{self.last_released_ns} ns was answered (out of order or late)')
        bundle = self._pending.get(stamp_ns)
        if bundle is None:
            bundle = self._pending[stamp_ns] = FrameBundle(stamp_ns, now)
        elif kind in bundle.values:
            self.dropped += 1
            return [], f'duplicate {kind.value} for stamp {stamp_ns} ns'
        bundle.values[kind] = value
        released = []
        if len(self._pending) > self.max_pending:   # a stuck stamp never blocks the rest
            released += self._release_up_to(min(self._pending), timed_out=True)
        if self._complete(bundle):
            released += self._release_up_to(stamp_ns, timed_out=False)
        return released, ''

    def note_imu(self, stamp_ns: int) -> list[FrameBundle]:
        """Note an IMU sample's stamp; return the bundles it completes (oldest first)."""
        stamp_ns = int(stamp_ns)
        if self.imu_through_ns is not None and stamp_ns <= self.imu_through_ns:
            return []
        self.imu_through_ns = stamp_ns
        done = [s for s, b in self._pending.items() if self._complete(b)]
        return self._release_up_to(max(done), timed_out=False) if done else []

    def newest_stamp_ns(self) -> int | None:
        """Newest stamp of any input seen (pending or released), or None."""
        stamps = list(self._pending) + ([self.last_released_ns]
                                        if self.last_released_ns is not None else [])
        return max(stamps) if stamps else None

    def poll(self, now: float) -> list[FrameBundle]:
        """Release the bundles whose timeout has expired (call from a wall-clock timer)."""
        expired = [s for s, b in self._pending.items()
                   if now - b.first_arrival >= self.timeout_s]
        if not expired:
            return []
        return self._release_up_to(max(expired), timed_out=True)

    def _complete(self, b: FrameBundle) -> bool:
        if self.wait_for_imu and (self.imu_through_ns is None
                                  or self.imu_through_ns < b.stamp_ns):
            return False
        return (all(k in b.values for k in self.required)
                and all(k in b.values for k in self.optional if self._expected(k)))

    def _missing_inputs(self, b: FrameBundle) -> tuple:
        missing = [k.value for k in self.required if k not in b.values]
        missing += [k.value for k in self.optional if self._expected(k) and k not in b.values]
        if self.wait_for_imu and (self.imu_through_ns is None
                                  or self.imu_through_ns < b.stamp_ns):
            missing.append('imu')
        return tuple(missing)

    def _release_up_to(self, stamp_ns: int, timed_out: bool) -> list[FrameBundle]:
        out = []
        for s in sorted(x for x in self._pending if x <= stamp_ns):
            b = self._pending.pop(s)
            b.missing = self._missing_inputs(b)
            b.timed_out = timed_out or bool(b.missing)
            out.append(b)
        for b in out:
            self.last_released_ns = b.stamp_ns
            for k in self.optional:
                self._missing[k] = 0 if k in b.values else self._missing[k] + 1
        return out


class ModeTracker:
    """The mode to fly for each frame.

    A frame flies the mode the supervisor reported for that very stamp (the MODE input of its
    bundle, ``ibvs/supervisor_status``), so that which frame first flies a new mode does not
    depend on message timing. A frame released without it (supervisor silent or late: the
    bundle timed out) flies the latest mode known from any status or ``ibvs/mode``.
    """

    def __init__(self, initial: Mode = Mode.IDLE) -> None:
        self.mode = initial
        self.frames_without_status = 0

    def note(self, mode: Mode) -> None:
        """Latest mode from ``ibvs/mode`` or from a status of any stamp."""
        self.mode = mode

    def mode_at(self, bundle: FrameBundle) -> Mode:
        """Return the mode to fly for ``bundle`` (and remember it as the latest)."""
        mode = bundle.get(InputKind.MODE)
        if mode is None:
            self.frames_without_status += 1
            return self.mode
        self.mode = mode
        return mode


class PadPairing:
    """Pair each ``pad/landmarks`` with the ``pad/groups`` message that follows it.

    The pad detector publishes both for every image, landmarks first; ``pad/groups`` has no
    stamp, so a pair is made only in that order and only when the counts agree (4 landmarks
    per group, 0 for none). Group names are never kept for a later landmarks message: that
    could label frame k's landmarks with frame k-1's groups at a group switch. A groups
    message without its landmarks is dropped (counted in ``unpaired``).
    """

    def __init__(self, landmarks_per_group: int = 4) -> None:
        self.landmarks_per_group = landmarks_per_group
        self.unpaired = 0
        self._landmarks: tuple | None = None     # (stamp, bearings or None)

    def add_landmarks(self, stamp, bearings: np.ndarray | None) -> None:
        """Hold a landmarks message (it replaces one whose groups never came)."""
        if self._landmarks is not None:
            self.unpaired += 1
        self._landmarks = (stamp, bearings)

    def drop_landmarks(self) -> None:
        """Forget the held landmarks (e.g. the message was refused)."""
        self._landmarks = None

    def add_groups(self, groups: tuple) -> tuple | None:
        """Return (stamp, bearings, groups) if these groups complete the held landmarks."""
        held, self._landmarks = self._landmarks, None
        if held is None:
            self.unpaired += 1
            return None
        stamp, bearings = held
        n = 0 if bearings is None else len(bearings)
        if n != self.landmarks_per_group * len(groups):
            self.unpaired += 1
            return None
        return stamp, bearings, tuple(groups)


class AttitudeHistory:
    """Recent IMU attitudes R_IB by stamp (ns); :meth:`at` picks the one at or before."""

    def __init__(self, horizon_ns: int) -> None:
        self.horizon_ns = int(horizon_ns)
        self._stamps: deque = deque()
        self._rots: deque = deque()

    def add(self, stamp_ns: int, R_IB: np.ndarray) -> bool:
        """Store an attitude; an older stamp than the newest is ignored (returns False)."""
        stamp_ns = int(stamp_ns)
        if self._stamps and stamp_ns < self._stamps[-1]:
            return False
        self._stamps.append(stamp_ns)
        self._rots.append(np.asarray(R_IB, dtype=float))
        while self._stamps and self._stamps[0] < stamp_ns - self.horizon_ns:
            self._stamps.popleft()
            self._rots.popleft()
        return True

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """R_IB at or just before stamp_ns; the oldest if all are newer; None if empty."""
        if not self._stamps:
            return None
        i = bisect_right(self._stamps, int(stamp_ns)) - 1
        return self._rots[max(i, 0)]

    def latest(self) -> np.ndarray | None:
        """Return the newest attitude, or None."""
        return self._rots[-1] if self._rots else None


BEARING_NORM_TOLERANCE = 0.05   # |b| of a unit bearing must be within 5 % of 1


def check_bearings(points: np.ndarray, expected: int | None = None
                   ) -> tuple[np.ndarray | None, str]:
    """Validate bearings (rows) from a polygon: return (unit bearings or None, error).

    An empty set is "not detected": (None, ''). A wrong count (``expected``), a non-finite
    value or a vector that is not unit within 5 % returns (None, reason).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        return None, ''
    if expected is not None and len(p) != expected:
        return None, f'{len(p)} bearings where {expected} were expected'
    if not np.all(np.isfinite(p)):
        return None, 'non-finite bearing'
    n = np.linalg.norm(p, axis=1)
    if np.any(np.abs(n - 1.0) > BEARING_NORM_TOLERANCE):
        return None, f'bearings are not unit vectors (norms {np.round(n, 3).tolist()})'
    return p / n[:, None], ''


def check_vector(v: np.ndarray) -> tuple[np.ndarray | None, str]:
    """Validate a 3-vector (a flow, a force): (vector or None, error)."""
    x = np.asarray(v, dtype=float)
    if x.shape != (3,) or not np.all(np.isfinite(x)):
        return None, f'non-finite vector {x.tolist()}'
    return x, ''


def is_no_flow(phi_map: np.ndarray) -> bool:
    """Return True for the "no valid flow at this stamp" message: all three components NaN.

    The optical_flow nodes publish one flow message per image, so that a consumer knows at
    each stamp whether a flow is coming (lockstep runs then do not depend on arrival order);
    an image without a valid estimate (first frame, too few inliers, no window, no attitude)
    gets this all-NaN vector.
    """
    x = np.asarray(phi_map, dtype=float)
    return x.shape == (3,) and bool(np.all(np.isnan(x)))


def check_flow(phi_map: np.ndarray, frame_id: str) -> tuple[np.ndarray | None, str]:
    """Validate a translational flow given in ``frame_id``: (phi in {I} (1/s) or None, error).

    Flows are published in ``map`` (ENU); any other frame or a partly non-finite value is
    refused (None and an error); the all-NaN "no flow at this stamp" (:func:`is_no_flow`) is
    None without an error.
    """
    if frame_id != MAP_FRAME:
        return None, f'frame {frame_id!r} is not {MAP_FRAME!r}'
    if is_no_flow(phi_map):
        return None, ''
    phi, err = check_vector(phi_map)
    return (None, err) if phi is None else (vec_map_to_I(phi), '')


def heading_quat_enu_flu(yaw_ned: float) -> np.ndarray:
    """Return the ibvs/heading_setpoint quaternion (w, x, y, z) for a NED yaw (rad).

    The yaw-only rotation R_Z(yaw) (body FRD in NED) expressed as the attitude of base_link
    in map (frames.quat_ned_frd_to_enu_flu).
    """
    return quat_ned_frd_to_enu_flu(quat_from_rot(rot_z(float(yaw_ned))))


def step_controller(controller: IbvsController, mode: Mode, bundle: FrameBundle,
                    R_IB: np.ndarray | None) -> tuple[ControlOutput | None, np.ndarray]:
    """Answer one frame: (controller output or None, force F in {I} (N)).

    The PAD input of the bundle is (landmark bearings or None, group names), as PadPairing
    gives it; a bare array (no group names) is accepted too.

    Without any IMU attitude yet the controller cannot derotate the bearings: the answer is
    the hover force m g e3 (level) and no output (no heading, no features). A non-finite
    controller force (a bug) is replaced by the hover force as well.
    """
    hover = controller.config.mass * GRAVITY * e3
    if R_IB is None:
        return None, hover
    pad, pad_groups = bundle.get(InputKind.PAD), None
    if isinstance(pad, tuple):
        pad, pad_groups = pad
    meas = Measurements(
        t=bundle.stamp_ns / NS_PER_S, R_IB=R_IB,
        window_bearings_C=bundle.get(InputKind.WINDOW), pad_bearings_C=pad,
        phi_front_I=bundle.get(InputKind.FLOW_FRONT), phi_down_I=bundle.get(InputKind.FLOW_DOWN),
        pad_groups=pad_groups)
    out = controller.step(mode, meas)
    F = np.asarray(out.F_I, dtype=float)
    if F.shape != (3,) or not np.all(np.isfinite(F)) or not np.isfinite(out.yaw_des):
        return None, hover
    return out, F


FEATURE_NAMES = ('q_w', 'q_w_bar', 'q_t', 'phi_w', 'phi_t', 'eta_w')


def feature_vector(features: FeatureSnapshot) -> tuple[list[str], list[float]]:
    """Flatten a FeatureSnapshot for ibvs/features: names 'q_w.x', ..., 'alpha_w' (in {I}).

    Features that are not available (None) or not finite are left out of the message.
    """
    names, values = [], []
    for name in FEATURE_NAMES:
        v = getattr(features, name)
        if v is not None and np.all(np.isfinite(v)):
            names += [f'{name}.x', f'{name}.y', f'{name}.z']
            values += [float(x) for x in np.asarray(v, dtype=float).reshape(3)]
    if features.alpha_w is not None and np.isfinite(features.alpha_w):
        names.append('alpha_w')
        values.append(float(features.alpha_w))
    return names, values
