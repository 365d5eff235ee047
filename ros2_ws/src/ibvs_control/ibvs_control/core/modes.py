"""Flight modes of the application scenario (paper section 4.3, SPEC.md section 3)."""
from enum import IntEnum


class Mode(IntEnum):
    """The value published on ``ibvs/mode`` (std_msgs/UInt8)."""

    IDLE = 0        # before start: the autopilot holds the vehicle
    WINDOW = 1      # window approach, F_w (eq:Fw)
    CROSSING = 2    # blind crossing (forward camera lost the window)
    LANDING = 3     # landing, F_t (eq:FT)
    SHUTDOWN = 4    # motors ramped down, then disarm
    FAILSAFE = 5    # an input went stale or an abort: level, slow descent


FLYING_MODES = (Mode.WINDOW, Mode.CROSSING, Mode.LANDING)
