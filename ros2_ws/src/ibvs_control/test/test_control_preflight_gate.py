"""ibvs/start and the preflight's verdict: refused on a no-go, accepted on a go or overridden.

The gate alone (``core.preflight_gate``), the ibvs/preflight message (``node_common``), and
the supervisor node with real rclpy: a verdict published latched as the preflight does.
"""
import numpy as np
from rclpy.parameter import Parameter

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from ibvs_common.node_common import (MODE_QOS, PREFLIGHT_TOPIC, preflight_verdict,
                                     preflight_verdict_msg)
from ibvs_control.core.preflight_gate import PreflightGate
from ibvs_control.mode_supervisor_node import ModeSupervisorNode

from test_control_nodes import call, Feeder, spin_until, TAG  # noqa: E402

NO_GO = 'PREFLIGHT NO-GO: 1 of 15 checks failed: autopilot failsafe when the bridge stops'
GO = 'PREFLIGHT GO: 15 checks passed'


def test_the_gate_refuses_only_on_a_no_go_unless_overridden():
    gate = PreflightGate(required=True)
    assert gate.refusal() is None                         # no verdict: not refused
    assert 'no preflight verdict' in gate.note()
    gate.on_verdict(False, NO_GO, 3.0)
    refusal = gate.refusal()
    assert refusal.startswith('preflight no-go: ' + NO_GO) and 'require_preflight_go' in refusal
    gate.on_verdict(True, GO, 4.0)                        # the preflight run again: go
    assert gate.refusal() is None and gate.note() is None
    gate.on_verdict(None, "no 'preflight' status", 5.0)   # unreadable: a no-go
    assert "unreadable preflight verdict (no 'preflight' status)" in gate.refusal()
    override = PreflightGate(required=False)
    override.on_verdict(False, NO_GO, 3.0)
    assert override.refusal() is None
    assert override.note() == ('preflight no-go overridden (require_preflight_go: false): '
                               + NO_GO)


def test_a_go_older_than_its_maximum_age_refuses_the_start():
    gate = PreflightGate(required=True, max_age_s=900.0)
    gate.on_verdict(True, GO, 100.0)
    assert gate.refusal(now=1000.0) is None                 # 900 s old: still valid
    refusal = gate.refusal(now=1000.5)
    assert refusal.startswith('preflight go is 900 s old (preflight_max_age_s 900 s)')
    assert 'run the preflight again' in refusal
    assert gate.refusal() is None                           # no time given: age not judged
    assert PreflightGate(required=True).refusal(now=1e9) is None   # 0: a go never expires
    override = PreflightGate(required=False, max_age_s=1.0)
    override.on_verdict(True, GO, 0.0)
    assert override.refusal(now=50.0) is None


def test_the_verdict_message_round_trips_and_a_bad_one_is_unreadable():
    msg = preflight_verdict_msg(False, NO_GO, [('armed or armable', 'OK: armed')], 7_000_000_000)
    assert preflight_verdict(msg) == (False, NO_GO)
    assert msg.header.stamp.sec == 7 and msg.status[0].values[0].value == 'OK: armed'
    assert preflight_verdict(preflight_verdict_msg(True, GO, [], 0)) == (True, GO)
    warn = DiagnosticArray(status=[DiagnosticStatus(name='preflight', level=DiagnosticStatus.WARN,
                                                    message='?')])
    go, why = preflight_verdict(warn)
    assert go is None and 'neither OK (go) nor ERROR (no-go)' in why
    assert preflight_verdict(DiagnosticArray()) == (None, "no 'preflight' status")


def _supervisor(ctx, suffix, *overrides):
    """A supervisor on sim time, a Feeder and a latched verdict publisher; IDLE seen."""
    context, executor, nodes = ctx
    sup = ModeSupervisorNode(node_name=f'sup_gate{suffix}_{TAG}', context=context,
                             parameter_overrides=[Parameter('use_sim_time', value=True),
                                                  *overrides])
    feed = Feeder(context, f'feed_gate{suffix}_{TAG}')
    verdict = feed.node.create_publisher(DiagnosticArray, PREFLIGHT_TOPIC, MODE_QOS)
    nodes += [sup, feed.node]
    executor.add_node(sup)
    executor.add_node(feed.node)
    assert spin_until(executor, lambda: feed.modes == [0], 5.0)
    return sup, feed, verdict


