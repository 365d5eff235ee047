"""Benchmark: the cost of a throttled log call on the flight path, rclpy's vs ThrottledLog.

A node that logs a throttled warning for every frame (a frame released at its deadline, no
window for the front flow) pays for each call, even when the throttle drops it. Prints the
median, p95 and max per call (microseconds) of:

- rclpy: ``node.get_logger().warning(text, throttle_duration_sec=2.0)``;
- ThrottledLog: ``ibvs_common.throttled_log.ThrottledLog(node.get_logger()).warning(text,
  2.0)``;

with the text formatted per call as the nodes do, and what one such call per frame costs at
50 Hz in % of a core. Run: ``.venv/bin/python benchmarks/bench_log_throttle.py``.
"""
import argparse
import os
import statistics
import time

import rclpy
from rclpy.node import Node

from ibvs_common.throttled_log import ThrottledLog

FRAME_HZ = 50.0


def time_calls(call, n: int) -> list[float]:
    """Return the duration (us) of each of ``n`` calls of ``call(i)``."""
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        call(i)
        out.append(1e6 * (time.perf_counter() - t0))
    return out


def report(name: str, us: list[float]) -> None:
    us = sorted(us)
    p95 = us[int(0.95 * (len(us) - 1))]
    median = statistics.median(us)
    print(f'{name:12s} median {median:8.1f} us  p95 {p95:8.1f} us  max {us[-1]:8.1f} us  '
          f'= {median * FRAME_HZ / 1e4:.2f} % of a core at one call per frame, 50 Hz')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--calls', type=int, default=2000, help='calls per logger')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rclpy.init()
    node = Node('bench_log_throttle')
    try:
        logger = node.get_logger()
        throttled = ThrottledLog(logger)
        report('rclpy', time_calls(lambda i: logger.warning(
            f'frame {i * 0.02:.3f} s released at its deadline', throttle_duration_sec=2.0),
            args.calls))
        report('ThrottledLog', time_calls(lambda i: throttled.warning(
            f'frame {i * 0.02:.3f} s released at its deadline', 2.0), args.calls))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
