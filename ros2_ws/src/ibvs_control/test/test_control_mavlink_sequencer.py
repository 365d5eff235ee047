"""The engage / arm / hand-back state machine alone (no I/O): inputs in, commands out.

Expected commands from the MAVLink / PX4 / ArduPilot documentation: DO_SET_MODE (176) with
param1 = 1 and PX4 main mode 6 (OFFBOARD) / main 4 sub 6 (AUTO.LAND), ArduCopter modes 20
(GUIDED_NOGPS) and 9 (LAND); COMPONENT_ARM_DISARM (400), force magic 21196.
"""
from dataclasses import replace

import pytest

from ibvs_control.mavlink.sequencer import (
    Autopilot, engage_sequencer, EngageState, MavCmd, MavResult, SequencerConfig,
    SequencerInputs)
from ibvs_common.core.modes import Mode

OFFBOARD, POSCTL, AUTO_LAND = 6 << 16, 3 << 16, (4 << 16) | (6 << 24)
GUIDED_NOGPS, GUIDED, LAND = 20, 4, 9


class Rig:
    """A sequencer and the inputs of one step, stepped at 10 ms."""

    def __init__(self, autopilot=Autopilot.PX4, **cfg):
        self.seq = engage_sequencer(autopilot, SequencerConfig(prestream_s=1.0,
                                                               command_retry_s=1.0, **cfg))
        self.inp = SequencerInputs(t=0.0, link_up=True, supervisor_mode=Mode.IDLE,
                                   idle_reports=1, armed=True,
                                   custom_mode=POSCTL if autopilot == Autopilot.PX4 else 0,
                                   streaming_s=5.0, hover_thrust_ready=True, guid_options=8,
                                   armable=True, landed=False)
        self.sent = []                           # (t, CommandRequest)

    def step(self, **changes):
        self.inp = replace(self.inp, **changes)
        out = self.seq.step(self.inp)
        self.sent += [(self.inp.t, c) for c in out]
        return out

    def run(self, seconds, **changes):
        end = self.inp.t + seconds
        while self.inp.t < end - 1e-9:
            self.step(t=round(self.inp.t + 0.01, 6), **changes)
            changes = {}

    def commands(self, command, param1=None):
        return [(t, c) for t, c in self.sent if c.command == command
                and (param1 is None or c.params[0] == param1)]

    def engage_disarmed(self, armable, arm=True):
        """Disarmed in the autopilot's own mode (ArduPilot STABILIZE) with ``armable``; WINDOW."""
        self.step(armed=False, armable=armable, custom_mode=0)
        if arm:
            assert self.seq.request_arm()[0]
        self.step(supervisor_mode=Mode.WINDOW)

    def engage(self):
        self.step(supervisor_mode=Mode.WINDOW)
        assert self.seq.state == EngageState.SET_MODE
        self.step(custom_mode=OFFBOARD if self.seq.strategy.autopilot == Autopilot.PX4
                  else GUIDED_NOGPS)
        assert self.seq.state == EngageState.ENGAGED


def test_px4_standby_streams_ardupilot_does_not():
    px4, ap = Rig(), Rig(Autopilot.ARDUPILOT)
    px4.step()
    ap.step()
    assert px4.seq.state == ap.seq.state == EngageState.STANDBY
    assert px4.seq.streaming and not ap.seq.streaming
    ap.step(supervisor_mode=Mode.WINDOW)
    assert ap.seq.streaming                      # from the switch on
    [c] = ap.sent
    assert c[1].params == (1.0, 20.0)


