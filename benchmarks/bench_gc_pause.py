"""Benchmark: the pause of a full garbage collection in a flight node, before and after gc.freeze.

Python runs a full (generation 2) collection now and then, in the middle of whatever callback
allocates at that moment; it scans every tracked object. A node of this graph holds tens of
thousands of them after start-up (modules, parameters, buffers). ``ibvs_common.spin`` calls
``gc.freeze()`` before spinning, which takes those out of every later collection.

Builds, in one process, the nodes of the flight path that run Python callbacks per frame
(supervisor, force controller, window detector, down optical flow; their imports are the
union of the separate processes'), then prints the median and max of ``--repeats`` full
collections (ms) before and after ``gc.freeze()``, and the objects tracked.
Run: ``.venv/bin/python benchmarks/bench_gc_pause.py``.
"""
import argparse
import gc
import os
import statistics
import time

import rclpy
from rclpy.parameter import Parameter


def full_collections_ms(repeats: int) -> list[float]:
    """Return the duration (ms) of ``repeats`` full collections."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        gc.collect()
        out.append(1e3 * (time.perf_counter() - t0))
    return out


def report(name: str, ms: list[float]) -> None:
    print(f'{name:22s} median {statistics.median(ms):7.2f} ms  max {max(ms):7.2f} ms  '
          f'({len(gc.get_objects())} objects tracked)')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--repeats', type=int, default=20, help='full collections timed')
    args = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from ibvs_control.force_controller_node import ForceControllerNode
    from ibvs_control.mode_supervisor_node import ModeSupervisorNode
    from ibvs_perception.optical_flow_node import OpticalFlowNode
    from ibvs_perception.window_detector_node import WindowDetectorNode
    rclpy.init()
    nodes = [ModeSupervisorNode(), ForceControllerNode(), WindowDetectorNode(),
             OpticalFlowNode('down_optical_flow',
                             parameter_overrides=[Parameter('camera', value='down')])]
    try:
        report('before gc.freeze()', full_collections_ms(args.repeats))
        gc.freeze()
        report('after gc.freeze()', full_collections_ms(args.repeats))
        print(f'frozen objects: {gc.get_freeze_count()}')
    finally:
        gc.unfreeze()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
