"""Test set-up of ibvs_control's tests: own DDS domain per pytest worker, rclpy contexts."""
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor

from ibvs_common.testing import isolate_dds, rclpy_context

isolate_dds()


@pytest.fixture()
def context():
    """Yield a fresh rclpy context for one test; shut it down after."""
    yield from rclpy_context()


@pytest.fixture()
def ctx():
    """Yield (a fresh rclpy context, an executor on it, a list of nodes destroyed after)."""
    context = rclpy.context.Context()
    rclpy.init(context=context)
    nodes = []
    executor = SingleThreadedExecutor(context=context)
    yield context, executor, nodes
    executor.shutdown()
    for n in nodes:
        n.destroy_node()
    rclpy.try_shutdown(context=context)
