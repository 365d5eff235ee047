"""Test set-up shared by every package's tests (pytest): DDS isolation and an rclpy context.

:func:`isolate_dds` gives each pytest process its own DDS domain on loopback, so parallel
runs (and developers' shells) never see each other's topics. Under pytest-xdist the workers
inherit the controller's environment, so each worker moves to a domain of its own: the
controller's domain + 1 + the worker's number (``PYTEST_XDIST_WORKER`` = gw0, gw1, ...).
:func:`rclpy_context` is the node tests' fixture body: a fresh context, shut down after.
:func:`shared_dir` finds the SITL firmware and the spec that tests needing them use (they skip
without it).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import rclpy
from rclpy.context import Context

SHARED_ENV = 'IBVS_SHARED_DIR'   # where ../shared is, if not beside the checkout
DOMAIN_ID_SPAN = 200            # ROS_DOMAIN_IDs used: 1 ... 200 (Fast DDS allows 0 ... 232)


def isolate_dds() -> None:
    """Set this process's ROS_DOMAIN_ID (one per pytest worker) and loopback discovery."""
    if os.environ.get('IBVS_TEST_DDS_ISOLATED') == str(os.getpid()):
        return
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % DOMAIN_ID_SPAN))
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw') and worker[2:].isdigit():
        controller = int(os.environ['ROS_DOMAIN_ID'])
        os.environ['ROS_DOMAIN_ID'] = str(1 + (controller + int(worker[2:])) % DOMAIN_ID_SPAN)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
    os.environ['IBVS_TEST_DDS_ISOLATED'] = str(os.getpid())


def rclpy_context() -> Iterator[Context]:
    """Yield a fresh rclpy context for one test; shut it down after (a fixture's body)."""
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def shared_dir() -> Path | None:
    """Return the ``shared`` directory (PX4 / ArduPilot SITL), or None where there is none.

    ``$IBVS_SHARED_DIR`` if set, else the first ``shared`` directory holding a SITL beside the
    current directory or this file or any of their parents (a checkout next to ``shared/``).
    """
    if os.environ.get(SHARED_ENV):
        return Path(os.environ[SHARED_ENV])
    for base in (Path.cwd(), Path(__file__).resolve()):
        for parent in (base, *base.parents):
            candidate = parent / 'shared'
            if (candidate / 'px4-sitl').is_dir() or (candidate / 'ardupilot-sitl').is_dir():
                return candidate
    return None


class FakeLogger:
    """A logger that keeps (level, text) lines (for ThrottledLog and the nodes' log calls)."""

    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(('info', text))

    def warning(self, text):
        self.lines.append(('warning', text))

    def error(self, text):
        self.lines.append(('error', text))


class FakeClock:
    """A settable clock (s): ``clock.t`` is what ``clock()`` returns."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t
