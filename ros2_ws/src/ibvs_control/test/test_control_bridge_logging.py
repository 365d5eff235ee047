"""The bridge node relays its core's events through the throttled log, each kind apart."""
from ibvs_common.testing import FakeClock, FakeLogger
from ibvs_common.throttled_log import ThrottledLog


def test_the_bridge_relays_each_kind_of_event_under_its_own_throttle():
    """Two different warnings in one batch both go out (one call site relays them all)."""
    from types import SimpleNamespace
    from ibvs_control.mavlink_bridge_node import MavlinkBridgeNode
    logger, clock = FakeLogger(), FakeClock()
    events = [('warn', 'setpoint source none -> level_hover'),
              ('warn', 'PX4 offboard loss: COM_OBL_RC_ACT = 0 (Position mode)'),
              ('warn', 'setpoint source none -> level_hover')]
    bridge = SimpleNamespace(pop_heading_warning=lambda: '', pop_events=lambda: events)
    node = SimpleNamespace(get_logger=lambda: logger, _bridge=bridge,
                           log=ThrottledLog(logger, clock))
    MavlinkBridgeNode._log_events(node)
    assert logger.lines == [('warning', events[0][1]), ('warning', events[1][1])]
