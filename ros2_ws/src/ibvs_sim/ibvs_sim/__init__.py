"""Simulated AscTec Pelican-class quadrotor with two cameras and a MAVLink autopilot (PX4 offboard-like) for the IBVS stack."""
