"""One frame's inputs from messages to the controller and back (ROS-free).

Validation of the products a frame carries (bearings, flows), pairing of ``pad/landmarks``
with ``pad/groups``, one controller step on a released :class:`~ibvs_control.core.timing.Frame`
and the flattening of its features for ``ibvs/features``. When a frame is released is the
timing layer's business (core/timing.py), not this module's.
"""
from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from ibvs_control.core.controller import (
    ControlOutput, FeatureSnapshot, IbvsController, Measurements)
from ibvs_common.core.frames import (
    e3, GRAVITY, MAP_FRAME, quat_from_rot, quat_ned_frd_to_enu_flu, rot_z, vec_map_to_I)
from ibvs_common.core.modes import Mode
from ibvs_common.core.modes import InputKind
from ibvs_common.core.stamps import NS_PER_S
from ibvs_control.core.timing import Frame


class PadPairing:
    """Pair each ``pad/landmarks`` with the ``pad/groups`` of the same image, by stamp.

    The pad detector publishes both for every image, stamped with the image. Two topics are
    not ordered with respect to each other (an executor that fell behind takes frame k+1's
    landmarks before frame k's groups), so halves are matched only by equal stamps, in
    either order, never by arrival: a landmarks message is never labelled with another
    image's groups. A pair must agree in count (4 landmarks per group, none for no group).
    Halves still waiting when a newer pair completes can never be completed (each topic is
    in order), nor can the oldest beyond ``depth`` per topic: they are dropped and counted in
    ``unpaired``. Stamps are integers (ns).
    """

    def __init__(self, landmarks_per_group: int = 4, depth: int = 4) -> None:
        self.landmarks_per_group = landmarks_per_group
        self.depth = depth
        self.unpaired = 0
        self._landmarks: dict[int, np.ndarray | None] = {}
        self._groups: dict[int, tuple] = {}

    def add_landmarks(self, stamp_ns: int, bearings: np.ndarray | None) -> tuple | None:
        """Hold a landmarks message; return (stamp_ns, bearings, groups, weights) on a pair."""
        self._landmarks[int(stamp_ns)] = bearings
        return self._pair(int(stamp_ns))

    def add_groups(self, stamp_ns: int, groups: Iterable[str],
                   weights: tuple | None = None) -> tuple | None:
        """Hold a groups message (its group weights or None); return the pair it completes."""
        self._groups[int(stamp_ns)] = (tuple(groups), weights)
        return self._pair(int(stamp_ns))

    def drop(self, stamp_ns: int) -> None:
        """Forget both halves at ``stamp_ns`` (its landmarks were refused, for instance)."""
        self._landmarks.pop(int(stamp_ns), None)
        self._groups.pop(int(stamp_ns), None)

    def _pair(self, stamp_ns: int) -> tuple | None:
        if stamp_ns in self._landmarks and stamp_ns in self._groups:
            bearings = self._landmarks.pop(stamp_ns)
            groups, weights = self._groups.pop(stamp_ns)
            self._forget_before(stamp_ns)
            n = 0 if bearings is None else len(bearings)
            if n != self.landmarks_per_group * len(groups):
                self.unpaired += 1
                return None
            return stamp_ns, bearings, groups, weights
        for held in (self._landmarks, self._groups):
            while len(held) > self.depth:
                del held[min(held)]
                self.unpaired += 1
        return None

    def _forget_before(self, stamp_ns: int) -> None:
        for held in (self._landmarks, self._groups):
            for t in [t for t in held if t < stamp_ns]:
                del held[t]
                self.unpaired += 1


