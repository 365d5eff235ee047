"""Fixtures shared by the node tests (real rclpy)."""
import pytest
import rclpy


@pytest.fixture()
def context():
    """Yield a fresh rclpy context for one test; shut it down after."""
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
