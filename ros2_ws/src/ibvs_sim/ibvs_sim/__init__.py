"""Simulated AscTec Pelican-class quadrotor with two cameras and a MAVLink autopilot.

PX4 offboard-like autopilot, planar world renderer and rigid-body plant for the IBVS stack.
"""
