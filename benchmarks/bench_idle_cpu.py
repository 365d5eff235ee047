#!/usr/bin/env python3
"""CPU of the idle onboard graph (linked to an autopilot, no camera images), by layout.

Issue 12's target: the idle graph takes <= 5 % of one core. Without images the graph's work is
the 100 Hz IMU: the bridge reads the autopilot's MAVLink streams and publishes imu/data, and
five nodes take every sample. Measured here, each case in a fresh process (CPU = utime +
stime of that process over ``--window-s`` after ``--settle-s``), repeated ``--repeats`` times:

- ``composed``: the seven onboard nodes in one process (ibvs_bringup.composed), imu/data to
  the co-located nodes in process (ibvs_common.intra_process), the vehicle at rest (disarmed,
  supervisor IDLE: the bridge slows the attitude, IMU and thrust streams to
  ``quiet_telemetry_rate_hz``, docs/mavlink.md "Telemetry at rest"): the graph on the pad;
- ``composed, full telemetry``: the same with ``quiet_telemetry_rate_hz:=0`` (100 Hz attitude
  and IMU as in flight: the idle graph before 2026-12-02, and an idle graph while a pilot
  flies);
- ``composed, DDS imu``: full telemetry with ``--no-intra-process`` (every node subscribes
  through DDS);
- ``bridge alone``: the MAVLink bridge node only, with its default ``streams_off``, at rest;
- ``bridge alone, streams on`` (``--autopilot px4-sih`` only): ``streams_off: ['']``, i.e.
  PX4's default onboard streams left on, full telemetry. PX4 keeps a stream setting until it
  reboots, so every case there gets a fresh PX4.
- ``no autopilot``: the composed process with nothing on the other end (its floor: timers,
  DDS).

- ``wake-up reference``: no ROS: a bare Python thread woken by ``REFERENCE_WAKEUPS_HZ``
  ATTITUDE_QUATERNION datagrams a second (select, recvfrom, pymavlink's parse), as the
  bridge's reader thread is by the autopilot's streams. It does nothing else, so its CPU is
  what this machine charges today for a wake-up with a fixed piece of Python work. Idle
  figures of different hours compare only together with it (the same graph read 5.5 % at
  14:43 and 9.3 % at 17:15 on 2026-11-27: docs/performance.md "Idle CPU").

Autopilot: ``stand-in`` (default; the sim's PX4-like autopilot, disarmed and still, in a
thread of this process, streams at the rates the bridge asks) or ``px4-sih``
(../shared/px4-sitl, instance 5+; skipped with a message when absent). Nothing subscribes
to imu/data outside the measured process.

Usage: ``bench_idle_cpu.py [--autopilot stand-in|px4-sih] [--repeats N] [--window-s S]
[--smoke]``. Figures: docs/performance.md "Idle CPU".
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLK_TCK = os.sysconf('SC_CLK_TCK')
STAND_IN_RATE_HZ = 100.0
REFERENCE_WAKEUPS_HZ = 150.0    # the bridge's reader thread: ~150 wake-ups/s for ~280 messages
# the wake-up reference's receiver: a thread in select + recvfrom, as MavlinkReader waits, that
# parses each datagram with pymavlink (a fixed piece of Python work per wake-up)
REFERENCE_RECEIVER = '''
import select, socket, threading, time
from pymavlink.dialects.v20 import common as mavlink
parser = mavlink.MAVLink(None)
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(('127.0.0.1', 0))
sock.setblocking(False)
def read():
    while True:
        if select.select([sock], [], [], 0.1)[0]:
            try:
                while True:
                    parser.parse_buffer(sock.recvfrom(2048)[0])
            except BlockingIOError:
                pass
threading.Thread(target=read, daemon=True).start()
print(sock.getsockname()[1], flush=True)
time.sleep(3600)
'''


def cpu_seconds(pid: int) -> float:
    """Return the CPU time (utime + stime, s) of a process so far."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def stand_in(url: str, stop: threading.Event) -> None:
    """Serve the sim's PX4-like autopilot, disarmed, level and still, until ``stop``."""
    from ibvs_sim.core.autopilot import AutopilotConfig
    from ibvs_sim.core.autopilot.stand_in import HoverStandIn
    served = HoverStandIn(AutopilotConfig(url=url, telemetry_default_hz=STAND_IN_RATE_HZ,
                                          start_armed=False))
    try:
        stop.wait()
    finally:
        served.close()


def measure(url: str | None, extra: list, settle_s: float, window_s: float) -> float:
    """% of one core of one composed process (``extra``: its arguments) over window_s."""
    cmd = [sys.executable, '-m', 'ibvs_bringup.composed',
           '--mavlink-url', url or 'udpin:127.0.0.1:9'] + extra
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(settle_s)
        if proc.poll() is not None:
            raise RuntimeError(f'{cmd} exited {proc.returncode} during start-up')
        a = cpu_seconds(proc.pid)
        time.sleep(window_s)
        return 100.0 * (cpu_seconds(proc.pid) - a) / window_s
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def wakeup_reference(settle_s: float, window_s: float) -> float:
    """% of one core of a bare Python receiver woken REFERENCE_WAKEUPS_HZ times a second."""
    proc = subprocess.Popen([sys.executable, '-c', REFERENCE_RECEIVER], stdout=subprocess.PIPE,
                            text=True)
    stop = threading.Event()
    try:
        line = proc.stdout.readline()
        if not line.strip().isdigit():
            raise RuntimeError(f'wake-up reference receiver did not start (said {line!r})')
        port = int(line)
        sender = threading.Thread(target=_send_datagrams, args=(port, stop), daemon=True)
        sender.start()
        time.sleep(min(settle_s, 2.0))
        a = cpu_seconds(proc.pid)
        time.sleep(window_s)
        return 100.0 * (cpu_seconds(proc.pid) - a) / window_s
    finally:
        stop.set()
        proc.terminate()
        proc.wait(timeout=30)


