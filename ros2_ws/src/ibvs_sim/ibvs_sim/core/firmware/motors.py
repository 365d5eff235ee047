"""Firmware motor outputs -> the plant's rotor thrust commands (N): order and thrust curve.

A firmware numbers its motors its own way (PX4's quad X: front-right, rear-left, front-left,
rear-right) and sends each as a normalised output u in [0, 1]. The plant's rotors are numbered
by :data:`~ibvs_sim.core.dynamics.ROTOR_AZIMUTHS_RAD` (front-right, rear-right, rear-left,
front-left). :class:`MotorModel` maps one to the other by the rotors' positions, and applies
the rotors' static thrust curve::

    T(u) = T_max ((1 - k) u + k u^2),     u in [0, 1]

``k`` is what a user measures on a thrust stand and sets as PX4's ``THR_MDL_FAC`` or
ArduPilot's ``MOT_THST_EXPO`` (both use this model to linearise thrust). The rotor's lag is
the plant's (first order, :class:`~ibvs_sim.core.dynamics.QuadrotorPlant`).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from ibvs_sim.core.dynamics import N_ROTORS, ROTOR_AZIMUTHS_RAD, ROTOR_SPIN

#: PX4's quad X (airframe 4001, CA_ROTOR0..3): (x forward, y right) unit directions and spin
#: (+1 counter-clockwise seen from above, PX4's CA_ROTORn_KM > 0), in PX4's output order.
PX4_QUAD_X = (((1.0, 1.0), +1), ((-1.0, -1.0), +1), ((1.0, -1.0), -1), ((-1.0, 1.0), -1))


class MotorMapError(ValueError):
    """A firmware rotor layout that does not match the plant's rotors."""


def plant_rotor_for(direction_xy: Sequence[float], spin: int) -> int:
    """Return the plant rotor at body direction ``direction_xy`` (FRD) with spin ``spin``."""
    azimuth = math.atan2(float(direction_xy[1]), float(direction_xy[0])) % (2.0 * math.pi)
    for i, (a, s) in enumerate(zip(ROTOR_AZIMUTHS_RAD, ROTOR_SPIN)):
        if abs(math.remainder(azimuth - a, 2.0 * math.pi)) < 1e-6 and int(s) == int(spin):
            return i
    raise MotorMapError(f'no plant rotor at azimuth {math.degrees(azimuth):.1f} deg with '
                        f'spin {spin:+d}')


@dataclass(frozen=True)
class MotorModel:
    """Normalised firmware outputs -> the plant's rotor thrust commands (N)."""

    output_to_rotor: tuple[int, ...]   # firmware output i drives plant rotor output_to_rotor[i]
    thrust_max: float                  # N per rotor at u = 1
    curve: float = 0.0                 # k of T(u) = T_max ((1 - k) u + k u^2), in [0, 1]

    def __post_init__(self) -> None:
        """Check the map is a permutation of the plant's rotors and k in [0, 1]."""
        if sorted(self.output_to_rotor) != list(range(N_ROTORS)):
            raise MotorMapError(f'output_to_rotor must be a permutation of 0..{N_ROTORS - 1}, '
                                f'got {self.output_to_rotor}')
        if not (self.thrust_max > 0.0 and 0.0 <= self.curve <= 1.0):
            raise MotorMapError(f'need thrust_max > 0 and curve in [0, 1], got '
                                f'{self.thrust_max}, {self.curve}')

    @classmethod
    def for_layout(cls, layout: Sequence, thrust_max: float,
                   curve: float = 0.0) -> 'MotorModel':
        """Build from a firmware layout: per output, ((x, y) direction, spin)."""
        return cls(tuple(plant_rotor_for(d, s) for d, s in layout), float(thrust_max),
                   float(curve))

    def thrust(self, u: np.ndarray | float) -> np.ndarray:
        """Return T(u) (N) for normalised outputs u, clipped to [0, 1] (NaN -> 0: motor off)."""
        u = np.nan_to_num(np.asarray(u, float), nan=0.0)
        u = np.clip(u, 0.0, 1.0)
        return self.thrust_max * ((1.0 - self.curve) * u + self.curve * u * u)

    def output_for(self, thrust_n: float) -> float:
        """Return the output u that gives ``thrust_n`` (N) per rotor (the curve's inverse)."""
        x = min(max(float(thrust_n) / self.thrust_max, 0.0), 1.0)
        k = self.curve
        if k < 1e-9:
            return x
        return (-(1.0 - k) + math.sqrt((1.0 - k) ** 2 + 4.0 * k * x)) / (2.0 * k)

    def rotor_commands(self, outputs: Sequence[float]) -> np.ndarray:
        """Return the plant's rotor thrust commands (N) for the firmware's first outputs."""
        u = np.asarray(list(outputs)[:len(self.output_to_rotor)], float)
        if u.shape != (N_ROTORS,):
            raise MotorMapError(f'need {N_ROTORS} motor outputs, got {u.shape}')
        cmd = np.zeros(N_ROTORS)
        cmd[list(self.output_to_rotor)] = self.thrust(u)
        return cmd
