"""Test-session set-up shared by all layers (unit, nodes, integration).

Each pytest process gets its own DDS domain on loopback, so parallel runs (and developers'
shells) never see each other's topics. Under pytest-xdist (``make test`` runs two workers) the
workers inherit the controller's environment, so each worker moves to a domain of its own: the
controller's domain + 1 + the worker's number (``PYTEST_XDIST_WORKER`` = gw0, gw1, ...).
"""
import os

DOMAIN_ID_SPAN = 200            # ROS_DOMAIN_IDs used: 1 ... 200 (Fast DDS allows 0 ... 232)

os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % DOMAIN_ID_SPAN))
_worker = os.environ.get('PYTEST_XDIST_WORKER', '')
if _worker.startswith('gw') and _worker[2:].isdigit():
    _controller = int(os.environ['ROS_DOMAIN_ID'])
    os.environ['ROS_DOMAIN_ID'] = str(1 + (_controller + int(_worker[2:])) % DOMAIN_ID_SPAN)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
