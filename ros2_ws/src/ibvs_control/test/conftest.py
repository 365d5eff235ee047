"""Test set-up of ibvs_control's tests: own DDS domain per pytest worker, rclpy contexts."""
import pytest

from ibvs_common.testing import isolate_dds, rclpy_context

isolate_dds()


@pytest.fixture()
def context():
    """Yield a fresh rclpy context for one test; shut it down after."""
    yield from rclpy_context()