def test_never_arms_unless_asked_then_waits_for_armable_and_backs_off():
    r = Rig(arm_backoff_max_s=4.0)
    r.step(armed=False)
    r.step(supervisor_mode=Mode.WINDOW)
    r.step(custom_mode=OFFBOARD)
    r.run(5.0)
    assert r.seq.state == EngageState.WAIT_ARM and r.commands(MavCmd.COMPONENT_ARM_DISARM) == []
    assert r.seq.streaming                       # PX4 stays in OFFBOARD with the stream
    ok, _ = r.seq.request_arm()
    assert ok
    r.run(2.0, armable=False)
    assert r.seq.state == EngageState.ARMING and r.commands(MavCmd.COMPONENT_ARM_DISARM) == []
    r.inp = replace(r.inp, armable=True)
    t0 = r.inp.t
    r.run(12.0)                                  # refused (never armed): 1, 2, 4, 4 s apart
    times = [t - t0 for t, _ in r.commands(MavCmd.COMPONENT_ARM_DISARM, 1.0)]
    assert times == pytest.approx([0.01, 1.01, 3.01, 7.01, 11.01], abs=0.011)
    r.seq.on_command_ack(400, MavResult.TEMPORARILY_REJECTED)
    r.step(t=r.inp.t + 0.01, armed=True)
    assert r.seq.state == EngageState.ENGAGED and not r.seq.arm_requested


def test_an_accepted_arm_is_not_sent_again_before_the_heartbeat_can_show_it():
    # PX4 SITL acknowledged ARM at once but its 1 Hz HEARTBEAT showed armed only 1.0-1.5 s
    # later: a retry after command_retry_s sent a second ARM; ACCEPTED waits the longest backoff
    r = Rig(arm_backoff_max_s=4.0)
    r.step(armed=False)
    r.step(supervisor_mode=Mode.WINDOW)
    r.step(custom_mode=OFFBOARD)
    assert r.seq.request_arm()[0]
    r.step(t=r.inp.t + 0.01)
    t0 = r.inp.t
    assert len(r.commands(MavCmd.COMPONENT_ARM_DISARM, 1.0)) == 1
    r.seq.on_command_ack(400, MavResult.ACCEPTED)
    r.run(3.9)                                   # not armed yet: no second ARM before 4 s
    assert len(r.commands(MavCmd.COMPONENT_ARM_DISARM, 1.0)) == 1
    r.run(0.2)                                   # accepted but never armed: sent again at 4 s
    times = [t - t0 for t, _ in r.commands(MavCmd.COMPONENT_ARM_DISARM, 1.0)]
    assert times == pytest.approx([0.0, 4.0], abs=0.011)
    r.step(t=r.inp.t + 0.01, armed=True)
    assert r.seq.state == EngageState.ENGAGED


def test_arming_gives_up_after_arm_timeout():
    r = Rig(arm_timeout_s=3.0)
    r.step(armed=False)
    r.seq.request_arm()
    r.step(supervisor_mode=Mode.WINDOW)
    r.step(custom_mode=OFFBOARD)
    r.run(3.5)
    assert r.seq.state == EngageState.FAILED
    assert r.seq.request_arm()[0] is False


def test_ardupilot_no_mode_switch_before_it_is_armable():
    # ArduCopter SITL in a fresh-clone CI run: GUIDED_NOGPS set 1.5 s after boot, then its RC
    # input turned valid and it applied its mode switch (STABILIZE): the bridge saw a takeover
    r = Rig(Autopilot.ARDUPILOT)
    r.engage_disarmed(armable=False)
    r.run(3.0)
    assert r.seq.state == EngageState.SET_MODE and r.sent == []
    assert any('armable' in e and 'before switching' in e for e in r.seq.pop_events())
    assert 'armable' in r.seq.last_reason        # what /diagnostics shows meanwhile
    assert not r.seq.streaming                   # ArduPilot: setpoints from the switch on
    r.run(1.0, custom_mode=2)                    # the autopilot picks a mode of its own: fine
    assert r.seq.state == EngageState.SET_MODE and r.sent == []
    r.step(t=r.inp.t + 0.01, armable=True)       # ready: switch, then arm
    assert r.seq.streaming
    [(_, c)] = r.commands(MavCmd.DO_SET_MODE)
    assert c.params == (1.0, 20.0)
    r.step(t=r.inp.t + 0.01, custom_mode=GUIDED_NOGPS)
    assert r.seq.state == EngageState.ARMING and len(r.commands(MavCmd.COMPONENT_ARM_DISARM)) == 1


