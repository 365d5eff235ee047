"""ThrottledLog: one message per call site per period, decided before rclpy is called."""
from ibvs_common.testing import FakeClock, FakeLogger
from ibvs_common.throttled_log import message_kind, ThrottledLog


def make():
    logger, clock = FakeLogger(), FakeClock()
    return ThrottledLog(logger, clock), logger, clock


def test_one_call_site_logs_once_per_period():
    log, logger, clock = make()
    sent = []
    for i in range(5):                       # one call site, five frames 0.5 s apart
        sent.append(log.warning(f'frame {i}', 2.0))
        clock.t += 0.5
    # out at 100.0 s; 100.5-101.5 s are within 2 s of it; 102.0 s is 2 s later: out again
    assert sent == [True, False, False, False, True]
    assert logger.lines == [('warning', 'frame 0'), ('warning', 'frame 4')]


def test_call_sites_are_throttled_apart():
    log, logger, clock = make()
    for _ in range(3):
        log.error('a', 10.0)
        log.error('b', 10.0)
        log.info('c', 10.0)
    assert logger.lines == [('error', 'a'), ('error', 'b'), ('info', 'c')]


def test_a_period_of_zero_logs_every_call():
    log, logger, _ = make()
    for i in range(3):
        log.info(str(i), 0.0)
    assert [text for _, text in logger.lines] == ['0', '1', '2']


def test_different_texts_from_one_call_site_share_its_throttle_as_in_rclpy():
    log, logger, clock = make()

    def report(text):
        log.error(text, 1.0)                 # one call site for every text

    report('first')
    report('second')
    clock.t += 1.0
    report('third')
    assert [text for _, text in logger.lines] == ['first', 'third']


def test_a_key_throttles_by_kind_instead_of_by_call_site():
    log, logger, clock = make()
    texts = ['setpoint source none -> level_hover', 'PX4 offboard loss: COM_OBL_RC_ACT = 0',
             'imu/data: 3 sample(s) dropped (40 in all)',
             'imu/data: 5 sample(s) dropped (45 in all)']
    for text in texts:                       # one call site, as the bridge's event relay
        log.warning(text, 2.0, key=message_kind(text))
    # the one-off warning is not held back by the one before it; the two counts are one kind
    assert [t for _, t in logger.lines] == texts[:3]
    clock.t += 2.0
    assert log.warning(texts[3], 2.0, key=message_kind(texts[3]))


def test_message_kind_replaces_numbers_only():
    assert message_kind('x 1.5e-3 s, -2 m, +7 (v1.16)') == 'x # s, # m, # (v#)'
    assert message_kind('no numbers') == 'no numbers'
