"""IBVS core and control nodes: mode supervisor, outer-loop force controller, MAVLink bridge.

The ROS-free core (frames, camera model, the paper's features and control laws, the mode state
machine) lives in ``ibvs_control.core``.
"""