class SpecificForceBuffer:
    """The IMU's specific force over time, for the disturbance observer.

    f_I = v' - g e3 = (-F + Delta) / m (what an accelerometer measures, rotated to {I} with the
    attitude of its sample). Samples are kept in the body frame FRD (m/s^2) as they arrive;
    :meth:`mean_between` rotates the ones of a frame interval with the attitude at their stamps
    and gives their mean, so the observer sees the force that acted while the previous
    command was applied.
    """

    def __init__(self, history_s: float = 1.0) -> None:
        self.history_s = history_s
        self._t: list[float] = []
        self._f_B: list[np.ndarray] = []

    def add(self, t: float, f_B: np.ndarray) -> None:
        """Keep one body-frame sample (non-finite ones are ignored); drop older than history_s."""
        f = np.asarray(f_B, dtype=float).reshape(3)
        if not (np.isfinite(t) and np.all(np.isfinite(f))):
            return
        self._t.append(float(t))
        self._f_B.append(f)
        while self._t and self._t[0] < self._t[-1] - self.history_s:
            del self._t[0], self._f_B[0]

    def clear(self) -> None:
        """Drop every sample (the IMU's stamps went back: a clock step)."""
        self._t.clear()
        self._f_B.clear()

    def mean_between(self, t0: float | None, t1: float,
                     attitude_at: Callable[[float], np.ndarray | None]) -> np.ndarray | None:
        """Mean f_I of the samples with t0 < t <= t1 (t0 None: the newest only), or None.

        ``attitude_at(t)``: R_IB at a sample's stamp (AttitudeBuffer.attitude_at); a sample
        without an attitude is left out.
        """
        picked = [(t, f) for t, f in zip(self._t, self._f_B)
                  if t <= t1 and (t0 is None or t > t0)]
        if t0 is None:
            picked = picked[-1:]
        f_I = []
        for t, f_B in picked:
            R_IB = attitude_at(t)
            if R_IB is not None:
                f_I.append(R_IB @ f_B)
        return np.mean(f_I, axis=0) if f_I else None


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


def unpack_pad(value) -> tuple:
    """Return (bearings or None, group names or None, group weights or None) of a PAD input.

    The PAD input is PadPairing's (bearings, groups, weights); (bearings, groups) and a bare
    array (no group names) are accepted too.
    """
    if not isinstance(value, tuple):
        return value, None, None
    if len(value) == 2:
        return value[0], value[1], None
    return value[0], value[1], value[2]


def step_controller(controller: IbvsController, mode: Mode, frame: Frame,
                    R_IB: np.ndarray | None, specific_force_I: np.ndarray | None = None,
                    omega_B: np.ndarray | None = None
                    ) -> tuple[ControlOutput | None, np.ndarray]:
    """Answer one frame: (controller output or None, force F in {I} (N)).

    The PAD input of the frame is (landmark bearings or None, group names, group weights), as
    PadPairing gives it (:func:`unpack_pad`).

    Without any IMU attitude yet the controller cannot derotate the bearings: the answer is
    the hover force m g e3 (level) and no output (no heading, no features). A non-finite
    controller force (a bug) is replaced by the hover force as well.
    """
    hover = controller.config.mass * GRAVITY * e3
    if R_IB is None:
        return None, hover
    pad, pad_groups, pad_weights = unpack_pad(frame.get(InputKind.PAD))
    meas = Measurements(
        t=frame.stamp_ns / NS_PER_S, R_IB=R_IB,
        window_bearings_C=frame.get(InputKind.WINDOW), pad_bearings_C=pad,
        phi_front_I=frame.get(InputKind.FLOW_FRONT), phi_down_I=frame.get(InputKind.FLOW_DOWN),
        pad_groups=pad_groups, pad_group_weights=pad_weights,
        specific_force_I=specific_force_I, omega_B=omega_B)
    out = controller.step(mode, meas)
    F = np.asarray(out.F_I, dtype=float)
    if F.shape != (3,) or not np.all(np.isfinite(F)) or not np.isfinite(out.yaw_des):
        return None, hover
    return out, F


FEATURE_NAMES = ('q_w', 'q_w_bar', 'q_t', 'phi_w', 'phi_t', 'eta_w', 'd_hat')


def feature_vector(features: FeatureSnapshot) -> tuple[list[str], list[float]]:
    """Flatten a FeatureSnapshot for ibvs/features: names 'q_w.x', ..., 'alpha_w' (in {I}).

    Features that are not available (None) or not finite are left out of the message.
    With q_t, 'pad_predicted' is 1 when q_t was carried on the floor flow (pad_prediction.py).
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
    if 'q_t.x' in names:        # 1: q_t carried on the floor flow through a pad loss
        names.append('pad_predicted')
        values.append(float(features.pad_predicted))
    return names, values