def _send_datagrams(port: int, stop: threading.Event) -> None:
    """Send an ATTITUDE_QUATERNION (MAVLink 2) REFERENCE_WAKEUPS_HZ times a second."""
    import socket
    from pymavlink.dialects.v20 import common as mavlink
    enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = enc.attitude_quaternion_encode(1, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3).pack(enc)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    period, t = 1.0 / REFERENCE_WAKEUPS_HZ, time.monotonic()
    try:
        while not stop.is_set():
            sock.sendto(frame, ('127.0.0.1', port))
            t += period
            time.sleep(max(0.0, t - time.monotonic()))
    finally:
        sock.close()


FULL_TELEMETRY = ['-p', 'quiet_telemetry_rate_hz:=0.0']
CASES = {
    'composed': [],
    'composed, full telemetry': ['--ros-args'] + FULL_TELEMETRY,
    'composed, DDS imu': ['--no-intra-process', '--ros-args'] + FULL_TELEMETRY,
    'bridge alone': ['--nodes', 'mavlink_bridge'],
    'bridge alone, streams on': ['--nodes', 'mavlink_bridge', '--ros-args', '-p',
                                 "streams_off:=['']"] + FULL_TELEMETRY,
}


def run_case(name: str, autopilot: str, settle_s: float, window_s: float) -> float:
    """One measurement of one case against a fresh autopilot."""
    if autopilot == 'px4-sih':
        from ibvs_harness.px4_sih import free_instance, Px4Sitl
        px4 = Px4Sitl(instance=free_instance(), params={})
        px4.start()
        try:
            return measure(f'udpin:0.0.0.0:{14540 + px4.instance}', CASES[name], settle_s,
                           window_s)
        finally:
            px4.stop()
    from ibvs_common.core.mavlink_connection import free_udp_port
    port = free_udp_port()
    stop = threading.Event()
    thread = threading.Thread(target=stand_in, args=(f'udpin:127.0.0.1:{port}', stop),
                              daemon=True)
    thread.start()
    try:
        return measure(f'udpout:127.0.0.1:{port}', CASES[name], settle_s, window_s)
    finally:
        stop.set()
        thread.join(timeout=5.0)


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--autopilot', choices=('stand-in', 'px4-sih'), default='stand-in')
    p.add_argument('--repeats', type=int, default=3, help='measurements per case')
    p.add_argument('--settle-s', type=float, default=10.0, help='s before the window (link, '
                   'clock sync, streams)')
    p.add_argument('--window-s', type=float, default=15.0, help='s of CPU measured')
    p.add_argument('--smoke', action='store_true', help='CI: one short run of each case')
    a = p.parse_args(argv)
    os.environ.setdefault('AMENT_PREFIX_PATH', os.path.join(ROOT, '.venv'))
    if a.smoke:
        a.repeats, a.settle_s, a.window_s = 1, 4.0, 1.0
    if a.autopilot == 'px4-sih':
        from ibvs_harness.px4_sih import find_px4_sitl
        try:
            find_px4_sitl()
        except (FileNotFoundError, RuntimeError) as exc:
            print(f'bench_idle_cpu: no PX4 SITL ({exc}); nothing measured')
            return 0
    cases = [c for c in CASES if a.autopilot == 'px4-sih' or 'streams on' not in c]
    load = os.getloadavg()[0]
    print(f'bench_idle_cpu: autopilot {a.autopilot}, {a.repeats} x {a.window_s:g} s per case, '
          f'load average {load:.2f} on {os.cpu_count()} cores (% of one core)')
    results = {c: [] for c in cases}
    for _ in range(a.repeats):            # interleaved: slow drifts of the machine hit all
        for c in cases:
            results[c].append(run_case(c, a.autopilot, a.settle_s, a.window_s))
    results['no autopilot'] = [measure(None, [], a.settle_s, a.window_s)
                               for _ in range(a.repeats)]
    results['wake-up reference'] = [wakeup_reference(a.settle_s, a.window_s)
                                    for _ in range(a.repeats)]
    for c, v in results.items():
        print(f'{c:26s} median {statistics.median(v):5.1f} %   runs '
              + ', '.join(f'{x:.1f}' for x in v))
    ref = statistics.median(results['wake-up reference'])
    print(f'wake-up reference: {REFERENCE_WAKEUPS_HZ:g} wake-ups/s of a bare Python reader cost '
          f'{ref:.2f} % here, {ref / 100.0 / REFERENCE_WAKEUPS_HZ * 1e6:.0f} us each '
          '(compare idle figures of different hours only with it)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
