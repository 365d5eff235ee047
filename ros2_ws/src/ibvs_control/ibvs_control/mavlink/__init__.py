"""The MAVLink bridge's ROS-free pieces, one concern per module (as MAVROS's plugins).

``link`` (connection, heartbeat, signing, reading), ``time_sync`` (TIMESYNC onto the ROS
clock), ``sequencer`` (arming and mode changes, PX4 and ArduPilot), ``telemetry`` (attitude,
IMU, thrust, status in), ``setpoints`` (force -> attitude/thrust out), ``safety`` (when to hand
the vehicle back), ``params`` (the autopilot's parameters), ``hover`` (hover thrust) and
``bridge``, which composes them for the ``mavlink_bridge`` node.
"""
