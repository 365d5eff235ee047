"""Real flight firmware as the sim's autopilot, in lockstep with the sim's plant (issue 47).

The firmware (PX4 SITL on its simulator_mavlink interface, ``px4_hil``) runs its own mixer,
rate and attitude controllers and estimator; the sim's plant (:mod:`ibvs_sim.core.dynamics`)
turns its motor outputs into motion (:mod:`~ibvs_sim.core.firmware.motors`) and answers with
the sensors it needs, and the firmware's clock is the sim's (:mod:`~ibvs_sim.core.firmware.
lockstep`). ROS-free. docs/firmware_lockstep.md.
"""
