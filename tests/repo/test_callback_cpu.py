"""benchmarks/callback_cpu.py: what a wrapped callback counts, and the split by mode."""
import inspect
from pathlib import Path
import time

import pytest
from script_module import load_script

LAUNCHER = Path(__file__).resolve().parents[2] / 'benchmarks' / 'callback_cpu.py'


def load():
    return load_script(LAUNCHER, 'callback_cpu')


def test_a_wrapped_callback_counts_its_thread_cpu_not_its_sleep():
    cc = load()
    counter = cc.CallbackCpu()
    seen = []

    def busy(msg, info=None):
        seen.append((msg, info))
        t_end = time.thread_time() + 0.02
        while time.thread_time() < t_end:        # 20 ms of this thread's CPU
            pass
        time.sleep(0.05)                         # waiting is not CPU

    wrapped = counter.wrap('node sub topic', busy)
    # rclpy reads the signature to decide whether to pass a MessageInfo: it must be busy's
    assert list(inspect.signature(wrapped).parameters) == ['msg', 'info']
    wrapped('a')
    wrapped('b', 'info')
    assert seen == [('a', None), ('b', 'info')]
    snapshot = counter.snapshot()
    cells = snapshot['bins']['node sub topic'].values()
    calls, cpu_ns = sum(c[0] for c in cells), sum(c[1] for c in cells)
    assert calls == 2
    assert 0.04 <= cpu_ns / 1e9 < 0.08                # 2 x 20 ms of CPU, not the 100 ms slept
    assert snapshot['threads']['node sub topic'] == 'MainThread'


def test_an_exception_is_counted_and_passed_on():
    counter = load().CallbackCpu()

    def fails():
        raise ValueError('bad')
    with pytest.raises(ValueError):
        counter.wrap('node timer 1 s', fails)()
    assert sum(c[0] for c in counter.snapshot()['bins']['node timer 1 s'].values()) == 1


def test_per_mode_takes_each_bin_by_its_middle():
    cc = load()
    ms = 1_000_000
    # bins of 100 ms: bin 10 is [1000, 1100) ms, its middle 1050 ms
    snapshot = {'bin_ns': 100 * ms, 'process_cpu_s': 0.0, 'threads': {},
                'bins': {'a sub x': {'9': [1, 5], '10': [2, 7], '11': [1, 11], '12': [4, 13]},
                         'b timer 1 s': {'11': [1, 100], '30': [1, 1000]}}}
    # WINDOW from 1040 ms (bin 10's middle is in it), LANDING from 1160 ms (bin 11's middle,
    # 1150, is not), the end at 1240 ms (bin 12's middle, 1250, is after it)
    modes = [(1040 * ms, 'WINDOW'), (1160 * ms, 'LANDING')]
    split = cc.per_mode(snapshot, modes, 1240 * ms)
    assert split == {'WINDOW': {'a sub x': (3, 18), 'b timer 1 s': (1, 100)}, 'LANDING': {}}
