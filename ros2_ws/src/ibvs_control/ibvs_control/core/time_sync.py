"""Clock sync with the autopilot by MAVLink TIMESYNC: offset = ROS time - autopilot boot time.

ROS-free, no I/O: the bridge sends the requests and hands the answers in. Two clocks:

- ROS time (ns): system time on a vehicle (a camera driver stamps images in it), sim time from
  ``/clock`` in the sim. Every stamp the graph sees is on this clock.
- the autopilot's boot time (ns): ``time_boot_ms`` of its messages, ``tc1`` of its TIMESYNC.

Round trip (as PX4's timesync and MAVROS's sys_time plugin do)
    request: TIMESYNC tc1 = 0, ts1 = our ROS time t0 (ns). The autopilot answers tc1 = its
    boot time t1 (ns) when it handles the request, ts1 echoed. At receipt, ROS time t2:

        rtt    = t2 - t0                               (ns)
        offset = (t0 + t2 - 2 t1) / 2  = ROS - boot    (ns, integer division)

    i.e. the autopilot's t1 is taken to be the middle of the round trip: the error of one
    sample is half the asymmetry of the two legs, at most rtt / 2.
RTT gate (``max_rtt_s``, 10 ms)
    A sample with rtt > max_rtt_s (or rtt < 0: our clock went back) may be off by up to rtt / 2:
    rejected, counted. Only answers to requests we sent (ts1 one of our recent requests) count.
Initialisation
    The offset is unknown (:attr:`synced` False, the mappings return None) until
    ``init_samples`` (5) samples passed the RTT gate; the estimate is then their median (an
    actual sample, exact integer: one wrong sample of five cannot move it). While unsynced,
    :meth:`next_request` asks at every call but at most every ``init_request_period_s`` of the
    steady clock (the ROS clock may stand still: a lockstep sim waits for the graph); once
    synced, every ``period_s`` (0.1 s, 10 Hz as MAVROS) of ROS time.
Tracking
    Exponential smoothing (``alpha``) of the accepted samples, kept as an exact integer base (the
    initial median) plus a float residual: samples equal to the estimate leave it unchanged to
    the bit (in a lockstep sim the true offset is exactly 0 and a round trip takes 0 s of sim
    time, so every good sample is exactly 0 and the mapped stamps repeat bit for bit). A sample
    farther than ``max_deviation_s`` (10 ms) from the estimate is an outlier and not used (e.g.
    -20 ms with rtt 0 when our ``/clock`` lags the sim by one frame); ``max_consecutive_outliers``
    (5) in a row mean a time jump (a clock was set): reset, re-initialise.
Reboot
    A ``time_boot_ms`` or ``tc1`` more than 1 s before the previous one of its kind: the
    autopilot rebooted, reset, re-initialise.
Mapping
    boot ms -> ROS ns = ms * 1e6 + offset; ROS ns -> boot ms = (ns - offset) / 1e6 rounded to
    the nearest ms (halves up); None while unsynced.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
import statistics

NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000
REBOOT_BACKSTEP_NS = NS_PER_S          # boot time going back by more than this: a reboot
PENDING_REQUESTS_KEPT = 32             # ts1 of our latest requests an answer may echo
STEADY_EPS_S = 1e-9                    # s, float slack of the steady-clock request period
RTT_WARN_EVERY = 20                    # warn after this many RTT rejections in a row (again)


@dataclass(frozen=True)
class TimeSyncConfig:
    """Settings of :class:`TimeSync` (node parameters ``timesync_*``, params.yaml)."""

    period_s: float = 0.1                  # s of ROS time between requests once synced
    init_request_period_s: float = 0.05    # s of steady clock between requests while unsynced
    init_samples: int = 5                  # accepted samples whose median starts the estimate
    max_rtt_s: float = 0.010               # s, round trips above this are rejected
    alpha: float = 0.05                    # smoothing gain of the tracked offset, (0, 1]
    max_deviation_s: float = 0.010         # s, a sample this far from the estimate: outlier
    max_consecutive_outliers: int = 5      # that many outliers in a row: time jump, reset

    def __post_init__(self):
        for name in ('period_s', 'init_request_period_s', 'max_rtt_s', 'max_deviation_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'timesync {name} must be finite and > 0, got {v}')
        if not (math.isfinite(self.alpha) and 0.0 < self.alpha <= 1.0):
            raise ValueError(f'timesync alpha must be in (0, 1], got {self.alpha}')
        for name in ('init_samples', 'max_consecutive_outliers'):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f'timesync {name} must be an integer >= 1, got {v}')


@dataclass(frozen=True)
class TimeSyncStatus:
    """Snapshot for /diagnostics."""

    synced: bool
    offset_ns: int | None           # ROS - boot, None while unsynced
    accepted: int                   # samples used (initialisation + tracking)
    rejected_rtt: int               # round trip above max_rtt_s (or negative)
    rejected_outliers: int          # farther than max_deviation_s from the estimate
    unmatched: int                  # answers to no request of ours (ignored)
    resets: int                     # time jumps and reboots
    last_rtt_ns: int | None         # of the last answer to one of our requests


class TimeSync:
    """Offset between the ROS clock and the autopilot's boot clock (see the module doc)."""

    def __init__(self, config: TimeSyncConfig | None = None) -> None:
        self.config = config if config is not None else TimeSyncConfig()
        c = self.config
        self._period_ns = int(round(c.period_s * NS_PER_S))
        self._max_rtt_ns = int(round(c.max_rtt_s * NS_PER_S))
        self._max_dev_ns = int(round(c.max_deviation_s * NS_PER_S))
        self.accepted = 0
        self.rejected_rtt = 0
        self.rejected_outliers = 0
        self.unmatched = 0
        self.resets = 0
        self.last_rtt_ns: int | None = None
        self._pending: deque = deque(maxlen=PENDING_REQUESTS_KEPT)
        self._last_request_ros_ns: int | None = None
        self._last_request_steady_s: float | None = None
        self._rtt_streak = 0
        self._last_boot_ns: dict[str, int] = {}
        self._clear()

    # --- state -------------------------------------------------------------------------------
    @property
    def synced(self) -> bool:
        """Whether the offset is known (``init_samples`` accepted since the last reset)."""
        return self._base_ns is not None

    @property
    def offset_ns(self) -> int | None:
        """ROS time - autopilot boot time (ns), None while unsynced."""
        if self._base_ns is None:
            return None
        return self._base_ns + int(round(self._residual_ns))

    @property
    def init_progress(self) -> int:
        """Accepted samples collected towards the initial median (0 once synced)."""
        return len(self._init)

    def status(self) -> TimeSyncStatus:
        """Return the counters and the estimate."""
        return TimeSyncStatus(self.synced, self.offset_ns, self.accepted, self.rejected_rtt,
                              self.rejected_outliers, self.unmatched, self.resets,
                              self.last_rtt_ns)

    # --- requests ----------------------------------------------------------------------------
    def next_request(self, ros_ns: int | None, steady_s: float) -> int | None:
        """Return the ts1 (= ``ros_ns``) of a request to send now, or None.

        ``ros_ns``: ROS time now (None or 0: no clock yet, e.g. no ``/clock`` received under
        use_sim_time; ts1 = 0 would be meaningless); ``steady_s``: steady clock (s).
        """
        if ros_ns is None or ros_ns <= 0:
            return None
        ros_ns = int(ros_ns)
        if self.synced:
            last = self._last_request_ros_ns
            due = last is None or ros_ns - last >= self._period_ns or ros_ns < last
        else:
            last_s = self._last_request_steady_s
            due = (last_s is None
                   or steady_s - last_s >= self.config.init_request_period_s - STEADY_EPS_S)
        if not due:
            return None
        self._last_request_ros_ns, self._last_request_steady_s = ros_ns, steady_s
        self._pending.append(ros_ns)
        return ros_ns

    # --- answers -----------------------------------------------------------------------------
    def on_reply(self, tc1_ns: int, ts1_ns: int, ros_ns: int) -> list[tuple[str, str]]:
        """Take an answer (tc1 > 0) received at ROS time ``ros_ns``.

        Returns (level, text) events for the log: synced, time jump, reboot, RTT too high.
        """
        tc1_ns, ts1_ns, ros_ns = int(tc1_ns), int(ts1_ns), int(ros_ns)
        if ts1_ns not in self._pending:
            self.unmatched += 1
            return []
        self._pending.remove(ts1_ns)
        events = self.on_boot_time('tc1', tc1_ns)
        rtt = ros_ns - ts1_ns
        self.last_rtt_ns = rtt
        if rtt < 0 or rtt > self._max_rtt_ns:
            self.rejected_rtt += 1
            self._rtt_streak += 1
            if self._rtt_streak % RTT_WARN_EVERY == 0:
                events.append(('warn', f'TIMESYNC: {self._rtt_streak} round trips in a row '
                                       f'above {self.config.max_rtt_s * 1e3:.1f} ms (last '
                                       f'{rtt / NS_PER_MS:.1f} ms): samples rejected'))
            return events
        self._rtt_streak = 0
        sample = (ts1_ns + ros_ns - 2 * tc1_ns) // 2
        if not self.synced:
            self.accepted += 1
            self._init.append(sample)
            if len(self._init) >= self.config.init_samples:
                self._base_ns = statistics.median_low(self._init)
                self._residual_ns = 0.0
                self._init = []
                events.append(('info', f'clock synced with the autopilot: ROS - boot = '
                                       f'{self._base_ns / NS_PER_S:.6f} s (median of '
                                       f'{self.config.init_samples} TIMESYNC samples)'))
            return events
        if abs(sample - self.offset_ns) > self._max_dev_ns:
            self.rejected_outliers += 1
            self._outlier_streak += 1
            if self._outlier_streak >= self.config.max_consecutive_outliers:
                events.append(('warn', f'TIMESYNC: {self._outlier_streak} samples in a row more '
                                       f'than {self.config.max_deviation_s * 1e3:.1f} ms from '
                                       f'the offset (last {(sample - self.offset_ns) / 1e6:+.1f}'
                                       ' ms): time jump, clock sync reset'))
                self.reset()
            return events
        self.accepted += 1
        self._outlier_streak = 0
        self._residual_ns += self.config.alpha * ((sample - self._base_ns) - self._residual_ns)
        return events

    def on_boot_time(self, kind: str, boot_ns: int) -> list[tuple[str, str]]:
        """Note an autopilot boot time of ``kind`` ('time_boot_ms', 'tc1'; ns).

        More than 1 s before the previous one of its kind: the autopilot rebooted, reset.
        """
        boot_ns = int(boot_ns)
        last = self._last_boot_ns.get(kind)
        self._last_boot_ns[kind] = boot_ns
        if last is not None and boot_ns < last - REBOOT_BACKSTEP_NS:
            self.reset()
            self._last_boot_ns = {kind: boot_ns}
            return [('warn', f'autopilot {kind} went back from {last / NS_PER_S:.3f} s to '
                             f'{boot_ns / NS_PER_S:.3f} s: reboot, clock sync reset')]
        return []

    def reset(self) -> None:
        """Forget the offset (counted): unsynced until ``init_samples`` new samples."""
        self.resets += 1
        self._clear()

    # --- mapping -----------------------------------------------------------------------------
    def boot_ms_to_ros_ns(self, time_boot_ms: int) -> int | None:
        """Autopilot time_boot_ms -> ROS time (ns); None while unsynced."""
        offset = self.offset_ns
        if offset is None:
            return None
        return int(time_boot_ms) * NS_PER_MS + offset

    def ros_ns_to_boot_ms(self, ros_ns: int) -> int | None:
        """ROS time (ns) -> autopilot time_boot_ms, nearest ms (halves up); None unsynced."""
        offset = self.offset_ns
        if offset is None:
            return None
        return (int(ros_ns) - offset + NS_PER_MS // 2) // NS_PER_MS

    def _clear(self) -> None:
        self._base_ns: int | None = None
        self._residual_ns = 0.0
        self._init: list[int] = []
        self._outlier_streak = 0
        self._last_request_ros_ns = None
