"""MAVLink ids and flags, and PX4's modes, as the sim autopilot speaks them.

pymavlink, MAVLink 2, ``common`` dialect. Importing this module selects MAVLink 2 and the
dialect before pymavlink is used: the other modules of the autopilot take ``mavlink`` and
``mavutil`` from here, never from pymavlink directly.

PX4's ``custom_mode`` layout: main mode in bits 16-23, sub mode in bits 24-31
(src/modules/commander/px4_custom_mode.h).
"""
from __future__ import annotations

import enum
import os

# MAVLink 2 must be chosen before pymavlink.mavutil is imported (it picks the wire version then).
os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

MAVLINK_DIALECT = 'common'
mavutil.set_dialect(MAVLINK_DIALECT)  # re-select: an earlier import may have chosen MAVLink 1
mavlink = mavutil.mavlink

# --- MAVLink ids and flags (from pymavlink where it has them) ----------------------------------
MAV_COMP_ID_AUTOPILOT1 = mavlink.MAV_COMP_ID_AUTOPILOT1
MAV_TYPE_QUADROTOR = mavlink.MAV_TYPE_QUADROTOR
MAV_AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MAV_MODE_FLAG_SAFETY_ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
MAV_STATE_STANDBY = mavlink.MAV_STATE_STANDBY
MAV_STATE_ACTIVE = mavlink.MAV_STATE_ACTIVE
MAV_STATE_CRITICAL = mavlink.MAV_STATE_CRITICAL

MAV_CMD_COMPONENT_ARM_DISARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
MAV_CMD_DO_SET_MODE = mavlink.MAV_CMD_DO_SET_MODE
MAV_CMD_SET_MESSAGE_INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_CMD_REQUEST_MESSAGE = mavlink.MAV_CMD_REQUEST_MESSAGE

MAV_RESULT_ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
MAV_RESULT_TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
MAV_RESULT_DENIED = mavlink.MAV_RESULT_DENIED
MAV_RESULT_UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
MAV_RESULT_FAILED = mavlink.MAV_RESULT_FAILED

MAV_PARAM_TYPE_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
MAV_PARAM_TYPE_INT32 = mavlink.MAV_PARAM_TYPE_INT32
# COM_OBL_RC_ACT of what the sim does on an offboard loss: AUTO_LAND at once (PX4's 4, Land mode)
OFFBOARD_LOSS_ACTION_LAND = 4
MAV_SEVERITY_INFO = mavlink.MAV_SEVERITY_INFO
MAV_SEVERITY_WARNING = mavlink.MAV_SEVERITY_WARNING
MAV_SEVERITY_CRITICAL = mavlink.MAV_SEVERITY_CRITICAL

MSG_ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
MSG_ID_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
MSG_ID_HIGHRES_IMU = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
MSG_ID_ATTITUDE_TARGET = mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET
MSG_ID_EXTENDED_SYS_STATE = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
MSG_ID_SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
MSG_ID_RC_CHANNELS = mavlink.MAVLINK_MSG_ID_RC_CHANNELS
MAV_LANDED_STATE_ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
MAV_LANDED_STATE_IN_AIR = mavlink.MAV_LANDED_STATE_IN_AIR
MAV_VTOL_STATE_UNDEFINED = mavlink.MAV_VTOL_STATE_UNDEFINED
MAV_SYS_STATUS_PREARM_CHECK = mavlink.MAV_SYS_STATUS_PREARM_CHECK

TYPEMASK_BODY_RATES_IGNORE = (mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE
                              | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
                              | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE)
TYPEMASK_THROTTLE_IGNORE = mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
TYPEMASK_ATTITUDE_IGNORE = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE

HIGHRES_IMU_FIELDS_ACC_GYRO = (mavlink.HIGHRES_IMU_UPDATED_XACC | mavlink.HIGHRES_IMU_UPDATED_YACC
                               | mavlink.HIGHRES_IMU_UPDATED_ZACC
                               | mavlink.HIGHRES_IMU_UPDATED_XGYRO
                               | mavlink.HIGHRES_IMU_UPDATED_YGYRO
                               | mavlink.HIGHRES_IMU_UPDATED_ZGYRO)

BROADCAST_ID = 0                 # target_system / target_component 0: everyone
PX4_FORCE_DISARM_MAGIC = 21196   # COMPONENT_ARM_DISARM param2 that forces a disarm in the air
ARM_ACTION_DISARM = 0
ARM_ACTION_ARM = 1
SET_INTERVAL_DISABLE = -1        # SET_MESSAGE_INTERVAL param2: stop the stream
SET_INTERVAL_DEFAULT = 0         # SET_MESSAGE_INTERVAL param2: back to the default rate
UINT8_MASK = 0xFF                # PX4 casts the float params of DO_SET_MODE to uint8_t
PX4_MAIN_MODE_BIT = 16           # custom_mode bits 16-23: main mode
PX4_SUB_MODE_BIT = 24            # custom_mode bits 24-31: sub mode
US_PER_S = 1_000_000
MS_PER_S = 1000
PARAM_ID_LEN = 16                # PARAM_VALUE.param_id, chars
STATUSTEXT_LEN = 50              # STATUSTEXT.text, chars


class Px4MainMode(enum.IntEnum):
    """PX4's main modes (src/modules/commander/px4_custom_mode.h)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE_LEGACY = 8
    SIMPLE = 9
    TERMINATION = 10


class Px4AutoSubMode(enum.IntEnum):
    """PX4's AUTO sub modes (src/modules/commander/px4_custom_mode.h)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


class FlightMode(enum.Enum):
    """The PX4 modes this autopilot flies; value = (main mode, sub mode)."""

    POSCTL = (Px4MainMode.POSCTL, 0)
    OFFBOARD = (Px4MainMode.OFFBOARD, 0)
    AUTO_LOITER = (Px4MainMode.AUTO, Px4AutoSubMode.LOITER)
    AUTO_LAND = (Px4MainMode.AUTO, Px4AutoSubMode.LAND)

    @property
    def main_mode(self) -> int:
        """PX4 main mode number."""
        return int(self.value[0])

    @property
    def sub_mode(self) -> int:
        """PX4 sub mode number (0 = none)."""
        return int(self.value[1])

    @property
    def custom_mode(self) -> int:
        """HEARTBEAT.custom_mode in PX4's layout (main << 16 | sub << 24)."""
        return (self.main_mode << PX4_MAIN_MODE_BIT) | (self.sub_mode << PX4_SUB_MODE_BIT)


# The modes that hold the position where they were entered (or where the vehicle was armed).
HOLD_MODES = (FlightMode.POSCTL, FlightMode.AUTO_LOITER)


class ReferenceSource(str, enum.Enum):
    """Where the inner-loop reference comes from."""

    OFFBOARD = 'offboard'
    HOLD = 'hold'
    FAILSAFE = 'failsafe'
    DISARMED = 'disarmed'