def test_px4_switches_to_offboard_even_when_not_armable_in_the_pilots_mode():
    # PX4's pre-arm bit is canArm(current nav_state): Position mode without a position
    # estimate (indoors) is never armable, OFFBOARD attitude is; so PX4 switches, then waits
    r = Rig()
    r.step(armed=False, armable=False)
    assert r.seq.request_arm()[0]
    r.step(supervisor_mode=Mode.WINDOW)
    r.step(t=r.inp.t + 0.01)
    [(_, c)] = r.commands(MavCmd.DO_SET_MODE)     # at once (its stream ran > prestream_s)
    assert c.params[1] == 6.0 and r.seq.streaming
    r.step(t=r.inp.t + 0.01, custom_mode=OFFBOARD)
    r.run(1.0)
    assert r.seq.state == EngageState.ARMING and r.commands(MavCmd.COMPONENT_ARM_DISARM) == []
    r.run(0.5, armable=True)
    assert len(r.commands(MavCmd.COMPONENT_ARM_DISARM)) == 1


def test_no_pre_arm_report_yet_waits_for_one_then_tries():
    # fresh-clone CI again: the switch went out 0.05 s before ArduPilot's first SYS_STATUS
    r = Rig(Autopilot.ARDUPILOT, armable_unknown_wait_s=1.0)
    r.engage_disarmed(armable=None)
    r.run(0.5)
    assert r.sent == [] and r.seq.state == EngageState.SET_MODE
    r.step(t=r.inp.t + 0.01, armable=False)             # the report: not armable, wait on
    r.run(2.0)
    assert r.sent == []
    r.step(t=r.inp.t + 0.01, armable=True)
    assert [c.params for _, c in r.sent] == [(1.0, 20.0)]
    # an autopilot that never reports the bit: tried after armable_unknown_wait_s
    r = Rig(Autopilot.ARDUPILOT, armable_unknown_wait_s=1.0)
    r.engage_disarmed(armable=None, arm=False)
    r.run(0.95)
    assert r.sent == []
    r.run(0.1)
    assert [c.params for _, c in r.sent] == [(1.0, 20.0)]


def test_never_armable_with_an_arm_request_fails_after_arm_timeout_without_a_switch():
    r = Rig(Autopilot.ARDUPILOT, arm_timeout_s=3.0)
    r.engage_disarmed(armable=False)
    r.run(2.9)
    assert r.seq.state == EngageState.SET_MODE
    r.run(0.2)
    assert r.seq.state == EngageState.FAILED and 'not armable' in r.seq.last_reason
    assert r.sent == []


def test_a_second_engagement_arms_on_its_own_timer():
    # the arming timer of the first engagement must not time out the second one's
    r = Rig(arm_timeout_s=5.0)
    r.step(armed=False)
    assert r.seq.request_arm()[0]
    r.step(supervisor_mode=Mode.WINDOW)
    r.step(custom_mode=OFFBOARD)
    assert r.seq.state == EngageState.ARMING
    r.step(t=r.inp.t + 0.5, armed=True)
    assert r.seq.state == EngageState.ENGAGED
    r.step(t=r.inp.t + 0.01, custom_mode=POSCTL)          # the pilot takes over, lands
    assert r.seq.state == EngageState.HELD
    r.step(t=r.inp.t + 30.0, armed=False, supervisor_mode=Mode.IDLE, idle_reports=2)
    assert r.seq.state == EngageState.STANDBY
    assert r.seq.request_arm()[0]
    r.step(t=r.inp.t + 0.01, supervisor_mode=Mode.WINDOW)
    r.step(t=r.inp.t + 0.01, custom_mode=OFFBOARD)
    assert r.seq.state == EngageState.ARMING, r.seq.last_reason
    assert len(r.commands(MavCmd.COMPONENT_ARM_DISARM, 1.0)) == 2


