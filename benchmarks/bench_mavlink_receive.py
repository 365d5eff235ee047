"""Benchmark: CPU of the bridge's MAVLink receive (MavlinkLink.poll), per message and per wake-up.

Without images, the graph's work is the autopilot's ~280 messages a second (attitude and IMU at
100 Hz, thrust at 50 Hz; PX4 sends one message per UDP datagram), read by the bridge's reader
thread at ~150 wake-ups a second (docs/performance.md, "Idle CPU"). Compares, on a UDP loopback
link with real datagrams:

- ``link``: MavlinkLink.poll as shipped (its own read loop, ``_next_message``);
- ``recv_msg``: the same poll through pymavlink's ``recv_msg`` (with its ``post_message``
  bookkeeping), the way the link read before 2026-11-27.

Prints, as CPU time of the polling thread (``time.thread_time_ns``): per message when
``--messages`` datagrams are queued and read in one poll, and per poll when one datagram is read
2 ms after the previous poll (a wake-up of the reader thread; caches are colder). Run:
``.venv/bin/python benchmarks/bench_mavlink_receive.py [--messages N] [--wakeups N] [--smoke]``.
"""
import argparse
import socket
import statistics
import time

from ibvs_control.mavlink.link import LinkConfig, MavlinkLink, mavlink

WAKE_GAP_S = 0.002


def autopilot_frames() -> tuple[bytes, list[bytes]]:
    """(HEARTBEAT, [ATTITUDE_QUATERNION, HIGHRES_IMU]) as PX4 frames them (MAVLink 2)."""
    enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = enc.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0,
                                     0, 0).pack(enc)
    stream = [enc.attitude_quaternion_encode(1234, 1.0, 0.0, 0.0, 0.0, 0.1, -0.2, 0.3).pack(enc),
              enc.highres_imu_encode(5_000_000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0, 0, 0, 0,
                                     0, 0, 0, 0).pack(enc)]
    return heartbeat, stream


class Rig:
    """A linked MavlinkLink (udpin) and a UDP sender speaking as the autopilot."""

    def __init__(self, way: str) -> None:
        self.link = MavlinkLink(LinkConfig(url='udpin:127.0.0.1:0'))
        if way == 'recv_msg':
            conn = self.link._conn                  # the comparison arm
            self.link._next_message = conn.recv_msg
        self.sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sender.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
        self.address = ('127.0.0.1', self.link.local_port)
        heartbeat, self.stream = autopilot_frames()
        self.sender.sendto(heartbeat, self.address)
        time.sleep(0.02)
        if not self.link.poll() or self.link.target_system != 1:
            raise RuntimeError('no HEARTBEAT received on the loopback link')

    def per_message(self, n: int) -> float:
        """CPU us per message: ``n`` datagrams queued, read in polls of 100 datagrams."""
        got, cpu_ns = 0, 0
        for start in range(0, n, 100):
            for k in range(start, min(n, start + 100)):
                self.sender.sendto(self.stream[k % 2], self.address)
            time.sleep(0.005)
            t0 = time.thread_time_ns()
            got += len(self.link.poll(max_messages=1000))
            cpu_ns += time.thread_time_ns() - t0
        if got != n:
            raise RuntimeError(f'{got} of {n} messages read')
        return cpu_ns / got / 1e3

    def per_wakeup(self, n: int) -> list[float]:
        """CPU us of each of ``n`` polls reading one datagram sent WAKE_GAP_S after the last."""
        out = []
        for k in range(n):
            self.sender.sendto(self.stream[k % 2], self.address)
            time.sleep(WAKE_GAP_S)
            t0 = time.thread_time_ns()
            if len(self.link.poll()) != 1:
                raise RuntimeError('a wake-up read no message')
            out.append((time.thread_time_ns() - t0) / 1e3)
        return out

    def close(self) -> None:
        self.link.close()
        self.sender.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--messages', type=int, default=5000, help='messages read in batches')
    p.add_argument('--wakeups', type=int, default=500, help='single-datagram polls')
    p.add_argument('--repeats', type=int, default=3, help='alternating rounds per way')
    p.add_argument('--smoke', action='store_true', help='CI: a short run')
    a = p.parse_args()
    if a.smoke:
        a.messages, a.wakeups, a.repeats = 200, 20, 1
    results = {'link': ([], []), 'recv_msg': ([], [])}
    for _ in range(a.repeats):
        for way, (batch, wake) in results.items():
            rig = Rig(way)
            try:
                batch.append(rig.per_message(a.messages))
                wake += rig.per_wakeup(a.wakeups)
            finally:
                rig.close()
    for way, (batch, wake) in results.items():
        print(f'{way:8s} per message (batched) median {statistics.median(batch):6.1f} us   '
              f'per wake-up median {statistics.median(wake):6.1f} us  p95 '
              f'{statistics.quantiles(wake, n=20)[-1] if len(wake) > 1 else wake[0]:6.1f} us  '
              f'({a.repeats} x {a.messages} messages, {len(wake)} wake-ups)')


if __name__ == '__main__':
    main()
