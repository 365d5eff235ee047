"""A node that dies without a goodbye is unmatched within the profile's lease (fastdds.xml).

Fast DDS keeps a SIGKILLed reader matched until its participant's lease expires (20 s by
default), and from a few seconds after the death every write to it costs the publisher more
(docs/performance.md, "A killed node"). The lease is announced by the reader's own
participant: the reader here runs in a child process that takes the project's profile, as every
node started by the runner, run_scenario or the launch files does; this process only watches.
"""
import os
import signal
import subprocess
import sys
import time

import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image

from ibvs_common.dds_profile import dds_env_overrides, FASTDDS_PROFILE_ENV

DEFAULT_LEASE_S = 20.0          # Fast DDS 2.x default participant lease
MATCH_TIMEOUT_S = 15.0          # the child's start (rclpy import) and discovery
UNMATCH_BOUND_S = 8.0           # the profile's 3 s lease + announcement period + margin

READER = """
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
rclpy.init()
node = rclpy.create_node('dds_lease_reader')
node.create_subscription(Image, '{topic}', lambda msg: None, qos_profile_sensor_data)
rclpy.spin(node)
"""


def _wait_for(publisher, count: int, timeout_s: float) -> float:
    """Return the s until ``publisher`` has ``count`` readers, at most ``timeout_s``.

    No spinning needed: discovery and leases run in Fast DDS's own threads.
    """
    start = time.monotonic()
    while publisher.get_subscription_count() != count:
        if time.monotonic() - start > timeout_s:
            break
        time.sleep(0.05)
    return time.monotonic() - start


def test_a_killed_reader_is_unmatched_well_before_the_default_lease(context):
    topic = f'dds_lease_{os.getpid()}'
    env = dict(os.environ, **dds_env_overrides({}))
    assert env[FASTDDS_PROFILE_ENV].endswith('fastdds.xml')
    node = rclpy.create_node(f'dds_lease_writer_{os.getpid()}', context=context)
    publisher = node.create_publisher(Image, topic, qos_profile_sensor_data)
    reader = subprocess.Popen([sys.executable, '-c', READER.format(topic=topic)], env=env)
    try:
        _wait_for(publisher, 1, MATCH_TIMEOUT_S)
        assert publisher.get_subscription_count() == 1, 'the reader was never matched'
        reader.send_signal(signal.SIGKILL)
        reader.wait(timeout=5.0)
        unmatched_after_s = _wait_for(publisher, 0, DEFAULT_LEASE_S + 5.0)
        assert publisher.get_subscription_count() == 0, 'the dead reader stayed matched'
        assert unmatched_after_s < UNMATCH_BOUND_S, (
            f'the dead reader was unmatched {unmatched_after_s:.1f} s after its death: the '
            'lease of fastdds.xml was not applied (Fast DDS default: 20 s)')
    finally:
        if reader.poll() is None:
            reader.kill()
            reader.wait()
        node.destroy_node()