def test_no_engagement_without_idle_and_not_again_after_a_takeover_until_idle():
    r = Rig()
    r.step(idle_reports=0, supervisor_mode=Mode.WINDOW)
    assert r.seq.state == EngageState.STANDBY     # bridge started mid-flight: no takeover
    r.step(idle_reports=1)
    assert r.seq.state == EngageState.SET_MODE
    r.step(custom_mode=OFFBOARD)
    r.step(custom_mode=POSCTL)                    # the pilot takes POSCTL
    assert r.seq.state == EngageState.HELD and not r.seq.streaming
    r.run(3.0)
    assert len(r.commands(MavCmd.DO_SET_MODE)) == 1
    r.step(supervisor_mode=Mode.IDLE, idle_reports=2)
    assert r.seq.state == EngageState.STANDBY
    r.step(supervisor_mode=Mode.WINDOW)
    assert r.seq.state == EngageState.SET_MODE


def test_offboard_entered_without_the_bridge_asking_is_not_flown():
    r = Rig()
    r.step()
    r.step(custom_mode=OFFBOARD)                  # a GCS switched to OFFBOARD during standby
    assert r.seq.state == EngageState.HELD and not r.seq.streaming


@pytest.mark.parametrize('autopilot, action, land_params', [
    (Autopilot.PX4, 'auto', None), (Autopilot.ARDUPILOT, 'auto', (1.0, 9.0)),
    (Autopilot.PX4, 'land', (1.0, 4.0, 6.0)), (Autopilot.ARDUPILOT, 'stop', None)])
def test_inputs_lost_stops_the_stream_or_lands(autopilot, action, land_params):
    r = Rig(autopilot, input_loss_action=action)
    r.engage()
    r.step(inputs_lost=True)
    if land_params is None:
        assert r.seq.state == EngageState.HELD and not r.seq.streaming
        assert 'offboard-loss failsafe' in r.seq.last_reason
    else:
        assert r.seq.state == EngageState.LANDING and r.seq.streaming and r.seq.level_hold
        assert r.sent[-1][1].params == land_params


@pytest.mark.parametrize('custom_mode, lands', [(OFFBOARD, True), (AUTO_LAND, False),
                                                (POSCTL, False)])
def test_failsafe_just_after_a_loss_stop_lands_while_the_autopilot_is_still_offboard(
        custom_mode, lands):
    """A dead camera stops the forces and goes stale at one instant (hold_last_s = the
    staleness timeouts): the bridge may stop the stream before the supervisor's FAILSAFE
    reaches it (a CI run: 14 ms apart, PX4 then flew the last setpoint 1 s more, 0.7 m towards
    the wall). While PX4 is still armed in OFFBOARD nobody else has the vehicle: land mode.
    Once its own failsafe or the pilot has it, the bridge stays out."""
    r = Rig()
    r.engage()
    r.step(t=r.inp.t + 0.01, inputs_lost=True)
    assert r.seq.state == EngageState.HELD and not r.seq.streaming
    r.step(t=r.inp.t + 0.01, custom_mode=custom_mode, supervisor_mode=Mode.FAILSAFE)
    if lands:
        assert r.seq.state == EngageState.LANDING and r.seq.streaming and r.seq.level_hold
        assert r.sent[-1][1].params == (1.0, 4.0, 6.0)
    else:
        assert r.seq.state == EngageState.HELD and not r.seq.streaming
        assert len(r.commands(MavCmd.DO_SET_MODE)) == 1           # the engagement's only
    # a HELD of another cause (the pilot took POSCTL) never lands on a FAILSAFE
    r = Rig()
    r.engage()
    r.step(t=r.inp.t + 0.01, custom_mode=POSCTL)
    r.step(t=r.inp.t + 0.01, custom_mode=OFFBOARD, supervisor_mode=Mode.FAILSAFE)
    assert r.seq.state == EngageState.HELD and len(r.commands(MavCmd.DO_SET_MODE)) == 1


@pytest.mark.parametrize('autopilot, land_params', [(Autopilot.PX4, (1.0, 4.0, 6.0)),
                                                    (Autopilot.ARDUPILOT, (1.0, 9.0))])
