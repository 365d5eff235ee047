"""Clock sync with the autopilot by MAVLink TIMESYNC: offset = ROS time - autopilot boot time.

ROS-free, no I/O: :class:`TimeSync` estimates the offset and its skew from round trips
(RTT gate, median start, alpha-beta tracking, outliers and time jumps, reboots) and maps
stamps both ways; :class:`TimesyncExchange` sends and answers the messages; :class:`RosTime`
is the ROS time the node gives. How and why: docs/mavlink.md, "Clock sync (TIMESYNC)".
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
import statistics

from ibvs_common.core.params import param
from ibvs_common.core.stamps import NS_PER_S

NS_PER_MS = 1_000_000
REBOOT_BACKSTEP_NS = NS_PER_S          # boot time going back by more than this: a reboot
PENDING_REQUESTS_KEPT = 32             # ts1 of our latest requests an answer may echo
STEADY_EPS_S = 1e-9                    # s, float slack of the steady-clock request period
RTT_WARN_EVERY = 20                    # warn after this many RTT rejections in a row (again)


@dataclass(frozen=True)
class TimeSyncConfig:
    """Settings of :class:`TimeSync` (node parameters ``timesync_*``)."""

    period_s: float = param(0.1, 's (ROS clock) between TIMESYNC requests once synced',
                            0.0, None)
    init_request_period_s: float = param(
        0.05, 's (steady clock) between TIMESYNC requests while unsynced', 0.0, None)
    init_samples: int = param(5, 'accepted TIMESYNC samples whose median starts the offset',
                              1, None)
    max_rtt_s: float = param(0.010, 's (ROS clock), TIMESYNC round trips above this are '
                             'rejected', 0.0, None)
    alpha: float = param(0.05, 'smoothing gain of the clock offset per accepted sample',
                         0.0, 1.0)
    beta: float = param(0.002, 'smoothing gain of the clock skew per accepted sample',
                        0.0, 1.0)
    max_deviation_s: float = param(0.010, 's (ROS clock), a sample this far from the offset '
                                   'is an outlier', 0.0, None)
    max_consecutive_outliers: int = param(
        5, 'outliers in a row taken as a time jump: reset, re-sync', 0, None)

    def __post_init__(self):
        for name in ('period_s', 'init_request_period_s', 'max_rtt_s', 'max_deviation_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f'timesync {name} must be finite and > 0, got {v}')
        for name in ('alpha', 'beta'):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 < v <= 1.0):
                raise ValueError(f'timesync {name} must be in (0, 1], got {v}')
        for name in ('init_samples', 'max_consecutive_outliers'):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f'timesync {name} must be an integer >= 1, got {v}')


@dataclass(frozen=True)
class TimeSyncStatus:
    """Snapshot for /diagnostics."""

    synced: bool
    offset_ns: int | None           # ROS - boot at the last sample, None while unsynced
    skew_ppm: float | None          # rate of the offset, 1e-6 ns per ns (> 0: boot clock slow)
    accepted: int                   # samples used (initialisation + tracking)
    rejected_rtt: int               # round trip above max_rtt_s (or negative)
    rejected_outliers: int          # farther than max_deviation_s from the estimate
    unmatched: int                  # answers to no request of ours (ignored)
    resets: int                     # time jumps and reboots
    reboots: int                    # of those, autopilot reboots (its boot time went back)
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
        self.reboots = 0
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
        """ROS time - autopilot boot time (ns) at the last accepted sample; None unsynced."""
        if self._base_ns is None:
            return None
        return self._base_ns + int(round(self._residual_ns))

    @property
    def skew(self) -> float | None:
        """Rate of the offset (ns per ns of ROS time); None while unsynced."""
        return None if self._base_ns is None else self._skew

    def offset_at(self, ros_ns: int) -> int | None:
        """ROS - boot (ns) at ROS time ``ros_ns``, extrapolated with the skew; None unsynced."""
        if self._base_ns is None:
            return None
        return self._base_ns + int(round(self._predict(int(ros_ns))))

    @property
    def init_progress(self) -> int:
        """Accepted samples collected towards the initial median (0 once synced)."""
        return len(self._init)

    def status(self) -> TimeSyncStatus:
        """Return the counters and the estimate."""
        skew = self.skew
        return TimeSyncStatus(self.synced, self.offset_ns,
                              None if skew is None else skew * 1e6, self.accepted,
                              self.rejected_rtt, self.rejected_outliers, self.unmatched,
                              self.resets, self.reboots, self.last_rtt_ns)

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
        t = (ts1_ns + ros_ns) // 2                 # the sample's time: middle of the round trip
        if not self.synced:
            self.accepted += 1
            self._init.append((t, sample))
            if len(self._init) >= self.config.init_samples:
                self._start()
                events.append(('info', f'clock synced with the autopilot: ROS - boot = '
                                       f'{self._base_ns / NS_PER_S:.6f} s, skew '
                                       f'{self._skew * 1e6:+.0f} ppm (median of '
                                       f'{self.config.init_samples} TIMESYNC samples)'))
            return events
        residual = (sample - self._base_ns) - self._predict(t)
        if abs(residual) > self._max_dev_ns:
            self.rejected_outliers += 1
            self._outliers.append((t, sample))
            if len(self._outliers) >= self.config.max_consecutive_outliers:
                self._rejump(events, residual)
            return events
        self.accepted += 1
        self._outliers = []
        self._k += 1
        k = self._k
        a = max(self.config.alpha, 2.0 * (2 * k - 1) / (k * (k + 1)))
        b = max(self.config.beta, 6.0 / (k * (k + 1)))
        dt = t - self._t_ref
        self._residual_ns = self._predict(t) + a * residual
        if dt > 0:
            self._skew += b * residual / max(dt, self._period_ns)
            self._t_ref = t
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
            self.reboots += 1
            self._last_boot_ns = {kind: boot_ns}
            return [('warn', f'autopilot {kind} went back from {last / NS_PER_S:.3f} s to '
                             f'{boot_ns / NS_PER_S:.3f} s: reboot, clock sync reset')]
        return []

    def reset(self) -> None:
        """Forget the offset (counted): unsynced until ``init_samples`` new samples."""
        self.resets += 1
        self._clear()

    def _rejump(self, events: list, residual: float) -> None:
        """Start again from the outliers of a time jump's streak (counted as a reset).

        They passed the RTT gate, as initial samples must, and they are what the clock pair
        reads after the jump: the newest ``init_samples`` of them are taken as the new initial
        samples (their median, as at the start; synced at once when the streak is that long),
        so imu/data goes on without the gap that waiting for new samples leaves. (MAVROS's
        sys_time discards them and stamps with its receive time until it converges again.)

        The rate: a clock that was set keeps its rate, so the skew learnt so far is kept when
        the streak lies on it (every sample within ``max_deviation_s`` of the line of that
        slope through the streak's median). When it does not, the rate itself was wrong (PX4
        SIH runs 13 % slow for seconds after a freeze: 13 ms per 0.1 s request period, beyond
        the gate, so the tracker never sees a sample to learn it from and resets every
        0.5 s): the streak's own slope is taken, the median of its pairwise slopes
        (Theil-Sen: one wrong sample of five cannot move it).
        """
        streak = self._outliers[-self.config.init_samples:]
        skew = self._skew
        if len(streak) >= 2 and not _lies_on(streak, skew, self._max_dev_ns):
            skew = _theil_sen_slope(streak)
        self.reset()
        self._init = streak
        if len(streak) >= self.config.init_samples:
            self._start(skew)
        events.append(('warn', f'TIMESYNC: {len(streak)} samples in a row more than '
                               f'{self.config.max_deviation_s * 1e3:.1f} ms from the offset '
                               f'(last {residual / 1e6:+.1f} ms): time jump, clock sync '
                               're-initialised from them' + (
                                   f': ROS - boot = {self._base_ns / NS_PER_S:.6f} s'
                                   if self.synced else '')))

    # --- mapping -----------------------------------------------------------------------------
    def boot_ms_to_ros_ns(self, time_boot_ms: int) -> int | None:
        """Autopilot time_boot_ms -> ROS time (ns); None while unsynced."""
        offset = self.offset_ns
        if offset is None:
            return None
        boot_ns = int(time_boot_ms) * NS_PER_MS
        return boot_ns + self.offset_at(boot_ns + offset)

    def ros_ns_to_boot_ms(self, ros_ns: int) -> int | None:
        """ROS time (ns) -> autopilot time_boot_ms, nearest ms (halves up); None unsynced."""
        offset = self.offset_at(ros_ns)
        if offset is None:
            return None
        return (int(ros_ns) - offset + NS_PER_MS // 2) // NS_PER_MS

    def _predict(self, t: int) -> float:
        """Offset - base (ns) extrapolated to ROS time t."""
        return self._residual_ns + self._skew * (t - self._t_ref)

    def _start(self, skew: float = 0.0) -> None:
        """Start from the median of the initial samples at the latest one's time.

        Each sample is first brought to that time with ``skew`` (0 at the first start: an
        actual sample, exact integer; after a time jump, see :meth:`_rejump`).
        """
        self._t_ref, self._base_ns = _median_at_latest(self._init, skew)
        self._skew = skew
        self._residual_ns = 0.0
        self._k = len(self._init)
        self._init = []

    def _clear(self) -> None:
        self._base_ns: int | None = None
        self._residual_ns = 0.0
        self._skew = 0.0
        self._t_ref = 0
        self._k = 0
        self._init: list[tuple[int, int]] = []
        self._outliers: list[tuple[int, int]] = []     # (t, sample) of the current streak


def _median_at_latest(samples: list, skew: float) -> tuple[int, int]:
    """(latest t, lower median of the samples brought to it along ``skew``); ns, integers."""
    t_ref = max(t for t, _ in samples)
    return t_ref, statistics.median_low([s + int(round(skew * (t_ref - t)))
                                         for t, s in samples])


def _lies_on(samples: list, skew: float, tolerance_ns: int) -> bool:
    """Whether every (t, sample) is within ``tolerance_ns`` of the line of slope ``skew``.

    The line goes through the samples' median at the latest one's time.
    """
    t_ref, base = _median_at_latest(samples, skew)
    return all(abs(s + skew * (t_ref - t) - base) <= tolerance_ns for t, s in samples)


def _theil_sen_slope(samples: list) -> float:
    """Lower median of the pairwise slopes (ns per ns) of (t, sample); 0.0 if t never moves."""
    slopes = [(s2 - s1) / (t2 - t1) for i, (t1, s1) in enumerate(samples)
              for t2, s2 in samples[i + 1:] if t2 != t1]
    return statistics.median_low(slopes) if slopes else 0.0


class TimesyncExchange:
    """The TIMESYNC message exchange around a :class:`TimeSync` (no I/O of its own).

    ``send(tc1, ts1)`` sends one TIMESYNC (ns) and returns whether it left. :meth:`request` sends
    our requests when the estimator wants one; :meth:`on_message` answers the autopilot's own
    requests (``tc1 = 0``; PX4 sends them at ~10 Hz) with ``tc1`` = our ROS time, ``ts1`` echoed,
    as MAVROS does, and hands the answers to ours (``tc1 > 0``) to the estimator. Nothing is
    sent or used while the ROS time is unknown (None or 0: no ``/clock`` yet under
    use_sim_time), since ``tc1 = 0`` would read as a request.
    """

    def __init__(self, sync: TimeSync, send) -> None:
        self.sync = sync
        self._send = send
        self.answered = 0                  # the autopilot's requests we answered

    def request(self, ros_ns: int | None, steady_s: float) -> None:
        """Send a request if the estimator wants one now."""
        ts1 = self.sync.next_request(ros_ns, steady_s)
        if ts1 is not None:
            self._send(0, ts1)

    def on_message(self, tc1: int, ts1: int, ros_ns: int | None) -> list[tuple[str, str]]:
        """Take one TIMESYNC received at ROS time ``ros_ns``; return (level, text) events."""
        tc1, ts1 = int(tc1), int(ts1)
        if ros_ns is None or ros_ns <= 0:
            return []
        if tc1 == 0:
            if self._send(int(ros_ns), ts1):
                self.answered += 1
            return []
        if tc1 > 0:
            return self.sync.on_reply(tc1, ts1, int(ros_ns))
        return []


class RosTime:
    """The latest ROS time the node gave the bridge (ns): the clock of stamps and vehicle time.

    System time on a vehicle, sim time in the sim; None or 0 while unknown (no ``/clock`` yet).
    """

    def __init__(self) -> None:
        self.ns: int | None = None

    def set(self, ros_ns: int | None, force: bool = False) -> None:
        """Take ``ros_ns``; None keeps the latest unless ``force``."""
        if ros_ns is not None or force:
            self.ns = None if ros_ns is None else int(ros_ns)

    @property
    def vehicle_s(self) -> float | None:
        """Vehicle time: the ROS clock (s), None while unknown."""
        if self.ns is None or self.ns <= 0:
            return None
        return self.ns / NS_PER_S
