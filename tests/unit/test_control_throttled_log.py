"""ThrottledLog: one message per call site per period, decided before rclpy is called."""
from ibvs_common.throttled_log import ThrottledLog


class FakeLogger:
    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(('info', text))

    def warning(self, text):
        self.lines.append(('warning', text))

    def error(self, text):
        self.lines.append(('error', text))


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


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
