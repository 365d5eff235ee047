"""Test support shared by every package's tests and the benchmarks (never on the flight path).

:func:`isolate_dds` gives each pytest process its own DDS domain on loopback, so parallel
runs (and developers' shells) never see each other's topics. Under pytest-xdist the workers
inherit the controller's environment, so each worker moves to a domain of its own: the
controller's domain + 1 + the worker's number (``PYTEST_XDIST_WORKER`` = gw0, gw1, ...).
:func:`rclpy_context` is the node tests' fixture body: a fresh context, shut down after.
:func:`shared_dir` finds the SITL firmware and the spec that tests needing them use (they skip
without it). :class:`SerialCable` joins two pseudo-terminals like a serial cable at a baud
rate, for a MAVLink link over a "serial port" without hardware.
"""
from __future__ import annotations

import os
from pathlib import Path
import select
import threading
import time
import tty
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


class SerialCable:
    """Two pseudo-terminals joined like a serial cable at ``baud`` (8N1: baud / 10 bytes/s).

    ``ends`` are the two device paths (``/dev/pts/N``): open each with pymavlink or pyserial
    as ``/dev/pts/N,<baud>``. A thread moves the bytes each way no faster than the baud rate
    allows, in order, as a UART does; nothing is lost (a real UART's overrun is not modelled).
    """

    def __init__(self, baud: int = 921600) -> None:
        self.bytes_per_s = baud / 10.0
        self._fds = []
        self.ends = []
        masters = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)               # no echo, no line discipline: bytes as they are
            os.set_blocking(master, False)
            self._fds += [master, slave]
            masters.append(master)
            self.ends.append(os.ttyname(slave))
        self._masters = masters
        self.moved = [0, 0]                 # bytes moved end 0 -> 1, end 1 -> 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='serial-cable', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        queues = [bytearray(), bytearray()]       # bytes on the wire towards the other end
        free_at = [0.0, 0.0]                      # when each direction's wire is free again
        while not self._stop.is_set():
            now = time.monotonic()
            waits = [max(free_at[i] - now, 0.0) for i in (0, 1) if queues[i]]
            ready, _, _ = select.select(self._masters, [], [], min(waits + [0.05]))
            now = time.monotonic()
            for i, fd in enumerate(self._masters):
                if fd in ready:
                    try:
                        queues[i] += os.read(fd, 4096)
                    except (BlockingIOError, InterruptedError):
                        pass
                    except OSError:               # the other side closed its end
                        time.sleep(0.001)
            for i in (0, 1):
                if not queues[i] or free_at[i] > now:
                    continue
                # what the wire carried since it was last free, at most what is queued
                n = max(1, min(len(queues[i]), int(self.bytes_per_s * 0.002)))
                try:        # a full input queue at the far end takes part, or nothing, now
                    n = os.write(self._masters[1 - i], bytes(queues[i][:n]))
                except (BlockingIOError, InterruptedError):
                    n = 0
                except OSError:
                    pass
                if n == 0:                        # the far end is full: try again in 1 ms
                    free_at[i] = now + 0.001
                    continue
                del queues[i][:n]
                self.moved[i] += n
                free_at[i] = max(free_at[i], now) + n / self.bytes_per_s

    def close(self) -> None:
        """Stop moving bytes and close both ends."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
