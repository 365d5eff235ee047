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
