"""The pad centre carried through a short loss of the pad in LANDING, on the floor flow.

Why: near the floor the down camera sees only a few centimetres around it. At a camera height
of 0.15 m its image spans about +-0.1 m of floor across its short side, and the smallest
marker group (half-side 0.045 m, markers 0.025 m wide) leaves it as soon as the vehicle is
~4 cm off the pad. With no complete group there is no q_t, and the landing law used to hold
its last force until the pad came back or went stale: in the feature-level wind campaign
(0.5 m/s^2, PX4's estimate error) 14 of 86 landings lost the pad for 0.1-0.8 s below 0.2 m
and flew that force open loop into a sideways speed of up to 0.28 m/s at the shutdown switch.
docs/design.md "The pad through a short loss".

What: the pad centre's position relative to the down camera, ``r_I`` (m, {I}), from the last
complete group, moved each frame by the floor flow until a group is seen again or
``max_age_s`` (ROS clock, from the last pad frame's stamp) has passed.

- Measured: ``r_I = h p / (eta_t^T p)``, p = -q_t the pad centre's bearing (pad_feature), h the
  pad-image height (pad_height_estimate): the centre lies on the floor plane at depth h.
- Carried: over a flat floor the camera moves at v, so ``r' = -v``, and the floor flow is
  ``phi_t = v / d_t`` with the floor's depth ``d_t = eta_t^T r`` (the pad lies on the floor):
  ``r' = -phi_t eta_t^T r``, linear in r. With the frame's flow held over the step (the flow
  of a frame measures the motion since the last one), the exact step is
  ``r <- r - phi_t (eta_t^T r) (1 - exp(-s dt)) / s``, ``s = eta_t^T phi_t`` (-> dt as s -> 0):
  the height follows ``h <- h exp(-s dt)`` (a descent at s = v_z / h shrinks it
  geometrically), the plane offset moves by the metric velocity h phi_t integrated.
- Out: ``q_t = -r / |r|`` and ``h = eta_t^T r``, what the measurements would have given.

ROS-free; one ``step`` per LANDING frame: IbvsController flies the estimate, ModeSupervisor
takes its height for the 3 -> 4 switch (only within ``shutdown_carried_offset_m`` of the
carried centre, supervisor.py).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

#: |s dt| below which (1 - exp(-s dt)) / s is taken as dt (relative error < 1e-9)
_SMALL_EXPONENT = 1e-9


@dataclass(frozen=True)
class PadEstimate:
    """q_t (unit, {I}, from the pad centre towards the camera) and h (m), and their origin."""

    q_t: np.ndarray
    height_m: float | None  # None: a pad seen through no group of known size
    predicted: bool         # True: carried on the flow since the last pad frame
    r_I: np.ndarray | None = None   # m, {I}: the pad centre from the camera (None: no height)


def pad_centre_from_feature(q_t: np.ndarray, height_m: float,
                            eta_t: np.ndarray) -> np.ndarray:
    """Return r_I (m, {I}): the pad centre from the camera, r = h p / (eta_t^T p), p = -q_t.

    Raises ValueError when the centre's bearing does not point towards the floor.
    """
    p = -np.asarray(q_t, dtype=float)
    depth = float(p @ eta_t)
    if not depth > 0.0:
        raise ValueError('the pad centre is not below the camera')
    return float(height_m) * p / depth


def carry_pad_centre(r_I: np.ndarray, phi_t_I: np.ndarray, dt: float,
                     eta_t: np.ndarray) -> np.ndarray:
    """Move r_I (m, {I}) over dt (s) by the floor flow phi_t (1/s, {I}): r' = -phi_t eta_t^T r.

    Exact for a flow constant over the step (module docstring).
    """
    r = np.asarray(r_I, dtype=float)
    phi = np.asarray(phi_t_I, dtype=float)
    s = float(eta_t @ phi)
    if abs(s * dt) < _SMALL_EXPONENT:
        gain = dt
    else:
        gain = -math.expm1(-s * dt) / s
    return r - phi * float(eta_t @ r) * gain


class PadPrediction:
    """The pad centre from the last complete group, carried on the floor flow for max_age_s."""

    def __init__(self, max_age_s: float, eta_t: np.ndarray) -> None:
        if not (math.isfinite(max_age_s) and max_age_s >= 0.0):
            raise ValueError(f'max_age_s must be finite and >= 0: {max_age_s}')
        self.max_age_s = float(max_age_s)
        self.eta_t = np.asarray(eta_t, dtype=float)
        self.reset()

    def reset(self) -> None:
        """Forget the pad (a new LANDING)."""
        self._r_I: np.ndarray | None = None
        self._t_seen: float | None = None       # s, stamp of the last pad frame
        self._t_last: float | None = None       # s, stamp of the last step

    def step(self, t: float, q_t: np.ndarray | None, height_m: float | None,
             phi_t_I: np.ndarray | None) -> PadEstimate | None:
        """One LANDING frame at stamp t (s, ROS clock; frames in stamp order).

        A measured pad (q_t and its height) is returned as it is and remembered. Without one,
        the remembered centre is carried by this frame's floor flow and returned as predicted,
        for at most max_age_s after the last pad frame; None when there is nothing to carry
        (no pad yet, no flow this frame, too old, or the prediction is off: max_age_s 0).
        """
        dt, self._t_last = (0.0 if self._t_last is None else t - self._t_last), t
        if q_t is not None:
            self._r_I, self._t_seen = None, t
            if height_m is not None:
                try:
                    self._r_I = pad_centre_from_feature(q_t, height_m, self.eta_t)
                except ValueError:
                    pass
            return PadEstimate(np.asarray(q_t, dtype=float), height_m, False,
                               None if self._r_I is None else self._r_I.copy())
        if (self._r_I is None or phi_t_I is None or self.max_age_s <= 0.0
                or not 0.0 <= t - self._t_seen <= self.max_age_s or dt < 0.0):
            self._r_I = None
            return None
        self._r_I = carry_pad_centre(self._r_I, phi_t_I, dt, self.eta_t)
        height = float(self.eta_t @ self._r_I)
        if not height > 0.0:
            self._r_I = None
            return None
        return PadEstimate(-self._r_I / np.linalg.norm(self._r_I), height, True,
                           self._r_I.copy())
