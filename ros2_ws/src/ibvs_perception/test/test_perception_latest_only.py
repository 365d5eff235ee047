"""Latest only: a node behind skips an image once the next one has surely come."""
from collections import deque

import numpy as np

from ibvs_perception.core.latest_only import LatestOnly, LatestOnlyConfig, MIN_IMAGES

MS = 1_000_000
PERIOD = 20 * MS                      # 50 Hz, stride 1


def learnt(delivery_ms=30.0, **config):
    """A LatestOnly that saw MIN_IMAGES images taken ``delivery_ms`` after their stamp."""
    latest = LatestOnly(LatestOnlyConfig(**config))
    for _ in range(MIN_IMAGES):
        latest.observe(int(delivery_ms * MS))
    return latest


def test_nothing_is_skipped_before_the_delivery_latency_is_known():
    latest = LatestOnly(LatestOnlyConfig())
    for _ in range(MIN_IMAGES - 1):
        latest.observe(30 * MS)
    assert latest.delivery_ns is None and not latest.superseded(500 * MS, PERIOD)


def test_an_image_taken_within_a_period_and_the_margin_of_its_delivery_is_computed():
    latest = learnt(30.0)                             # margin 5 ms: up to 55 ms old
    assert latest.delivery_ns == 30 * MS
    assert not any(latest.superseded(a * MS, PERIOD) for a in (30, 45, 55))


def test_older_images_are_skipped_while_the_queue_drains_to_the_newest():
    latest = learnt(30.0)
    # a node 3 frames behind takes them back to back: 90, 70 and 50 ms old
    assert [latest.superseded(a * MS, PERIOD) for a in (90, 70, 50)] == [True, True, False]
    assert [latest.superseded(a * MS, PERIOD) for a in (70, 56)] == [True, True]
    assert latest.relearnt == 0


def test_an_old_image_after_a_skipped_one_as_old_is_computed_and_the_delivery_learnt_again():
    # the camera's delivery went from 30 to 80 ms: the first image is taken for a node behind,
    # the second, as old, shows that no newer one came as fast
    latest = learnt(30.0)
    assert latest.superseded(80 * MS, PERIOD)
    latest.observe(80 * MS)
    assert not latest.superseded(80 * MS, PERIOD) and latest.relearnt == 1
    for _ in range(MIN_IMAGES):
        latest.observe(80 * MS)
    assert latest.delivery_ns == 80 * MS and not latest.superseded(85 * MS, PERIOD)


def test_the_period_is_that_of_the_frames_computed():
    latest = learnt(30.0)
    assert not latest.superseded(70 * MS, 2 * PERIOD)            # stride 2: up to 75 ms
    assert latest.superseded(76 * MS, 2 * PERIOD)


def test_no_image_is_skipped_while_the_ros_clock_waits_for_the_graph():
    # lockstep: the sim's clock stands at the frame's stamp however long the machine takes
    latest = learnt(0.0)
    assert not any(latest.superseded(0, PERIOD) for _ in range(5))


def test_disabled_never_skips():
    assert not learnt(30.0, latest_only=False).superseded(500 * MS, PERIOD)


def computed_ages(latest_only: bool, cost_ms: float, n: int = 500, depth: int = 4,
                  delivery_ms: float = 30.0) -> np.ndarray:
    """Event simulation: a 50 Hz camera delivering ``delivery_ms`` after its stamps into a
    queue of ``depth``, a node computing each image it does not skip in ``cost_ms``; return
    the ages (ms) of the images computed, when taken."""
    latest = LatestOnly(LatestOnlyConfig(latest_only=latest_only))
    queue: deque = deque(maxlen=depth)                 # stamps (ms), oldest first
    stamps = [20.0 * k for k in range(n)]
    t, i, ages = 0.0, 0, []
    while i < n or queue:
        while i < n and stamps[i] + delivery_ms <= t:
            queue.append(stamps[i])
            i += 1
        if not queue:
            t = stamps[i] + delivery_ms
            continue
        age = t - queue.popleft()
        latest.observe(int(age * MS))
        if latest.superseded(int(age * MS), PERIOD):
            continue
        ages.append(age)
        t += cost_ms
    return np.array(ages)


def test_a_node_behind_computes_fresher_images_than_one_that_computes_each():
    # 30 ms per image at 50 Hz: the node keeps up with neither rule
    each = computed_ages(False, 30.0)
    latest = computed_ages(True, 30.0)
    # computing each image in turn, the queue stays full: 3 frames behind the newest
    assert np.median(each) >= 30.0 + 50.0
    # latest only: about a period and the margin after delivery at most (and one cost)
    assert np.median(latest) <= 30.0 + 30.0 and np.percentile(latest, 95) <= 30.0 + 45.0
    assert len(latest) >= 0.9 * len(each)              # and about as many computed


def test_a_node_that_keeps_up_skips_nothing():
    assert len(computed_ages(True, 15.0)) == 500