def test_failsafe_after_the_offboard_switch_was_asked_lands_before_its_heartbeat(
        autopilot, land_params):
    """The switch may have taken effect before a HEARTBEAT shows it (PX4: 1 Hz): a FAILSAFE
    then asks for the land mode rather than leaving the autopilot in a mode without setpoints.
    A FAILSAFE before any switch was asked leaves the vehicle where it is (HELD)."""
    r = Rig(autopilot)
    r.step(heartbeat_t=0.0, supervisor_mode=Mode.WINDOW)
    assert r.seq.state == EngageState.SET_MODE and len(r.commands(MavCmd.DO_SET_MODE)) == 1
    r.run(0.3)
    r.step(t=r.inp.t + 0.01, supervisor_mode=Mode.FAILSAFE)
    assert r.seq.state == EngageState.LANDING and r.seq.level_hold and r.seq.streaming
    assert r.sent[-1][1].params == land_params
    r = Rig(autopilot)
    r.step(streaming_s=0.0, supervisor_mode=Mode.WINDOW)     # PX4: prestream not done yet
    if autopilot == Autopilot.PX4:
        assert r.seq.state == EngageState.SET_MODE and not r.commands(MavCmd.DO_SET_MODE)
        r.step(t=r.inp.t + 0.01, supervisor_mode=Mode.FAILSAFE)
        assert r.seq.state == EngageState.HELD and not r.commands(MavCmd.DO_SET_MODE)


@pytest.mark.parametrize('autopilot, land_mode', [(Autopilot.PX4, AUTO_LAND),
                                                  (Autopilot.ARDUPILOT, LAND)])
def test_failsafe_lands_in_the_autopilots_mode_then_stops_and_disarms_when_landed(
        autopilot, land_mode):
    r = Rig(autopilot)
    r.engage()
    r.step(supervisor_mode=Mode.FAILSAFE)
    assert r.seq.state == EngageState.LANDING and r.seq.level_hold and r.seq.streaming
    r.run(0.5)
    assert len(r.commands(MavCmd.DO_SET_MODE)) == 2          # engage + land, not repeated
    r.step(t=r.inp.t + 0.01, custom_mode=land_mode)
    assert not r.seq.streaming                               # the autopilot lands
    r.run(1.0, landed=True)
    [(_, c)] = r.commands(MavCmd.COMPONENT_ARM_DISARM)       # backup plain disarm
    assert c.params == (0.0,)
    r.step(t=r.inp.t + 0.01, armed=False)
    assert r.seq.state == EngageState.DONE


def test_land_mode_refused_five_times_stops_streaming():
    r = Rig()
    r.engage()
    r.step(supervisor_mode=Mode.FAILSAFE)
    r.run(6.0)
    assert r.seq.state == EngageState.HELD and not r.seq.streaming
    assert len(r.commands(MavCmd.DO_SET_MODE)) == 1 + 5


def test_a_mode_switch_is_judged_only_on_a_heartbeat_sent_after_it():
    """An attempt counts as failed only once a HEARTBEAT came after it: a firmware in
    lockstep at 0.13 x real time reports its mode at 1 Hz of its own clock, 7.7 s of this
    one; without this rule its five attempts ran out before any report. With HEARTBEATs
    that keep the old mode, FAILED after max_attempts as before."""
    r = Rig()
    r.step(heartbeat_t=0.0, supervisor_mode=Mode.WINDOW)
    assert r.seq.state == EngageState.SET_MODE and len(r.commands(MavCmd.DO_SET_MODE)) == 1
    r.run(7.0)                                   # no HEARTBEAT since the first attempt
    assert r.seq.state == EngageState.SET_MODE and len(r.commands(MavCmd.DO_SET_MODE)) == 1
    r.step(t=r.inp.t + 0.01, heartbeat_t=r.inp.t + 0.01, custom_mode=OFFBOARD)
    assert r.seq.state == EngageState.ENGAGED
    # HEARTBEATs at 2 Hz that keep the old mode: five attempts, then FAILED
    r = Rig()
    r.step(heartbeat_t=0.0, supervisor_mode=Mode.WINDOW)
    while r.seq.state == EngageState.SET_MODE and r.inp.t < 10.0:
        t = round(r.inp.t + 0.01, 6)
        r.step(t=t, heartbeat_t=t if round(t * 100) % 50 == 0 else r.inp.heartbeat_t)
    assert r.seq.state == EngageState.FAILED and len(r.commands(MavCmd.DO_SET_MODE)) == 5


