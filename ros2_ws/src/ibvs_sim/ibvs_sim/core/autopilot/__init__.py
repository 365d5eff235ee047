"""The simulated autopilot: PX4 in offboard mode as a companion computer sees it over MAVLink.

ROS-free core. The sim node composes :class:`Autopilot` with its plant: at every physics step it
calls :meth:`Autopilot.poll` with the ground-truth state (answers commands, sends telemetry) and
:meth:`Autopilot.attitude_reference` to get the inner-loop reference (attitude + normalised
collective thrust) that its attitude controller tracks.

Frames and units (SPEC.md section 1): {I} is the autopilot's local NED frame (z down, gravity
``+g e3``), the body frame is FRD, quaternions are Hamilton ``(w, x, y, z)`` of ``R_IB`` (FRD in
NED) as MAVLink sends them. SI units; MAVLink time stamps are *sim* time since boot (the sim
clock starts at 0). Normalised thrust is ``T / T_max`` with ``T_max = m g / hover_thrust``.

One concern per module (details, and how it differs from real PX4, in docs/sim_autopilot.md):

- :mod:`~ibvs_sim.core.autopilot.protocol`: MAVLink ids and flags, PX4's modes (custom_mode
  layout: main mode in bits 16-23, sub mode in bits 24-31): POSCTL (position hold on ground
  truth, the start mode, armed and airborne), OFFBOARD (the companion's SET_ATTITUDE_TARGET is
  the reference), AUTO_LOITER (hold), AUTO_LAND (descent; also the offboard-loss failsafe);
- :mod:`~ibvs_sim.core.autopilot.config`: settings, ground truth in, reference out, counters;
- :mod:`~ibvs_sim.core.autopilot.link`: the UDP endpoint, optional MAVLink 2 signing, reading
  and dispatch; malformed, unknown, foreign or unsigned input is counted and ignored;
- :mod:`~ibvs_sim.core.autopilot.commands`: COMMAND_LONG (ARM_DISARM, DO_SET_MODE,
  SET_MESSAGE_INTERVAL, REQUEST_MESSAGE), acknowledged with PX4's results (a refused mode
  switch or arming change is TEMPORARILY_REJECTED, as PX4's commander answers);
- :mod:`~ibvs_sim.core.autopilot.params`: PARAM_REQUEST_READ / _LIST;
- :mod:`~ibvs_sim.core.autopilot.timesync`: TIMESYNC both ways as PX4 does: a request
  (tc1 = 0) gets tc1 = the boot time in ns (= the sim time it is polled at, the clock of
  time_boot_ms), ts1 echoed, not at time 0 (tc1 = 0 would read as a request); and requests of
  its own at 10 Hz of sim time, whose answers are checked and counted;
- :mod:`~ibvs_sim.core.autopilot.setpoints`: SET_ATTITUDE_TARGET validation and the offboard
  stream's timing;
- :mod:`~ibvs_sim.core.autopilot.modes`: armed state, flight mode, offboard-loss failsafe,
  landed detector and auto-disarm;
- :mod:`~ibvs_sim.core.autopilot.references`: the inner-loop reference of each mode (offboard
  setpoint, hold, land);
- :mod:`~ibvs_sim.core.autopilot.telemetry` and :mod:`~ibvs_sim.core.autopilot.noise`:
  ATTITUDE_QUATERNION and HIGHRES_IMU (50 Hz by default, paced in sim time, noisy),
  ATTITUDE_TARGET (the reference's thrust, 50 Hz), EXTENDED_SYS_STATE (landed state) and
  SYS_STATUS (pre-arm check passed) at 5 Hz, HEARTBEAT at 1 Hz wall time;
- :mod:`~ibvs_sim.core.autopilot.facade`: :class:`Autopilot`, which composes them;
- :mod:`~ibvs_sim.core.autopilot.stand_in`: :class:`HoverStandIn`, an Autopilot served on the
  wall clock for a vehicle at rest (benchmarks, tests).
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
