"""ModeGate: which images a perception node processes, from the supervisor's modes."""
import itertools

import pytest

from ibvs_common.core.modes import InputKind, Mode, modes_using
from ibvs_perception.core.mode_gate import ModeGate

MS = 1_000_000
DOWN_FLOW_MODES = (Mode.CROSSING, Mode.LANDING)


def released(items):
    return [(g.stamp_ns // MS, g.publish) for g in items]


def test_the_modes_using_each_product_follow_the_mode_table():
    # the mode table of docs/spec.md section 3: window and wall flow before the crossing, pad
    # (as the LANDING cue in CROSSING) from the crossing on, the floor flow from the
    # crossing on and as the frame clock of SHUTDOWN and FAILSAFE
    assert modes_using(InputKind.WINDOW) == {Mode.IDLE, Mode.WINDOW}
    assert modes_using(InputKind.FLOW_FRONT) == {Mode.WINDOW}
    assert modes_using(InputKind.PAD) == {Mode.CROSSING, Mode.LANDING}
    assert modes_using(InputKind.FLOW_DOWN) == {Mode.CROSSING, Mode.LANDING, Mode.SHUTDOWN,
                                                Mode.FAILSAFE}


def test_every_image_is_processed_before_any_status_and_when_disabled():
    gate = ModeGate(DOWN_FLOW_MODES)
    assert released(gate.on_image(0, 'a')) == [(0, True)]
    off = ModeGate(DOWN_FLOW_MODES, enabled=False)
    assert off.on_status(0, Mode.WINDOW) == []
    assert released(off.on_image(20 * MS, 'b')) == [(20, True)]


def test_before_any_status_the_supervisors_latched_mode_decides():
    """A slow computer's first status comes late: the floor flow must not compute the IDLE
    images before it (ibvs/mode says IDLE), and comes on at the first status that uses it."""
    gate = ModeGate(DOWN_FLOW_MODES, depth=3)
    gate.on_mode(Mode.IDLE)
    assert not gate.active
    assert [gate.on_image(t * MS, t) for t in (0, 20, 40)] == [[], [], []]
    assert gate.on_status(40 * MS, Mode.IDLE) == []           # no change: nothing released
    assert released(gate.on_status(60 * MS, Mode.CROSSING)) == [(40, False)]   # the primer
    assert released(gate.on_image(60 * MS, 60)) == [(60, True)]
    gate.on_mode(Mode.IDLE)                   # after a status, ibvs/mode decides nothing
    assert released(gate.on_image(80 * MS, 80)) == [(80, True)]
    # the ibvs/mode of a switch may come before the switch's status: the status still
    # switches, and releases its image (the wall flow's first WINDOW frame, in lockstep)
    wall = ModeGate((Mode.WINDOW,))
    wall.on_mode(Mode.IDLE)
    assert wall.on_status(0, Mode.IDLE) == [] and wall.on_image(20 * MS, 20) == []
    assert wall.on_image(40 * MS, 40) == []
    wall.on_mode(Mode.WINDOW)
    assert released(wall.on_status(40 * MS, Mode.WINDOW)) == [(20, False), (40, True)]
    # a mode that uses the product, latched before any status: computed at once
    on = ModeGate(DOWN_FLOW_MODES)
    on.on_mode(Mode.LANDING)
    assert released(on.on_image(0, 'a')) == [(0, True)]
    # after a clock step the gate computes every image again until the next status (the
    # latched IDLE of before no longer holds)
    assert gate.on_status(100 * MS, Mode.SHUTDOWN) == [] and gate.on_status(
        120 * MS, Mode.WINDOW) == [] and not gate.active
    assert gate.on_image(10_000 * MS, 'x') == []
    assert released(gate.on_image(8_000 * MS, 'y')) == [(8_000, True)]


def test_images_of_a_mode_that_does_not_use_the_product_are_kept_not_processed():
    gate = ModeGate(DOWN_FLOW_MODES, depth=3)
    assert gate.on_status(0, Mode.WINDOW) == []
    assert [gate.on_image(t * MS, t) for t in (20, 40, 60, 80)] == [[], [], [], []]
    # the switch at 60 ms, when 80 has come already (the status late behind a busy
    # executor): latest only, 80 is published, 60 (the image before it) primes the tracker;
    # 40 and 20 are not computed
    out = gate.on_status(60 * MS, Mode.CROSSING)
    assert released(out) == [(60, False), (80, True)]
    assert [g.item for g in out] == [60, 80]
    assert gate.superseded == 1                              # 60: computed, not published
    assert released(gate.on_image(100 * MS, 100)) == [(100, True)]
    assert gate.on_status(100 * MS, Mode.LANDING) == []     # still on: nothing to release


@pytest.mark.parametrize('status_first', [False, True])
def test_a_switch_processes_the_same_images_whatever_the_arrival_order(status_first):
    # lockstep: the status of frame 60 and the image of frame 60 race; the result must not
    processed = []
    gate = ModeGate(DOWN_FLOW_MODES)
    gate.on_status(0, Mode.WINDOW)
    for t in (20, 40):
        processed += released(gate.on_image(t * MS, t))
    events = [lambda: gate.on_status(60 * MS, Mode.CROSSING),
              lambda: gate.on_image(60 * MS, 60)]
    for event in (reversed(events) if not status_first else events):
        processed += released(event())
    processed += released(gate.on_image(80 * MS, 80))
    # either way: 40 primes the tracker, 60 and 80 are published
    assert processed == [(40, False), (60, True), (80, True)]


def test_after_a_switch_the_newest_image_is_published_whatever_the_interleaving():
    # every order of the events that respects each stream's own order (images in stamp
    # order, statuses in stamp order) publishes 80; 60 too when 80 comes after the switch
    # (lockstep), else 60 may be only its tracker's predecessor (latest only)
    images = [('img', t) for t in (20, 40, 60, 80)]
    statuses = [('st', 0, Mode.WINDOW), ('st', 40, Mode.WINDOW), ('st', 60, Mode.CROSSING)]
    results = set()
    for positions in itertools.combinations(range(len(images) + len(statuses)), len(statuses)):
        order, i, s = [], iter(images), iter(statuses)
        for k in range(len(images) + len(statuses)):
            order.append(next(s) if k in positions else next(i))
        gate = ModeGate(DOWN_FLOW_MODES, depth=4)
        published = []
        for ev in order:
            out = gate.on_status(ev[1] * MS, ev[2]) if ev[0] == 'st' \
                else gate.on_image(ev[1] * MS, ev[1])
            published += [g.stamp_ns // MS for g in out if g.publish]
        # before the first status every image is on: those count as the node's own choice,
        # so compare only the images from the switch on
        results.add(tuple(t for t in published if t >= 60))
        if order.index(('img', 80)) > order.index(statuses[-1]):   # lockstep's order
            assert tuple(t for t in published if t >= 60) == (60, 80)
    assert results == {(60, 80), (80,)}


def test_a_switch_off_stops_processing_from_its_stamp_and_a_late_image_keeps_its_mode():
    gate = ModeGate(DOWN_FLOW_MODES)
    gate.on_status(0, Mode.CROSSING)
    gate.on_status(100 * MS, Mode.SHUTDOWN)
    assert not gate.active
    assert gate.on_image(120 * MS, 'after') == []
    # an image stamped before the switch off, arriving late, was in CROSSING: processed
    assert released(gate.on_image(80 * MS, 'late')) == [(80, True)]
    # a status older than the last switch is out of order and ignored
    assert gate.on_status(90 * MS, Mode.LANDING) == []
    assert not gate.active


def test_after_a_clock_step_back_the_gate_starts_again_instead_of_ignoring_statuses():
    """The front flow, off in IDLE since 10 s, must come on at a start stamped 9.5 s."""
    gate = ModeGate((Mode.WINDOW,))
    gate.on_status(10_000 * MS, Mode.IDLE)           # off from 10 s
    assert gate.on_image(10_020 * MS, 'kept') == []
    # the clock steps back by 1 s: images and statuses stamped from 9.04 s on
    assert released(gate.on_image(9_040 * MS, 'a')) == [(9_040, True)]   # as before any status
    assert gate.on_status(9_040 * MS, Mode.IDLE) == [] and not gate.active
    assert gate.on_image(9_060 * MS, 'b') == []
    assert released(gate.on_status(9_060 * MS, Mode.WINDOW)) == [(9_060, True)]
    assert gate.active
    assert gate.clock_steps == 1                     # the statuses' own go-back: no new reset
    # within MAX_BACKSTEP_S a status out of order is still just ignored
    assert gate.on_status(9_000 * MS, Mode.IDLE) == [] and gate.active


def test_a_depth_below_two_is_refused():
    with pytest.raises(ValueError, match='depth'):
        ModeGate(DOWN_FLOW_MODES, depth=1)
