"""The simulated autopilot: PX4 in offboard mode as a companion computer sees it over MAVLink.

ROS-free. The simulation polls :class:`Autopilot` with the ground truth at every physics step
(it answers commands and sends telemetry) and takes its attitude reference (attitude and
normalised collective thrust) for the inner loop. Frames: {I} is the autopilot's local NED
frame, the body FRD, quaternions Hamilton ``(w, x, y, z)`` of ``R_IB``; MAVLink times are sim
time since boot. One concern per module: docs/sim_autopilot.md "Structure".
"""
from ibvs_sim.core.autopilot.config import (AttitudeReference, AutopilotConfig,
                                            AutopilotCounters, VehicleStateView)
from ibvs_sim.core.autopilot.facade import Autopilot
from ibvs_sim.core.autopilot.link import load_signing_key
from ibvs_sim.core.autopilot.protocol import (FlightMode, Px4AutoSubMode, Px4MainMode,
                                              ReferenceSource)

__all__ = ['Autopilot', 'AutopilotConfig', 'AutopilotCounters', 'AttitudeReference',
           'FlightMode', 'Px4AutoSubMode', 'Px4MainMode', 'ReferenceSource', 'VehicleStateView',
           'load_signing_key']
