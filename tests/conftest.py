"""Test-session set-up shared by all layers (unit, nodes, integration).

Each pytest process gets its own DDS domain on loopback, so parallel runs (and developers'
shells) never see each other's topics.
"""
import os

os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
