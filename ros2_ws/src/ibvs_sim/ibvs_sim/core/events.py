"""Contact events of the simulated vehicle: touchdown on the floor, collision with the scene.

:class:`ContactMonitor` checks the vehicle's envelope against the world after every physics
step (:func:`~ibvs_sim.core.contacts.min_clearance`) and reports a :class:`SimEvent`; the sim
node publishes each on ``sim/events`` (:meth:`SimEvent.to_dict`). A collision ends the run;
after touchdown, contacts are no longer checked. ROS-free.
"""
from __future__ import annotations

from dataclasses import dataclass
import enum

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import vec_I_to_map
from ibvs_sim.core.contacts import FLOOR, min_clearance
from ibvs_sim.core.dynamics import State
from ibvs_sim.core.world import WorldConfig


class EventType(str, enum.Enum):
    """Kinds of contact events."""

    COLLISION = 'collision'
    TOUCHDOWN = 'touchdown'


@dataclass
class SimEvent:
    """A contact event: collision (run ends) or touchdown."""

    type: EventType
    t: float                      # s, sim time
    surface: str                  # 'floor' | 'wall' | 'window_frame' | 'back_wall'
    position_I: np.ndarray        # m, body origin in {I}
    speed_mps: float              # touchdown: vertical speed; collision: speed

    def to_dict(self) -> dict:
        """Return the JSON object published on ``sim/events`` (position in ``map``, ENU)."""
        return {'type': self.type.value, 't': round(self.t, 6), 'surface': self.surface,
                'position_map': [round(float(x), 6) for x in vec_I_to_map(self.position_I)],
                'speed_mps': round(float(self.speed_mps), 6)}


class ContactMonitor:
    """Check the vehicle's envelope against the world; report touchdown once, then nothing."""

    def __init__(self, world: WorldConfig, vehicle: VehicleConfig) -> None:
        self.world, self.vehicle = world, vehicle
        self.touched_down = False

    def check(self, t: float, s: State, last_impact_speed: float) -> SimEvent | None:
        """Return the contact event of state ``s`` at sim time ``t`` (s), or None.

        ``last_impact_speed``: the plant's vertical speed before its floor stopped the body
        within the step (m/s), reported as the touchdown speed.
        """
        if self.touched_down:
            return None
        clearance, surface = min_clearance(s.xi_I, self.world, self.vehicle.envelope_radius,
                                           self.vehicle.envelope_height)
        if clearance > 0.0:
            return None
        if surface == FLOOR:
            self.touched_down = True
            # the plant's floor stops the body within the step: report the speed before it
            v_z = float(s.v_I[2]) if s.v_I[2] > 0.0 else float(last_impact_speed)
            return SimEvent(EventType.TOUCHDOWN, t, surface, s.xi_I.copy(), v_z)
        return SimEvent(EventType.COLLISION, t, surface, s.xi_I.copy(),
                        float(np.linalg.norm(s.v_I)))
