"""Test-session set-up of the whole-graph, SITL and repository tests (ibvs_common.testing)."""
import pytest

from ibvs_common.testing import isolate_dds, rclpy_context

isolate_dds()


@pytest.fixture()
def context():
    """Yield a fresh rclpy context for one test; shut it down after."""
    yield from rclpy_context()
