"""IBVS control: mode supervisor, outer-loop force controller, MAVLink bridge.

The ROS-free core (the paper's control laws, the mode state machine, the timing model and the
MAVLink pieces) lives in ``ibvs_control.core``; the geometry and configuration it shares with
perception and the sim live in ``ibvs_common``.
"""