def test_shutdown_disarm_plain_first_forced_only_under_the_touchdown_rule():
    r = Rig(disarm_force_after_s=1.0)
    r.engage()
    r.step(supervisor_mode=Mode.SHUTDOWN)
    assert r.seq.state == EngageState.SHUTDOWN_RAMP
    r.step(t=r.inp.t + 0.01, ramp_done=True)
    assert r.seq.state == EngageState.DISARMING
    [(t_first, c)] = r.commands(MavCmd.COMPONENT_ARM_DISARM)
    assert c.params == (0.0,)
    r.seq.on_command_ack(400, MavResult.TEMPORARILY_REJECTED)   # "not landed"
    r.run(3.0, touchdown=False)                  # no evidence: plain retries only, 1 s apart
    plain = r.commands(MavCmd.COMPONENT_ARM_DISARM)
    assert len(plain) >= 3 and all(c.params == (0.0,) for _, c in plain)
    r.seq.on_command_ack(400, MavResult.TEMPORARILY_REJECTED)
    r.run(1.0, touchdown=True)
    last_t, last = r.commands(MavCmd.COMPONENT_ARM_DISARM)[-1]
    assert last.params == (0.0, 21196.0) and r.seq.disarm_forced
    assert last_t - t_first >= 1.0 and last_t - plain[-1][0] >= 1.0 - 1e-9
    r.step(t=r.inp.t + 0.01, armed=False)
    assert r.seq.state == EngageState.DONE and 'forced' in r.seq.last_reason


def test_disarm_never_forced_without_a_refusal_and_lands_after_the_timeout():
    r = Rig(disarm_timeout_s=3.0)
    r.engage()
    r.step(supervisor_mode=Mode.SHUTDOWN)
    r.step(t=r.inp.t + 0.01, ramp_done=True)
    r.run(2.9, touchdown=True)                   # accepted, never effective, never refused
    assert all(c.params == (0.0,) for _, c in r.commands(MavCmd.COMPONENT_ARM_DISARM))
    r.run(0.2)
    assert r.seq.state == EngageState.LANDING
    assert r.sent[-1][1].params == (1.0, 4.0, 6.0)


def test_shutdown_in_the_air_lands_instead():
    r = Rig()
    r.engage()
    r.step(supervisor_mode=Mode.SHUTDOWN)
    r.step(t=r.inp.t + 0.01, airborne_at_low_thrust=True)
    assert r.seq.state == EngageState.LANDING
    assert r.commands(MavCmd.COMPONENT_ARM_DISARM) == []


@pytest.mark.parametrize('armed, landed, custom_mode, state', [
    (False, True, POSCTL, EngageState.DONE),
    (True, True, OFFBOARD, EngageState.DISARMING),
    (True, False, AUTO_LAND, EngageState.LANDING),
    (True, False, OFFBOARD, EngageState.LANDING)])
def test_link_lost_during_the_shutdown_ends_disarmed_or_landing(armed, landed, custom_mode,
                                                                state):
    r = Rig()
    r.engage()
    r.step(supervisor_mode=Mode.SHUTDOWN)
    r.step(t=r.inp.t + 0.01, link_up=False)
    assert r.seq.state == EngageState.NO_LINK
    r.run(1.0)
    r.step(t=r.inp.t + 0.01, link_up=True, armed=armed, landed=landed,
           custom_mode=custom_mode)
    assert r.seq.state == state
    if state == EngageState.DISARMING:
        assert r.sent[-1][1].params == (0.0,)


def test_link_back_after_a_loss_in_flight_is_held_never_reengaged():
    r = Rig()
    r.engage()
    r.step(t=r.inp.t + 0.01, link_up=False)
    r.step(t=r.inp.t + 1.0, link_up=True, custom_mode=AUTO_LAND)   # PX4's failsafe
    assert r.seq.state == EngageState.HELD
    r.run(2.0)
    assert len(r.commands(MavCmd.DO_SET_MODE)) == 1
