"""SIGINT / SIGTERM end ibvs_common.spin's spin between callbacks, the rclpy context still valid.

Each case runs a node in a fresh process, initialised as every node's ``main()`` does (rclpy's
own signal handlers installed by ``rclpy.init``), publishing from a 500 Hz timer; the timer
sends the signal to its own process after 50 ticks, i.e. in the middle of the work. With
rclpy's handlers the context was shut down under the running callback ("publisher's context is
invalid"); here the spin returns, the node still publishes, and is destroyed in order.
"""
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent('''
    import os, signal, sys
    import rclpy
    from std_msgs.msg import String
    from ibvs_common.spin import spin_guarded
    rclpy.init()
    node = rclpy.create_node('spin_stop_' + str(os.getpid()))
    pub = node.create_publisher(String, 'spin_stop_test', 10)
    ticks = [0]
    def tick():
        ticks[0] += 1
        pub.publish(String(data=str(ticks[0])))
        if ticks[0] == 50:
            os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    node.create_timer(0.002, tick)
    spin_guarded(node)
    pub.publish(String(data='after'))          # raises if the context was shut down
    print(f'returned ok={rclpy.ok()} ticks={ticks[0]}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
''')


@pytest.mark.parametrize('sig', ['SIGINT', 'SIGTERM'])
def test_a_stop_signal_ends_the_spin_with_the_context_still_valid(sig):
    proc = subprocess.run([sys.executable, '-c', SCRIPT, sig], capture_output=True, text=True,
                          timeout=60)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert 'returned ok=True' in proc.stdout, out
    ticks = int(proc.stdout.split('ticks=')[1].split()[0])
    assert 50 <= ticks <= 100, out                # stopped soon after the signal
    for bad in ('Exception', 'Traceback', 'context is invalid', 'FATAL'):
        assert bad not in out, out


GROUPS_SCRIPT = textwrap.dedent('''
    import os, signal, sys, time
    import rclpy
    from ibvs_common.spin import spin_guarded_groups
    rclpy.init()
    busy = rclpy.create_node('busy_' + str(os.getpid()))
    quick = rclpy.create_node('quick_' + str(os.getpid()))
    ticks = {'busy': 0, 'quick': 0}
    gaps = []
    last = [None]
    def busy_tick():                # an image callback that takes 50 ms, 20 times a second
        ticks['busy'] += 1
        time.sleep(0.05)
    def quick_tick():               # a 100 Hz control callback
        now = time.monotonic()
        if last[0] is not None:
            gaps.append(now - last[0])
        last[0] = now
        ticks['quick'] += 1
        if sys.argv[1] == 'raise' and ticks['quick'] == 30:
            raise ValueError('a control callback failed')
        if ticks['quick'] == 100:
            os.kill(os.getpid(), signal.SIGINT)
    busy.create_timer(0.05, busy_tick)
    quick.create_timer(0.01, quick_tick)
    try:
        spin_guarded_groups([[busy], [quick]])
    except ValueError as exc:
        print(f'raised {exc}', flush=True)
    gaps.sort()
    print(f'returned busy={ticks["busy"]} quick={ticks["quick"]} '
          f'gap_p90={gaps[int(0.9 * len(gaps))]:.4f}', flush=True)
    busy.destroy_node()
    quick.destroy_node()
    rclpy.try_shutdown()
''')


def test_groups_spin_apart_and_stop_together():
    """A group's callbacks do not wait behind another group's (the composed control thread).

    One executor would run the 100 Hz control timer only between the 50 ms busy callbacks
    (gaps of 50 ms); on its own thread it keeps its period (the busy one sleeps, as OpenCV
    releases the interpreter). SIGINT in the main thread stops both groups.
    """
    proc = subprocess.run([sys.executable, '-c', GROUPS_SCRIPT, 'run'], capture_output=True,
                          text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and 'returned' in proc.stdout, out
    figures = dict(kv.split('=') for kv in proc.stdout.split('returned ')[1].split())
    assert int(figures['quick']) >= 100 and int(figures['busy']) >= 10, out
    assert float(figures['gap_p90']) < 0.03, out
    for bad in ('Traceback', 'FATAL'):
        assert bad not in out, out


def test_an_exception_in_a_side_group_ends_the_spin_and_is_raised():
    """A control executor that dies must not leave the process spinning the images alone."""
    proc = subprocess.run([sys.executable, '-c', GROUPS_SCRIPT, 'raise'], capture_output=True,
                          text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert 'raised a control callback failed' in proc.stdout, out
    assert 'quick=30 ' in proc.stdout, out
