"""The sim autopilot's parameter protocol: PARAM_REQUEST_READ (name or index), PARAM_REQUEST_LIST.

Parameters (index order): ``MPC_THR_HOVER`` (REAL32, ``hover_thrust``), ``COM_OF_LOSS_T``
(REAL32, ``offboard_timeout_s``, s of sim time) and ``COM_OBL_RC_ACT`` (INT32 in PX4's bytewise
encoding, 4 = Land mode). An unknown name gets no PARAM_VALUE, only a STATUSTEXT, as PX4's
parameter manager; an index out of range gets nothing. PARAM_SET is not handled.
"""
from __future__ import annotations

import struct
from typing import Any

from ibvs_sim.core.autopilot.config import AutopilotConfig, AutopilotCounters, VehicleStateView
from ibvs_sim.core.autopilot.link import AutopilotLink
from ibvs_sim.core.autopilot.protocol import (MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32,
                                              MAV_SEVERITY_INFO, OFFBOARD_LOSS_ACTION_LAND,
                                              PARAM_ID_LEN)


class ParamServer:
    """The autopilot's read-only parameters, answered with PARAM_VALUE on ``link``."""

    def __init__(self, config: AutopilotConfig, counters: AutopilotCounters,
                 link: AutopilotLink) -> None:
        """Take the parameter values from ``config``."""
        self.counters = counters
        self._link = link
        self._params = {'MPC_THR_HOVER': float(config.hover_thrust),
                        'COM_OF_LOSS_T': float(config.offboard_timeout_s),
                        'COM_OBL_RC_ACT': OFFBOARD_LOSS_ACTION_LAND}      # INT32, as PX4's

    def names(self) -> list[str]:
        """Return the parameter names in index order."""
        return list(self._params)

    def on_request_read(self, msg: Any, state: VehicleStateView) -> None:
        """Answer PARAM_REQUEST_READ: by index when param_index >= 0, else by name."""
        if not self._link.for_us(msg.target_system, msg.target_component):
            return
        self.counters.param_requests += 1
        names = self.names()
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
            else:
                self.counters.param_unknown += 1
            return
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(
            'ascii', 'replace')
        name = name.rstrip('\x00')
        if name in self._params:
            self._send_param(name)
        else:
            # PX4's parameter manager sends no PARAM_VALUE, only an info text.
            self.counters.param_unknown += 1
            self._link.statustext(MAV_SEVERITY_INFO, f'[pm] unknown param: {name}')

    def on_request_list(self, msg: Any, state: VehicleStateView) -> None:
        """Answer PARAM_REQUEST_LIST with every parameter, in index order."""
        if not self._link.for_us(msg.target_system, msg.target_component):
            return
        self.counters.param_requests += 1
        for name in self.names():
            self._send_param(name)

    def _send_param(self, name: str) -> None:
        names = self.names()
        value, kind = self._params[name], MAV_PARAM_TYPE_REAL32
        if isinstance(value, int):     # PX4's bytewise encoding: the INT32's bytes as a float
            value, kind = struct.unpack('<f', struct.pack('<i', value))[0], MAV_PARAM_TYPE_INT32
        self._link.mav.param_value_send(name.encode('ascii')[:PARAM_ID_LEN], float(value), kind,
                                        len(names), names.index(name))