def _window_in_view(executor, feed, t0=1.0, frames=10):
    """Publish ``frames`` frames with the whole window in view (what a start needs)."""
    xi = np.array([-2.0, 0.0, -1.6])
    for k in range(frames):
        n = len(feed.statuses)
        feed.frame(t0 + 0.02 * k, xi, front_flow=np.zeros(3))
        assert spin_until(executor, lambda: len(feed.statuses) > n, 2.0)
    return t0 + 0.02 * frames, xi


def _latest_verdict_is(executor, sup, go):
    return spin_until(executor, lambda: sup._preflight.verdict is not None
                      and sup._preflight.verdict.go is go, 5.0)


def test_ibvs_start_is_refused_on_a_no_go_and_accepted_on_a_go(ctx):
    _, executor, _ = ctx
    sup, feed, verdict = _supervisor(ctx, '_on')
    t, xi = _window_in_view(executor, feed)
    verdict.publish(preflight_verdict_msg(False, NO_GO, [], 1))
    assert _latest_verdict_is(executor, sup, False)
    res = call(executor, feed.node, 'ibvs/start')
    assert not res.success and res.message.startswith('preflight no-go: ' + NO_GO), res.message
    feed.frame(t, xi, front_flow=np.zeros(3))               # a frame after the refused start
    assert spin_until(executor, lambda: len(feed.statuses) >= 11, 2.0)
    assert feed.modes == [0]                                 # still IDLE: nothing engages
    verdict.publish(preflight_verdict_msg(True, GO, [], 2))  # fixed, the preflight run again
    assert _latest_verdict_is(executor, sup, True)
    assert call(executor, feed.node, 'ibvs/start').success
    feed.frame(t + 0.02, xi, front_flow=np.zeros(3))
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)


def test_ibvs_start_goes_on_over_a_no_go_when_overridden(ctx):
    _, executor, _ = ctx
    sup, feed, verdict = _supervisor(ctx, '_off', Parameter('require_preflight_go', value=False))
    t, xi = _window_in_view(executor, feed)
    verdict.publish(preflight_verdict_msg(False, NO_GO, [], 1))
    assert _latest_verdict_is(executor, sup, False)
    res = call(executor, feed.node, 'ibvs/start')
    assert res.success, res.message
    feed.frame(t, xi, front_flow=np.zeros(3))
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)


def test_an_unreadable_verdict_refuses_the_start(ctx):
    _, executor, _ = ctx
    sup, feed, verdict = _supervisor(ctx, '_bad')
    _window_in_view(executor, feed)
    verdict.publish(DiagnosticArray(status=[DiagnosticStatus(name='something else')]))
    assert _latest_verdict_is(executor, sup, False)
    res = call(executor, feed.node, 'ibvs/start')
    assert not res.success and 'unreadable preflight verdict' in res.message, res.message


def test_ibvs_start_is_refused_on_a_go_older_than_preflight_max_age_s(ctx):
    """The go's age is the node's clock (here sim time, /clock from the frames) between the
    verdict's arrival and the start."""
    _, executor, _ = ctx
    sup, feed, verdict = _supervisor(ctx, '_age', Parameter('preflight_max_age_s', value=0.1))
    _window_in_view(executor, feed, t0=1.0, frames=2)
    verdict.publish(preflight_verdict_msg(True, GO, [], 1))
    assert _latest_verdict_is(executor, sup, True)
    t, xi = _window_in_view(executor, feed, t0=1.1, frames=10)     # 0.2 s of frames later
    res = call(executor, feed.node, 'ibvs/start')
    assert not res.success and res.message.startswith('preflight go is 0 s old '
                                                      '(preflight_max_age_s 0.1 s)'), res.message
    verdict.publish(preflight_verdict_msg(True, GO, [], 2))   # the preflight run again
    assert spin_until(executor, lambda: sup._preflight.verdict.t >= t - 0.02, 5.0)
    assert call(executor, feed.node, 'ibvs/start').success
    feed.frame(t, xi, front_flow=np.zeros(3))
    assert spin_until(executor, lambda: feed.modes[-1:] == [1], 2.0)
