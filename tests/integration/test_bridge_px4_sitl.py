"""The bridge core against PX4 v1.16 SITL (SIH): clock sync, engage, arm on request, hand back.

Uses ``../shared/px4-sitl`` (PX4 v1.16.0 SITL with its SIH simulator) next to the repository; the
tests SKIP when it is absent (a user's clone does not have it). A fresh PX4 for every test (started
in ~5 s, stopped at its end), so no test inherits another's vehicle state. No ROS: the bridge core
(:class:`~ibvs_control.mavlink.bridge.MavlinkBridge`) runs with the shipped params.yaml
(:func:`shipped_parameters`) on PX4's companion port (``udpin:``), polled every 4 ms (the node
reads on arrival, MavlinkReader), with ROS time = ``time.time_ns()`` (the system time a camera
driver stamps images in). In the flights a test controller sends, per 20 ms frame, a heading then a
force: an altitude PD on SIH's ground truth (HIL_STATE_QUATERNION on port 19410 + i) and commanded
roll / pitch / yaw (:class:`Flight`). Run with ``-s`` to see the figures (docs/mavlink.md "Measured
against real autopilots"). ``test_bridge_ardupilot_sitl.py`` uses this harness against ArduCopter.

Clock sync: the offset converges (synced, no reset, many accepted samples); every IMU sample's
stamp is close to the system time at which the bridge received it; the imu/data attitude and
rates are the autopilot's ATTITUDE_QUATERNION converted to ENU/FLU (converted here by hand:
map = ENU from NED, base_link = FLU from FRD).

What limits the stamps' accuracy here (measured, docs/mavlink.md "Clock sync"): the bridge reads
the link every 4 ms, so an answer waits up to 4 ms in the socket (offset up to 2 ms high); PX4
SIH's boot clock advances in 4 ms steps and runs ~1 % slow, wandering by a few ms (tc1 is the
start of the current step: offset up to 4 ms high); ArduCopter SITL back-dates tc1 by the serial
transfer time of the request at SERIAL1_BAUD (4.5 ms at the default 57600; we start it at 921600,
as a companion link is). Hence the stamp of a sample may lie a few ms after its receipt:
accepted down to -LATE_STAMP_TOLERANCE_MS.
"""
from __future__ import annotations

import gc
import os
from pathlib import Path
import re
import signal
import socket
import statistics
import subprocess
import threading
import time

import numpy as np
import pytest
import yaml

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil  # noqa: E402

from ibvs_common.core.config import load_vehicle  # noqa: E402
from ibvs_common.core.frames import GRAVITY  # noqa: E402
from ibvs_control.mavlink.bridge import BridgeConfig, MavlinkBridge  # noqa: E402
from ibvs_control.core.pilot_input import PilotInput  # noqa: E402
from ibvs_control.mavlink.link import LinkConfig  # noqa: E402
from ibvs_control.mavlink.pilot_switch import PilotSwitchConfig  # noqa: E402
from ibvs_control.mavlink.sequencer import px4_main_mode  # noqa: E402
from ibvs_harness.px4_sih import renice_threads, SITL_NICE  # noqa: E402
from ibvs_sim.core.autopilot import AutopilotConfig  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / 'shared'
PX4_DIR = SHARED / 'px4-sitl'
AP_DIR = SHARED / 'ardupilot-sitl'
POLL_PERIOD_S = 0.004              # the test polls the core (the node reads on arrival)
RUN_S = 6.0                        # s of listening after the start
SYNC_WITHIN_S = 2.0                # s after the first HEARTBEAT
MAX_AGE_MS = 20.0                  # receipt - stamp at most this for 90 % of the samples
#                                    (the rest: this 2-core machine stalled a process)
LATE_STAMP_TOLERANCE_MS = 12.0     # receipt - stamp at least -this (module doc: SITL clocks)
# autopilot clock jump: the one-way delay floor moved this much beyond the clock's rate: the
# bridge's deviation gate (timesync_max_deviation_s, 10 ms) less SIH's 4 ms clock grid, so a
# jump that can put samples beyond the gate counts (lenient)
JUMP_MS = 6.0
# PX4 SIH's boot clock against the system clock: 7700 ppm on a quiet machine (time_sync.py);
# 18800-27600 ppm on 2026-11-26 afternoon, when this machine ran 2.3 x slower and SIH's clock
# stalled and caught up (2 resets with 1 jump seen by the floors below: a CI failure); 14200
# ppm on 2026-11-26 evening (same slow machine, integration tests beside it), where one stamp
# lay 12.7 ms after its receipt (> LATE_STAMP_TOLERANCE_MS; median -3.4 ms, no reset). Beyond
# this (~1.4 x the quiet figure) the SITL is starved and its clock is not an autopilot's: the
# sync is not judged. Measured by the test itself (Run.clock_rate_ppm), not taken from the
# estimator under test: CI 21 failed when the bridge's skew, reset to 0 by time jumps, read
# +142 ppm for a SITL clock 2.4-4 % slow (estimator fixed since: a jump keeps the skew)
MAX_SITL_SKEW_PPM = 11000.0
# Clock jumps of PX4 after a 3 s SIGSTOP beyond which its SITL is starved (quiet: 1-3, a loaded
# CI run 6 that settled; a slow hour 11-35 that never did)
MAX_JUMPS_AFTER_FREEZE = 8
# A SITL's console log lines that say its simulated sensors stopped (Flight.skip_if_sensors_lost)
SENSOR_LOSS = re.compile(r'failed:\s+TIMEOUT|No valid data from')
SKEW_AGREEMENT_PPM = 3000.0        # bridge's skew vs the floors' rate, a run without jumps
JUMP_WINDOW_S = 0.2                # s, windows of the one-way delay floor
AFTER_JUMP_S = 1.0                 # s after a jump whose samples are not judged
# a poll this long after the previous one found its samples waiting in the socket for the test
# (this harness starved, not the stamps late): their receipt - stamp is not judged (CI of
# 6f594cc: p90 57.7 ms on a starved machine, rtt p95 20 ms, 14 TIMESYNC answers rejected)
HARNESS_STALL_MS = 3 * POLL_PERIOD_S * 1e3
MS = 1_000_000
VEHICLE_MASS = load_vehicle().mass         # the controller's mass (vehicle.yaml), as in the graph

R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FRD_FLU = np.diag([1.0, -1.0, -1.0])

# One PX4 per test (fixture ``px4``): in session 6 the tests shared one PX4 SIH, and in 2 of 2
# fresh-clone CI runs a test inherited the state the previous one had left (a failsafe, a mode)
# and its setpoint stream stopped (the bridge honours a mode change as a takeover).
# one SITL at a time (instance 9's ports), on one pytest-xdist worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group('sitl')]


def rotmat(q):
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def free_instance(*bases: int, tcp_bases: tuple = ()) -> int:
    """An instance number whose UDP ports 14540 + i (and base + i for each base) are free.

    ``tcp_bases``: TCP ports base + 10 i (ArduPilot's SERIAL0 server 5760 + 10 i) that must be
    free too, bound without SO_REUSEADDR as ArduPilot does: a port the previous SITL left in
    TIME_WAIT is taken (measured: "bind failed on port 5850" when a test started right after
    another).
    """
    for i in range(9, -1, -1):
        free = True
        ports = [(socket.SOCK_DGRAM, base + i) for base in (14540,) + bases]
        ports += [(socket.SOCK_STREAM, base + 10 * i) for base in tcp_bases]
        for kind, port in ports:
            with socket.socket(socket.AF_INET, kind) as s:
                try:
                    s.bind(('0.0.0.0' if kind == socket.SOCK_STREAM else '127.0.0.1', port))
                except OSError:
                    free = False
        if free:
            return i
    pytest.skip('no free autopilot instance (UDP ports 14540-14549 all taken)')


def px4_launcher(tmp_path: Path) -> Path:
    """The px4-sih script; through a private bin/ when the px4-* command links are plain files.

    PX4's start script runs px4-param etc., which must be links to the px4 binary (PX4 puts the
    binary's folder on PATH); a copy of the folder that turned them into 3-byte text files
    ("px4") makes PX4 exit at start. The private folder holds only symbolic links.
    """
    script = PX4_DIR / 'px4-sih'
    if os.access(PX4_DIR / 'bin' / 'px4-param', os.X_OK):
        return script
    shadow = tmp_path / 'px4-sitl'
    (shadow / 'bin').mkdir(parents=True)
    for f in (PX4_DIR / 'bin').iterdir():
        link = shadow / 'bin' / f.name
        if f.name.startswith('px4-') and f.stat().st_size < 16 \
                and f.read_text().strip() == 'px4':
            link.symlink_to('px4')
        else:
            link.symlink_to(f)
    (shadow / 'etc').symlink_to(PX4_DIR / 'etc')
    (shadow / 'px4-sih').symlink_to(script)     # it finds bin/ and etc/ next to itself
    return shadow / 'px4-sih'


def start(script: Path, args: list) -> dict:
    """Run ``script start args``; return its NAME=VALUE lines (the autopilot is up).

    The autopilot's threads then run at ``SITL_NICE``, as in px4_scenario: on a vehicle it
    has a processor of its own, here it shares two cores with the tests of the other worker
    (a CI run starved PX4 until its baro and compass timed out and it never landed).
    """
    out = subprocess.run([str(script), 'start', *args], capture_output=True, text=True,
                         timeout=90)
    env = dict(line.split('=', 1) for line in out.stdout.split() if '=' in line)
    if out.returncode != 0:
        raise RuntimeError(f'{script} start failed ({out.returncode}): {out.stderr[-2000:]}')
    pid = env.get('PX4_PID') or env.get('AP_PID')
    if pid:
        print(f'{script.name} (PID {pid}): {renice_threads(int(pid), SITL_NICE)}')
    return env


class Run:
    """The bridge core polled like the node; records what it got and what it made of it."""

    def __init__(self, url: str, **config) -> None:
        cfg = BridgeConfig(link=LinkConfig(url=url), mass=1.0, max_thrust_factor=2.0,
                           configured_hover_thrust=0.5, hover_thrust_source='config', **config)
        self.bridge = MavlinkBridge(cfg)
        self.bridge.setpoints.enabled = False     # listen only
        self.polls = []   # (ROS ns of the poll, synced before, synced after, raw, samples)
        self.events = []
        self.reset_ns = []    # ROS ns of the polls in which the bridge's clock sync reset
        self.t_link = self.t_sync = None
        self._raw = []
        link_poll = self.bridge.link.poll

        def tee(*args, **kw):
            msgs = link_poll(*args, **kw)
            self._raw = msgs
            return msgs
        self.bridge.link.poll = tee

    def rate_hz(self, kind: str, last_s: float) -> float:
        """Messages of ``kind`` a second received in the last ``last_s`` of the polls."""
        t_end = self.polls[-1][0]
        n = sum(1 for ros, _, _, raw, _ in self.polls if ros > t_end - last_s * 1e9
                for m in raw if m.get_type() == kind)
        return n / last_s

    def spin(self, seconds: float) -> None:
        b = self.bridge
        t0 = next_t = time.monotonic()
        while time.monotonic() - t0 < seconds:
            ros = time.time_ns()
            synced, resets = b.time_sync.synced, b.time_sync.resets
            samples = b.poll(ros)
            if b.time_sync.resets != resets:
                self.reset_ns.append(ros)
            self.polls.append((ros, synced, b.time_sync.synced, self._raw, samples))
            self.events += b.pop_events()
            now = time.monotonic() - t0
            if self.t_link is None and b.link.link_up:
                self.t_link = now
            if self.t_sync is None and b.time_sync.synced:
                self.t_sync = now
            next_t += POLL_PERIOD_S
            time.sleep(max(0.0, next_t - time.monotonic()))

    def close(self) -> None:
        self.bridge.close()

    # --- what was measured ---
    def ages_ms(self) -> np.ndarray:
        """System time at receipt - stamp (ms) of every IMU sample published."""
        return np.array([(ros - s.stamp_ns) / MS for ros, _, _, _, samples in self.polls
                         for s in samples])

    def rtts_ms(self) -> np.ndarray:
        """Round trips (ms) of the answers to our TIMESYNC requests."""
        return np.array([(ros - m.ts1) / MS for ros, _, _, raw, _ in self.polls for m in raw
                         if m.get_type() == 'TIMESYNC' and m.tc1 > 0])

    def clock_quantum_ms(self) -> float:
        """Resolution of the autopilot's boot clock seen in tc1 (ms): its grid."""
        tc1 = [int(m.tc1) // 1000 for _, _, _, raw, _ in self.polls for m in raw
               if m.get_type() == 'TIMESYNC' and m.tc1 > 0]
        return float(np.gcd.reduce(np.array(tc1, dtype=np.int64))) / 1000.0 if tc1 else 0.0

    def floors(self) -> tuple[np.ndarray, np.ndarray]:
        """(window start ROS ns, floor ns) of the one-way delay, seen without TIMESYNC.

        The floor of (receipt - time_boot_ms) over the ATTITUDE_QUATERNION of a JUMP_WINDOW_S
        window is the offset plus the smallest transport delay.
        """
        floors = {}
        for ros, _, _, raw, _ in self.polls:
            for m in raw:
                if m.get_type() == 'ATTITUDE_QUATERNION':
                    w = ros // int(JUMP_WINDOW_S * 1e9)
                    d = ros - int(m.time_boot_ms) * MS
                    floors[w] = min(floors.get(w, d), d)
        keys = sorted(floors)
        return (np.array(keys, dtype=np.int64) * int(JUMP_WINDOW_S * 1e9),
                np.array([floors[k] for k in keys], dtype=np.int64))

    def clock_rate_ppm(self) -> float | None:
        """The autopilot clock's rate against ours (ppm, > 0: slow), from the floors.

        The slope of a least-squares line through the floors: the test's own measurement of
        what the bridge's skew estimates (a second method); None with fewer than 5 windows.
        """
        t, f = self.floors()
        if len(t) < 5:
            return None
        return float(np.polyfit((t - t[0]) / 1e9, (f - f[0]) / 1e3, 1)[0])    # us/s = ppm

    def clock_jumps(self) -> list:
        """ROS times (ns) where the autopilot's clock jumped against ours, seen without TIMESYNC.

        A floor that moved by more than JUMP_MS from the previous window's beyond the clock's
        rate (clock_rate_ppm): the SITL's simulated clock stalled or caught up (this machine is
        loaded), a real time jump. A delayed burst counts too (lenient).
        """
        t, f = self.floors()
        rate = self.clock_rate_ppm() or 0.0
        moves = np.diff(f) - rate * 1e-6 * np.diff(t)
        return [int(b) for b, move in zip(t[1:], moves) if abs(move) > JUMP_MS * MS]

    def stalled_polls(self) -> list:
        """Indices of the polls that came more than HARNESS_STALL_MS after the previous one."""
        ros = np.array([p[0] for p in self.polls], dtype=np.int64)
        return [int(i) + 1 for i in np.flatnonzero(np.diff(ros) > HARNESS_STALL_MS * MS)]

    def judged_ages_ms(self, after_stalls: bool = False) -> np.ndarray:
        """Receipt - stamp (ms) of the samples not within AFTER_JUMP_S after a clock jump.

        Only those of punctual polls, unless ``after_stalls``: a poll after a stall of this
        harness (``stalled_polls``) adds the test's own delay to the age (it can only raise
        it, so the check of early stamps takes them all).
        """
        jumps = self.clock_jumps()
        stalled = set() if after_stalls else set(self.stalled_polls())
        return np.array([(ros - s.stamp_ns) / MS
                         for i, (ros, _, _, _, samples) in enumerate(self.polls)
                         if i not in stalled
                         for s in samples
                         if not any(j - JUMP_WINDOW_S * 1e9 <= ros <= j + AFTER_JUMP_S * 1e9
                                    for j in jumps)])

    def pairs(self) -> list:
        """(ATTITUDE_QUATERNION, ImuSample) of the polls where every sample was published."""
        out = []
        for _, before, after, raw, samples in self.polls:
            att = [m for m in raw if m.get_type() == 'ATTITUDE_QUATERNION']
            if before and after and len(att) == len(samples):
                out += list(zip(att, samples))
        return out

    def report(self, name: str) -> str:
        st = self.bridge.status().time_sync
        ages, rtts = self.judged_ages_ms(), self.rtts_ms()
        every = self.ages_ms()
        # unsynced at the end (a reset after a clock jump, not re-synced yet): said, and the
        # check's assertions say why it fails
        offset = 'none' if st.offset_ns is None else f'{st.offset_ns / 1e9:.6f} s'
        skew = 'none' if st.skew_ppm is None else f'{st.skew_ppm:+.0f} ppm'
        rate = self.clock_rate_ppm()
        rate = 'none' if rate is None else f'{rate:+.0f} ppm'
        synced = 'never synced' if self.t_sync is None or self.t_link is None \
            else f'synced {self.t_sync - self.t_link:.2f} s later'
        link = 'no link' if self.t_link is None else f'link after {self.t_link:.2f} s'
        t0 = self.polls[0][0] if self.polls else 0
        stalled = self.stalled_polls()
        gaps = np.diff([p[0] for p in self.polls]) / MS if len(self.polls) > 1 else np.zeros(1)

        def times(ns: list) -> str:
            return '[' + ', '.join(f'{(t - t0) / 1e9:.2f}' for t in ns) + '] s'
        return (f'{name}: {link}, {synced}; offset {offset}, skew {skew} (floors: {rate}); '
                f'TIMESYNC accepted {st.accepted}, rejected rtt {st.rejected_rtt} / outliers '
                f'{st.rejected_outliers}, resets {st.resets} at {times(self.reset_ns)}; rtt '
                f'median {np.median(rtts):.2f} '
                f'ms, p95 {np.percentile(rtts, 95):.2f} ms; boot clock grid '
                f'{self.clock_quantum_ms():.3f} ms; autopilot clock jumps seen '
                f'{len(self.clock_jumps())} at {times(self.clock_jumps())}; IMU receipt - '
                f'stamp over {len(ages)} samples '
                f'(of {len(every)}, those within {AFTER_JUMP_S} s after a jump and those of '
                f'{len(stalled)} polls after a stall of this harness left out; poll gaps p99 '
                f'{np.percentile(gaps, 99):.1f}, max {gaps.max():.1f} ms): '
                f'{spread_ms(ages)}; '
                f'{self.bridge.telemetry.imu_dropped_unsynced} dropped while unsynced')


def spread_ms(values: np.ndarray) -> str:
    """'min .., median .., p90 .., max .. ms' of ``values``, or 'none' when there are none."""
    if not len(values):
        return 'none'
    return (f'min {values.min():.2f}, median {statistics.median(values):.2f}, p90 '
            f'{np.percentile(values, 90):.2f}, max {values.max():.2f} ms')


def check(run: Run, name: str) -> None:
    report = run.report(name)
    print('\n' + report)
    st = run.bridge.status().time_sync
    rate = run.clock_rate_ppm()
    if rate is not None and abs(rate) > MAX_SITL_SKEW_PPM:
        pytest.skip(f'the SITL clock ran {rate:+.0f} ppm off the system clock (> '
                    f'{MAX_SITL_SKEW_PPM:.0f}: a starved machine), clock sync not judged: '
                    f'{report}')
    assert run.t_link is not None, f'no HEARTBEAT: {report}'
    assert run.t_sync is not None and run.t_sync - run.t_link <= SYNC_WITHIN_S, report
    # converged: synced from the median, tracked without a reset unless the autopilot's clock
    # really jumped (SITL under load), most answers used
    assert st.synced and st.accepted >= 20, report
    assert st.resets <= len(run.clock_jumps()), report
    assert st.rejected_outliers <= st.accepted // 5 + 5 * st.resets, report
    if rate is not None and not run.clock_jumps():
        # the bridge's skew against the test's own measurement of the clock rate
        assert abs(st.skew_ppm - rate) <= SKEW_AGREEMENT_PPM, report
    ages = run.judged_ages_ms()
    if len(ages) < 100 and run.clock_jumps():
        # CI 20d: no sample left to judge, the SITL clock jumping again and again (5 jumps
        # in 6 s seen locally the same evening): a starved SITL, as for the skew above
        pytest.skip(f'the SITL clock jumped {len(run.clock_jumps())} times: too few samples '
                    f'({len(ages)}) outside the jumps to judge the clock sync: {report}')
    assert len(ages) >= 100, report
    assert np.percentile(ages, 90) <= MAX_AGE_MS, report
    assert run.judged_ages_ms(after_stalls=True).min() >= -LATE_STAMP_TOLERANCE_MS, report
    assert -LATE_STAMP_TOLERANCE_MS / 2 <= statistics.median(ages) <= MAX_AGE_MS / 2, report
    # nothing published while unsynced, every valid sample once synced
    assert all(not samples for _, _, after, _, samples in run.polls if not after)
    pairs = run.pairs()
    assert len(pairs) >= 100, report
    for m, s in pairs:
        q_ned_frd = [m.q1, m.q2, m.q3, m.q4]
        expected = R_ENU_NED @ rotmat(q_ned_frd) @ R_FRD_FLU
        assert np.allclose(rotmat(s.q_wxyz), expected, atol=1e-6)
        assert np.allclose(s.angular_velocity_flu, [m.rollspeed, -m.pitchspeed, -m.yawspeed],
                           atol=1e-6)


# --- flights: the bridge core with the shipped params, a test controller on ground truth -------

PARAMS_YAML = REPO / 'ros2_ws' / 'src' / 'ibvs_bringup' / 'config' / 'params.yaml'
FORCE_HZ = 50.0                    # the controller's rate (one force per camera frame)
STALL_S = 0.1                      # a gap between two harness steps above this is a stall
ARM_WAIT_S = 15.0     # s (wall), arm request -> engaged, PX4's pre-arm checks included
MAX_TILT = np.radians(25.0)


def shipped_parameters(**overrides) -> dict:
    """The bridge's parameters as it reads the shipped params.yaml (onboard), with test overrides.

    Its code defaults, then the file's ``/**`` block and ``mavlink_bridge`` section.
    """
    from ibvs_common.core.params import node_values
    from ibvs_control.mavlink.config import MavlinkBridgeNodeConfig
    p = node_values(MavlinkBridgeNodeConfig, yaml.safe_load(PARAMS_YAML.read_text()),
                    'mavlink_bridge')
    p.update(overrides)
    return p


def euler_from_q(q):
    """(roll, pitch, yaw) ZYX of a (w, x, y, z) quaternion of FRD in NED."""
    w, x, y, z = q
    return (np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
            np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)),
            np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def heading_q(yaw_ned):
    """ibvs/heading_setpoint quaternion (base_link in map, ENU/FLU) of a NED yaw."""
    a = (np.pi / 2 - yaw_ned) / 2.0
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])


class Truth:
    """The simulator's ground truth: position z (NED, m, from the first sample) and vz."""

    def __init__(self, url: str, request=None) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.request = request             # (msg id, Hz): asked on a GCS link (ArduPilot)
        self.z = self.vz = None
        self.t = None
        self._alt0 = None
        self._asked = -1e9

    def poll(self) -> None:
        now = time.monotonic()
        if self.request is not None and now - self._asked > 2.0 and self.z is None:
            self._asked = now
            self.conn.mav.command_long_send(1, 1, 511, 0, self.request[0],
                                            1e6 / self.request[1], 0, 0, 0, 0, 0)
        while True:
            m = self.conn.recv_match(blocking=False)
            if m is None:
                return
            kind = m.get_type()
            if kind == 'HIL_STATE_QUATERNION':               # PX4 SIH: alt mm, vz cm/s down
                alt, vz = m.alt / 1000.0, m.vz / 100.0
            elif kind == 'SIM_STATE':                        # ArduPilot SITL: alt m, vd m/s
                alt, vz = float(m.alt), float(m.vd)
            else:
                continue
            if self._alt0 is None:
                self._alt0 = alt
            self.z, self.vz, self.t = -(alt - self._alt0), vz, now

    def close(self) -> None:
        self.conn.close()


class PilotRadio:
    """A pilot's radio as a GCS gives it: RC_CHANNELS_OVERRIDE at 10 Hz on the GCS link.

    Channels 1-8 at 1500 us (3, the throttle, at 1000) and ``channel`` at ``us`` (settable);
    PX4 and ArduPilot both feed the override into their RC input, and so into RC_CHANNELS.
    ArduPilot takes it only from its GCS system id (SYSID_MYGCS, 255 by default).
    """

    def __init__(self, url: str, target_system: int, channel: int = 7) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.target_system = target_system
        self.channel = channel
        self.us = 1500
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            rc = [1500, 1500, 1000, 1500, 1500, 1500, 1500, 1500]
            rc[self.channel - 1] = int(self.us)
            self.conn.mav.rc_channels_override_send(self.target_system, 1, *rc)
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)       # a GCS
            while self.conn.recv_msg() is not None:          # keep its socket drained
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()


def check_pilot_switch(rest: Run, radio: PilotRadio) -> None:
    """The bridge reads the pilot's switch from the firmware's RC_CHANNELS, also at rest."""
    rest.spin(1.0)
    rc_hz = rest.rate_hz('RC_CHANNELS', 1.0)
    radio.us = 1100

    def wait(value: PilotInput) -> bool:
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            rest.spin(0.1)
            if rest.bridge.pilot_input() == value:
                return True
        return False
    assert wait(PilotInput.OFF), rest.bridge.status()
    radio.us = 1900
    assert wait(PilotInput.ON), rest.bridge.status()
    print(f'pilot switch: RC_CHANNELS at {rc_hz:.1f} Hz at rest; OFF and ON read')
    assert 7.0 <= rc_hz <= 13.0, rc_hz


class Flight:
    """The bridge core configured from the shipped params.yaml, polled every 4 ms (poll +
    repeat check; the node reads on arrival), HEARTBEAT at 1 Hz, with ROS time = system time,
    and a test controller that sends a heading and then a force per frame at 50 Hz: an
    altitude PD on the simulator's ground truth and the commanded roll / pitch / yaw (the
    force's direction).
    """

    def __init__(self, url: str, truth: Truth, mass: float, **overrides) -> None:
        from ibvs_control.mavlink.bridge import MavlinkBridge
        from ibvs_common.core.params import build
        from ibvs_control.mavlink.config import MavlinkBridgeNodeConfig
        self.bridge = MavlinkBridge(build(MavlinkBridgeNodeConfig, shipped_parameters(
            url=url, **overrides)).bridge_config())
        self.truth = truth
        self.mass = mass                   # what the test controller assumes (vehicle.yaml)
        self.events, self.imu, self.raw = [], [], []   # imu: (receipt ns, sample); raw: (t, msg)
        self.timed_events = []                         # (monotonic s, event)
        self.sent = []                     # (t, q, thrust) of every SET_ATTITUDE_TARGET
        self.commands = []                 # (t, command, params) of every COMMAND_LONG
        self.forces = []                   # t of every force sent
        self.controller_on = False
        self.z_ref, self.roll, self.pitch, self.yaw = -2.0, 0.0, 0.0, 0.0
        self.vz_ref = None                 # a descent rate instead of z_ref
        self._next_force = self._next_hb = 0.0
        self._last_step = None
        self.stalls = []                   # (monotonic s, gap s) of every step gap > STALL_S
        self.autopilot_log: Path | None = None   # the SITL's console log, when known
        # The harness keeps every MAVLink message and pymavlink leaves cyclic garbage: a full
        # collection took up to 98 ms on a quiet machine (more under CI load, where this
        # harness's forces then stopped for more than hold_last_s). Collected at close().
        gc.disable()
        link_poll, send = self.bridge.link.poll, self.bridge.link.send_attitude_target

        def tee(*a, **kw):
            msgs = link_poll(*a, **kw)
            now = time.monotonic()
            self.raw += [(now, m) for m in msgs]
            return msgs

        def tee_send(ms, q, thrust, mask):
            ok = send(ms, q, thrust, mask)
            if ok:
                self.sent.append((time.monotonic(), np.array(q, dtype=float), thrust))
            return ok
        command = self.bridge.link.send_command_long

        def tee_command(cmd, params, *a):
            self.commands.append((time.monotonic(), int(cmd), tuple(params)))
            return command(cmd, params, *a)
        self.bridge.link.poll, self.bridge.link.send_attitude_target = tee, tee_send
        self.bridge.link.send_command_long = tee_command

    # --- driving ---
    def spin(self, seconds: float, until=None) -> bool:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.step()
            if until is not None and until():
                return True
            time.sleep(POLL_PERIOD_S)
        return until is not None and until()

    def step(self) -> None:
        b = self.bridge
        now = time.monotonic()
        if self._last_step is not None and now - self._last_step > STALL_S:
            self.stalls.append((now, now - self._last_step))   # this harness did not run
        self._last_step = now
        self.truth.poll()
        if now >= self._next_hb:
            self._next_hb = now + 1.0
            b.heartbeat()
        ros = time.time_ns()
        self.imu += [(ros, x) for x in b.poll(ros)]          # (receipt, sample)
        if self.controller_on and now >= self._next_force:
            self._next_force = max(self._next_force + 1.0 / FORCE_HZ, now - 0.1)
            self._control(time.time_ns())
        b.stream(time.time_ns())
        new = b.pop_events()
        self.events += new
        self.timed_events += [(now, e) for e in new]

    def _control(self, stamp: int) -> None:
        """Heading, then force, of one frame (as the force controller publishes them)."""
        z, vz = self.truth.z, self.truth.vz
        if z is None:
            a_z = 0.0
        elif self.vz_ref is not None:
            a_z = 2.0 * (self.vz_ref - vz)
        else:
            a_z = np.clip(2.0 * (self.z_ref - z) - 2.5 * vz, -4.0, 4.0)   # NED, m/s^2
        c, s = np.cos, np.sin
        r, p, y = self.roll, self.pitch, self.yaw
        Rz = np.array([[c(y), -s(y), 0], [s(y), c(y), 0], [0, 0, 1]])
        Ry = np.array([[c(p), 0, s(p)], [0, 1, 0], [-s(p), 0, c(p)]])
        Rx = np.array([[1, 0, 0], [0, c(r), -s(r)], [0, s(r), c(r)]])
        b3 = (Rz @ Ry @ Rx)[:, 2]
        T = self.mass * (GRAVITY - a_z) / b3[2]           # vertical part m (g - a_z)
        self.bridge.on_heading(stamp, heading_q(y), time.time_ns())
        self.bridge.on_force(stamp, T * b3, time.time_ns())
        self.forces.append(time.monotonic())

    def longest_stall(self, since: float) -> float:
        """Longest gap (s) between two steps of this harness that ended after ``since``."""
        return max((gap for t, gap in self.stalls if t >= since), default=0.0)

    def skip_if_stalled(self, since: float) -> None:
        """Skip when this harness itself stalled for hold_last_s or more after ``since``.

        Its forces then stopped for that long, and the bridge rightly handed the vehicle back
        (``held``): what the test wanted to judge after that cannot be judged.
        """
        hold_last_s = float(shipped_parameters()['hold_last_s'])
        stall = self.longest_stall(since)
        if stall >= hold_last_s:
            pytest.skip(f'the test harness stalled {stall:.2f} s (>= hold_last_s '
                        f'{hold_last_s} s: CPU load beside it?); its forces stopped and the '
                        f'bridge went {self.state()!r}, as it should')

    def autopilot_log_lines(self) -> list:
        """The lines of the SITL's console log (``autopilot_log``); [] when it is not known."""
        if self.autopilot_log is None or not self.autopilot_log.is_file():
            return []
        return self.autopilot_log.read_text(errors='replace').splitlines()

    def skip_if_sensors_lost(self, what: str) -> None:
        """Skip when the SITL's own log says its simulated sensors timed out or went invalid.

        A PX4 SIH starved beside the other test worker (CI: "MAG #0 failed: TIMEOUT!", then
        "Preflight Fail: No valid data from Baro 0" at every arming check) neither re-arms nor
        lands: ``what`` failed for the autopilot's sake, and the bridge cannot be judged. A
        quiet run logs none of these lines.
        """
        lost = [ln.strip() for ln in self.autopilot_log_lines() if SENSOR_LOSS.search(ln)]
        if lost:
            pytest.skip(f"{what}: the autopilot's own sensors failed ({lost[0]!r}, {len(lost)} "
                        f'such lines in its log): a starved SITL (CPU load beside it), the '
                        f'bridge not judged')

    # --- what the autopilot said ---
    def messages(self, kind: str, since: float = 0.0) -> list:
        return [(t, m) for t, m in self.raw if t >= since and m.get_type() == kind]

    def state(self):
        seq = self.bridge.engagement.sequencer
        return seq.state.value if seq else 'no_link'

    def reason(self):
        seq = self.bridge.engagement.sequencer
        return seq.last_reason if seq else ''

    def hb(self):
        return self.bridge.link.heartbeat

    def attitude(self):
        """(roll, pitch, yaw) of the latest ATTITUDE_QUATERNION."""
        _, m = self.messages('ATTITUDE_QUATERNION')[-1]
        return euler_from_q([m.q1, m.q2, m.q3, m.q4])

    def close(self) -> None:
        self.bridge.close()
        gc.enable()
        gc.collect()


def angle_diff(a, b):
    return float(np.arctan2(np.sin(a - b), np.cos(a - b)))


def step_response(f: Flight, axis: str, value: float, settle_s: float = 1.2,
                  hold_s: float = 0.6) -> float:
    """Command ``axis`` = value, wait ``settle_s``, return the mean error over ``hold_s`` (rad)."""
    setattr(f, axis, value)
    f.spin(settle_s)
    errors = []
    t_end = time.monotonic() + hold_s
    while time.monotonic() < t_end:
        f.step()
        r, p, y = f.attitude()
        got = {'roll': r, 'pitch': p, 'yaw': y}[axis]
        errors.append(angle_diff(got, value))
        time.sleep(POLL_PERIOD_S)
    return float(np.mean(errors))


# --- PX4 ---------------------------------------------------------------------------------------

PX4_HOVER_SIH = 1.0 * GRAVITY / (4 * 5.0)   # SIH defaults: SIH_MASS 1 kg, SIH_T_MAX 5 N x 4
PX4_OFFBOARD, PX4_POSCTL, PX4_AUTO_LAND = 6 << 16, 3 << 16, (4 << 16) | (6 << 24)


@pytest.fixture
def px4(tmp_path):
    """A fresh PX4 SIH for one test (started in ~5 s; stopped at its end, whatever happens)."""
    if not (PX4_DIR / 'px4-sih').exists():
        pytest.skip(f'{PX4_DIR} not found: the PX4 SITL tests need ../shared/px4-sitl next to '
                    'the repository (not part of it)')
    tmp = tmp_path / 'px4'
    tmp.mkdir()
    script = px4_launcher(tmp)
    i = free_instance(19410)
    state = {'script': script, 'i': i, 'args': ['-i', str(i), '-w', str(tmp / 'w')]}
    state['env'] = start(script, state['args'])
    try:
        yield state
    finally:
        os.kill(int(state['env']['PX4_PID']), signal.SIGCONT)     # never left frozen
        subprocess.run([str(script), 'stop', state['env']['PX4_WORKDIR']], timeout=30)


def px4_flight(px4, **overrides) -> Flight:
    i = px4['i']
    truth = Truth(f'udpin:127.0.0.1:{19410 + i}')
    f = Flight(f'udpin:0.0.0.0:{14540 + i}', truth, VEHICLE_MASS, **overrides)
    f.autopilot_log = Path(px4['env']['PX4_LOG']) if px4['env'].get('PX4_LOG') else None
    return f


def ready(f: Flight) -> None:
    ok = f.spin(10.0, until=lambda: f.bridge.link.link_up and f.bridge.time_sync.synced
                and f.bridge.rates.streams is not None and f.bridge.rates.streams.complete
                and f.truth.z is not None and f.state() == 'standby')
    assert ok, f'not ready: {f.state()}, {f.bridge.status()}'


def px4_take_off(f: Flight, z_ref: float = -2.0, arm: bool = True) -> None:
    """IDLE, the controller on, WINDOW: OFFBOARD; then arm on request and climb to z_ref."""
    f.bridge.on_supervisor_mode(0)
    f.controller_on = True
    f.z_ref = f.truth.z
    f.spin(0.3)
    f.bridge.on_supervisor_mode(1)
    ok = f.spin(5.0, until=lambda: f.state() in ('wait_arm', 'engaged'))
    assert ok, f'{f.state()}: {f.bridge.engagement.sequencer.last_reason}'
    if f.state() == 'wait_arm' and arm:
        assert f.bridge.request_arm()[0]
    f.z_ref = z_ref
    # PX4 may refuse to arm for a few seconds right after a landing (a fresh-clone CI run:
    # "Preflight Fail: Battery unhealthy" 0.3 s after the disarm); the bridge waits for
    # SYS_STATUS's pre-arm bit, as it should: wait for PX4, not only for the bridge
    if not f.spin(ARM_WAIT_S, until=lambda: f.state() == 'engaged'):
        f.skip_if_sensors_lost('PX4 never became armable')
    assert f.state() == 'engaged', f.bridge.engagement.sequencer.last_reason
    assert f.spin(10.0, until=lambda: f.truth.z < z_ref + 0.3), f'z {f.truth.z}'


def close_flight(f: Flight) -> None:
    """After a test: close the bridge and the ground-truth link (PX4 is stopped with it).

    Prints the bridge's last events and the autopilot's own log (``f.autopilot_log``, when
    known): pytest shows them when the test failed.
    """
    f.truth.close()
    f.close()
    print('\n--- bridge events (last 40):\n'
          + '\n'.join(f'{t:.2f} {lv}: {text}' for t, (lv, text) in f.timed_events[-40:]))
    print(f'--- harness stalls > {STALL_S} s (ended at, gap s): '
          + (', '.join(f'{t:.2f} {gap:.2f}' for t, gap in f.stalls) or 'none'))
    lines = [ln for ln in f.autopilot_log_lines()
             if 'WARN' in ln or 'ERROR' in ln or 'ailsafe' in ln or 'mode' in ln.lower()]
    if lines:
        print('--- autopilot log, warnings, errors, failsafes and modes (last 40):\n'
              + '\n'.join(lines[-40:]))


def left_our_setpoint(f: Flight, since: float) -> float | None:
    """Receipt time of the first ATTITUDE_TARGET after ``since`` that is not our last setpoint.

    PX4 reports its attitude setpoint at 50 Hz (we asked); our last SET_ATTITUDE_TARGET stays
    its setpoint in OFFBOARD, so the first different one is PX4 flying something else (its
    failsafe): a 20 ms measure of leaving OFFBOARD, where the HEARTBEAT is 1 Hz.
    """
    _, q_last, thrust_last = [s for s in f.sent if s[0] <= since][-1]
    for t, m in f.messages('ATTITUDE_TARGET', since):
        dq = abs(float(np.dot(np.array(m.q, dtype=float), q_last)))
        angle = 2.0 * np.arccos(min(1.0, dq))
        if abs(m.thrust - thrust_last) > 0.03 or angle > np.radians(3.0):
            return t
    return None


def test_px4_imu_and_clock_sync_on_the_system_clock(px4):
    # fresh after the boot, as the figures of docs/mavlink.md (the skew grows with load);
    # the 100 Hz attitude throughout (a vehicle at rest would get 10 Hz after 2 s: below)
    run = Run(px4['env']['PX4_OFFBOARD_URL'], quiet_telemetry_rate_hz=0.0)
    try:
        run.spin(RUN_S)
    finally:
        run.close()
    # At rest (disarmed, supervisor IDLE): PX4 itself sends the attitude at 10 Hz once asked,
    # and at 100 Hz again right after an arm request (nothing else engages here).
    rest = Run(px4['env']['PX4_OFFBOARD_URL'], quiet_telemetry_delay_s=0.5,
               pilot_switch=PilotSwitchConfig(channel=7))
    # the pilot's switch on RC channel 7 (PX4's system id is 1 + its instance)
    radio = PilotRadio(f"udpout:127.0.0.1:{px4['env']['PX4_GCS_PORT']}", px4['i'] + 1)
    try:
        rest.spin(2.0)
        check_pilot_switch(rest, radio)
        at_rest = rest.rate_hz('ATTITUDE_QUATERNION', 1.0), rest.rate_hz('HIGHRES_IMU', 1.0)
        slowed = rest.bridge.status().telemetry_slowed
        assert rest.bridge.request_arm()[0]
        rest.spin(1.5)
        after_arm = rest.rate_hz('ATTITUDE_QUATERNION', 1.0), rest.rate_hz('HIGHRES_IMU', 1.0)
        print(f'PX4 at rest: attitude, IMU {at_rest} Hz; after an arm request {after_arm} Hz')
        assert slowed and not rest.bridge.status().telemetry_slowed
        assert all(7.0 <= r <= 13.0 for r in at_rest), at_rest
        # full rate again: PX4's 100 Hz (76 Hz in a starved CI run), far above the quiet 10 Hz
        assert all(r >= 60.0 for r in after_arm), after_arm
        assert not rest.bridge.link.heartbeat.armed        # an arm request alone arms nothing
    finally:
        radio.close()
        rest.close()
    check(run, 'PX4 v1.16 SITL (SIH)')
    assert run.bridge.status().counters['timesync_answered'] >= 10   # PX4 asks us too
    # PX4's offboard-loss failsafe read and reported (INT32 decoded from PX4's bytewise
    # encoding): SITL's defaults, Position mode after 1 s, are not a dead-bridge landing
    said = [t for _, t in run.events if 'offboard loss' in t or 'dead-bridge' in t]
    print(f'PX4 offboard-loss parameters {run.bridge.params.dead_bridge_params}: {said}')
    assert run.bridge.params.dead_bridge_params == {'COM_OF_LOSS_T': 1.0, 'COM_OBL_RC_ACT': 0.0}
    # the sim's PX4-like autopilot fails safe after the same offboard loss as the real one
    assert AutopilotConfig().offboard_timeout_s == run.bridge.params.dead_bridge_params[
        'COM_OF_LOSS_T']
    assert run.bridge.params.dead_bridge_failsafe is False
    assert len(said) == 1 and 'COM_OBL_RC_ACT = 0 (Position mode)' in said[0], said


def test_px4_engages_arms_only_on_request_tracks_steps_learns_hover_then_fails_safe(px4):
    """Engage, arm on request, steps, the hover estimate, then PX4's own failsafe.

    The harness's own garbage collector once stalled its stream past hold_last_s mid-climb (and
    the bridge rightly handed back): collection is off during flights, and a stall that long
    skips the test with the stall named.
    """
    f = px4_flight(px4)
    try:
        ready(f)
        f.bridge.on_supervisor_mode(0)
        f.controller_on = True
        f.z_ref = f.truth.z
        f.spin(0.3)
        f.bridge.on_supervisor_mode(1)
        assert f.spin(5.0, until=lambda: f.state() == 'wait_arm'), f.reason()
        assert px4_main_mode(f.hb().custom_mode) == 6 and not f.hb().armed
        f.spin(2.0)                                            # engaged, disarmed: no ARM
        assert [c for c in f.commands if c[1] == 400] == [] and not f.hb().armed
        t_req = time.monotonic()
        assert f.bridge.request_arm()[0]
        f.z_ref = -2.0
        assert f.spin(5.0, until=lambda: f.state() == 'engaged'), f.reason()
        arms = [c for c in f.commands if c[1] == 400 and c[2][0] == 1.0]
        assert len(arms) == 1 and arms[0][0] >= t_req
        climbed = f.spin(10.0, until=lambda: f.truth.z < -1.7)
        if not climbed:
            f.skip_if_stalled(t_req)
        assert climbed, (f'z {f.truth.z}', f.state(), f.stalls)
        f.spin(1.0)
        y0 = f.attitude()[2]
        t_steps = time.monotonic()
        errors = {'roll': step_response(f, 'roll', np.radians(10.0))}
        f.roll = 0.0
        errors['pitch'] = step_response(f, 'pitch', np.radians(-10.0))
        f.pitch = 0.0
        errors['yaw'] = step_response(f, 'yaw', angle_diff(y0 + np.radians(30.0), 0.0),
                                      settle_s=2.5)
        dt = time.monotonic() - t_steps
        sp_rate = len([s for s in f.sent if s[0] >= t_steps]) / dt
        force_rate = len([t for t in f.forces if t >= t_steps]) / dt
        est, std = f.bridge.hover.now(), f.bridge.hover.estimator.std
        n_est = f.bridge.hover.estimator.accepted
        deg = {k: np.degrees(v) for k, v in errors.items()}
        print(f'\nPX4 SIH steps, mean error after 1.2 s (yaw 2.5 s): roll 10 deg '
              f'{deg["roll"]:+.2f}, pitch -10 deg {deg["pitch"]:+.2f}, yaw +30 deg '
              f'{deg["yaw"]:+.2f} deg; hover thrust estimate '
              f'{est:.4f} (std {std:.4f}, {n_est} samples; SIH {PX4_HOVER_SIH:.4f}, seed '
              f'MPC_THR_HOVER {f.bridge.hover.seed.value:.3f}); SET_ATTITUDE_TARGET at '
              f'{sp_rate:.1f} Hz with the forces at {force_rate:.1f} Hz')
        if f.state() != 'engaged' or not force_rate * 0.97 <= sp_rate:
            # the old flake's signature (setpoints stopped mid-flight): a stall of the harness
            # >= hold_last_s rightly hands the vehicle back; say so (SKIPPED names the stall)
            f.skip_if_stalled(t_req)
        assert force_rate * 0.97 <= sp_rate <= force_rate * 1.1, (sp_rate, force_rate, f.stalls)
        assert abs(errors['roll']) < np.radians(1.5) and abs(errors['pitch']) < np.radians(1.5)
        assert abs(errors['yaw']) < np.radians(3.0)
        assert est == pytest.approx(PX4_HOVER_SIH, abs=0.015) and n_est > 300
        # The controller goes silent: hold_last_s, then no setpoints; PX4's own failsafe.
        f.controller_on = False
        t_last = f.forces[-1]
        assert f.spin(1.0, until=lambda: f.state() == 'held')
        t_held = time.monotonic()
        assert f.spin(3.0, until=lambda: left_our_setpoint(f, t_last) is not None)
        t_left = left_our_setpoint(f, t_last)
        assert f.spin(3.0, until=lambda: px4_main_mode(f.hb().custom_mode) != 6)
        t_hb = [t for t, m in f.messages('HEARTBEAT', t_last)
                if px4_main_mode(m.custom_mode) != 6][0]
        print(f'PX4 silent controller: held {t_held - t_last:.2f} s after the last force, '
              f'last setpoint {f.sent[-1][0] - t_last:+.2f} s; PX4 left OFFBOARD '
              f'{t_left - t_last:.2f} s after the last force (ATTITUDE_TARGET), heartbeat '
              f'shows custom_mode 0x{f.hb().custom_mode:08x} at {t_hb - t_last:.2f} s')
        hold_last_s = float(shipped_parameters()['hold_last_s'])
        assert hold_last_s - 0.05 <= t_held - t_last <= hold_last_s + 0.2
        assert f.sent[-1][0] <= t_held + 0.05
        # PX4: hold_last_s + COM_OF_LOSS_T (1.0 s); t_left is our receipt of PX4's
        # ATTITUDE_TARGET, so a starved SITL and harness add to it (up to 0.3 s seen in CI
        # with the SITL clock +20000 ppm off)
        assert t_left - t_last <= hold_last_s + 1.0 + 0.5
        t0 = time.monotonic()
        if not f.spin(25.0, until=lambda: not f.hb().armed):
            f.skip_if_sensors_lost('PX4 did not land and disarm')
        assert not f.hb().armed, 'PX4 did not land and disarm'
        modes = []
        for t, m in f.messages('HEARTBEAT', t_last):
            if not modes or modes[-1][1] != m.custom_mode:
                modes.append((round(t - t_last, 1), m.custom_mode))
        print(f'PX4 landed and disarmed itself {time.monotonic() - t0:.1f} s later; heartbeat '
              f'modes (s after the last force, custom_mode): '
              f'{[(t, hex(c)) for t, c in modes]}')
        # OFFBOARD asked while engaging only (again after command_retry_s, 1 s, when PX4 had
        # not switched yet: CI 20d on a loaded machine), never after the hand-back
        set_modes = [c for c in f.commands if c[1] == 176]
        assert f.state() == 'held' and set_modes, set_modes
        assert all(t < t_req and params == (1.0, 6.0) for t, _, params in set_modes), set_modes
        assert all(b[0] - a[0] >= 0.95 for a, b in zip(set_modes, set_modes[1:])), set_modes
    finally:
        close_flight(f)


def test_px4_pilot_takeover_failsafe_land_mode_and_touchdown_disarm(px4):
    f = px4_flight(px4)
    try:
        ready(f)
        px4_take_off(f, -2.0)
        # A GCS asks for POSCTL (PX4 refuses it without RC, which SITL has not), then takes
        # Hold (AUTO.LOITER): the bridge stops at once and does not take the vehicle back.
        n_events, t_posctl = len(f.events), time.monotonic()
        f.bridge.link.send_command_long(176, (1.0, 3.0))       # as a GCS would
        f.spin(1.5)
        posctl = [t for _, t in f.events[n_events:] if 'command 176 answered' in t]
        if f.state() != 'engaged':
            f.skip_if_stalled(t_posctl)
        assert f.state() == 'engaged', 'PX4 took POSCTL without RC?'
        t_cmd = time.monotonic()
        f.bridge.link.send_command_long(176, (1.0, 4.0, 3.0))  # as a GCS would
        assert f.spin(3.0, until=lambda: f.state() == 'held'), f.reason()
        t_held = time.monotonic()
        f.spin(1.5)
        assert f.sent[-1][0] <= t_held + 0.05
        assert f.hb().custom_mode == (4 << 16) | (3 << 24)
        # the mission is over for the graph: ibvs/pilot_input OFF (the supervisor aborts)
        assert f.bridge.pilot_input() == PilotInput.OFF
        print(f'\nPX4 POSCTL asked by a GCS: {posctl}; Hold taken by a GCS: setpoints stopped '
              f'{t_held - t_cmd:.2f} s after the switch (its 1 Hz heartbeat), none since')
        # A new start engages again (armed: no ARM); FAILSAFE -> PX4's AUTO.LAND.
        f.bridge.on_supervisor_mode(0)
        f.bridge.on_supervisor_mode(1)
        f.z_ref = f.truth.z
        assert f.spin(5.0, until=lambda: f.state() == 'engaged'), f.reason()
        f.spin(1.0)
        t_fs = time.monotonic()
        f.bridge.on_supervisor_mode(5)
        assert f.spin(3.0, until=lambda: f.hb().custom_mode == PX4_AUTO_LAND)
        t_land = time.monotonic()
        assert f.spin(2.0, until=lambda: not f.bridge.status().streaming)
        sends = [c for c in f.commands if c[0] >= t_fs and c[1] == 176]
        assert sends[0][2] == (1.0, 4.0, 6.0)
        assert f.spin(25.0, until=lambda: not f.hb().armed), 'no landing'
        print(f'PX4 FAILSAFE: AUTO.LAND shown {t_land - t_fs:.2f} s after, setpoints stopped, '
              f'landed and disarmed {time.monotonic() - t_fs:.1f} s after; bridge {f.state()}')
        assert f.state() == 'done'
        # Touchdown: climb, descend at 0.4 m/s under the controller, SHUTDOWN on the ground.
        f.bridge.on_supervisor_mode(0)
        px4_take_off(f, -1.5)
        f.bridge.on_supervisor_mode(3)
        f.vz_ref = 0.4
        assert f.spin(10.0, until=lambda: f.truth.z > -0.05), f'z {f.truth.z}'
        f.spin(0.5)
        t_sd = time.monotonic()
        f.bridge.on_supervisor_mode(4)
        assert f.spin(10.0, until=lambda: f.state() == 'done'), f.reason()
        disarms = [c for c in f.commands if c[0] >= t_sd and c[1] == 400]
        print(f'PX4 touchdown: disarmed {time.monotonic() - t_sd:.2f} s after SHUTDOWN (ramp '
              f'2 s), disarm commands {[c[2] for c in disarms]}, landed state '
              f'{f.bridge.telemetry.landed_state}')
        # PX4's land detector may still say "in the air" 2 s after the ramp (measured: 2 of 4
        # runs): the touchdown rule then forces the disarm, on the ground only
        assert not f.hb().armed
        assert not f.bridge.engagement.sequencer.disarm_forced or f.truth.z > -0.1, f.truth.z
    finally:
        close_flight(f)


def test_px4_fails_safe_when_the_bridge_dies(px4):
    # The bridge process dies in flight: nothing more leaves it and its socket closes (what a
    # SIGKILL does on the wire). PX4's offboard-loss failsafe must take the vehicle.
    f = px4_flight(px4)
    watch = None
    try:
        ready(f)
        px4_take_off(f, -2.0)
        f.spin(1.0)
        t_kill = time.monotonic()
        f.close()                                              # dead: no poll, no send
        watch = mavutil.mavlink_connection(f'udpin:0.0.0.0:{14540 + px4["i"]}')
        thrust = f.sent[-1][2]
        t_left = t_disarmed = None
        deadline = t_kill + 25.0
        while time.monotonic() < deadline and t_disarmed is None:
            m = watch.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            now = time.monotonic()
            if m.get_type() == 'ATTITUDE_TARGET' and t_left is None \
                    and abs(m.thrust - thrust) > 0.03:
                t_left = now
            if m.get_type() == 'HEARTBEAT' and m.autopilot == 12 and not m.base_mode & 128:
                t_disarmed = now
        print(f'\nPX4 with the bridge dead: its failsafe flies {t_left - t_kill:.2f} s after '
              f'the last setpoint, landed and disarmed {t_disarmed - t_kill:.1f} s after')
        assert t_left is not None and t_left - t_kill <= 1.5
        assert t_disarmed is not None
    finally:
        if watch is not None:
            watch.close()
        close_flight(f)


def test_px4_reconnects_after_a_3_s_freeze(px4):
    f = px4_flight(px4)
    pid = int(px4['env']['PX4_PID'])
    try:
        ready(f)
        f.spin(1.0)
        port = f.bridge.link._conn.port.getsockname()
        os.kill(pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        try:
            f.spin(3.0)
        finally:
            os.kill(pid, signal.SIGCONT)
        t_cont = time.monotonic()
        resets = f.bridge.time_sync.resets
        assert f.spin(10.0, until=lambda: f.messages('HEARTBEAT', t_cont)
                      and f.bridge.link.link_up)
        t_hb = f.messages('HEARTBEAT', t_cont)[0][0]
        ns_cont = time.time_ns()
        reset_times = []              # when the bridge's clock sync saw a time jump (steady s)

        def stamped_again():
            if f.bridge.time_sync.resets > resets + len(reset_times):
                reset_times.append(time.monotonic())
            fresh = [(rx, x) for rx, x in f.imu if rx > ns_cont]
            return f.bridge.time_sync.synced and len(fresh) >= 50 \
                and all(abs(rx - x.stamp_ns) < 20 * MS for rx, x in fresh[-50:])
        if not f.spin(10.0, until=stamped_again):
            jumps = f.bridge.time_sync.resets - resets
            if jumps >= MAX_JUMPS_AFTER_FREEZE:
                # SIH paces PX4's clock with its own thread: starved, it keeps jumping (seen at
                # a slow hour: 11-35 jumps in 10-30 s, never settling); the bridge rightly
                # resets at each, and its part cannot be judged
                pytest.skip(f'PX4\'s SITL clock kept jumping after the freeze ({jumps} jumps '
                            f'in 10 s after SIGCONT, at ' + ', '.join(
                                f'{t - t_cont:.2f}' for t in reset_times) + ' s: a starved '
                            'machine), the re-sync not judged')
            pytest.fail(f'IMU stamps not right 10 s after SIGCONT ({jumps} clock jumps)')
        t_sync = time.monotonic()
        t_settled = max([t_cont] + reset_times)
        c = f.bridge.link.counters
        print(f'\nPX4 frozen {t_cont - t_stop:.1f} s: first heartbeat {t_hb - t_cont:.2f} s '
              f'after SIGCONT, IMU stamped on the system clock again {t_sync - t_cont:.2f} s '
              f'after (clock sync resets {f.bridge.time_sync.resets - resets}, at '
              + ', '.join(f'{t - t_cont:.2f}' for t in reset_times) + ' s; '
              f'{t_sync - t_settled:.2f} s after the last); link losses {c.link_losses}, '
              f'reconnects {c.reconnects}, reopens {c.reopens}; state {f.state()}')
        assert f.bridge.link._conn.port.getsockname() == port and c.reopens == 0
        # How long PX4's clock jumps after the freeze is PX4's and the machine's (quiet: 2-3
        # resets, stamps right again 2.2-2.6 s after SIGCONT; a loaded CI run: 6 resets,
        # 4.4 s). The bridge's part: right stamps soon after the last jump it saw (50 fresh
        # samples at 100 Hz take 0.5 s of that).
        assert t_hb - t_cont < 2.0 and t_sync - t_settled < 2.0
        assert f.state() == 'standby'
    finally:
        os.kill(pid, signal.SIGCONT)
        f.truth.close()
        f.close()


def test_px4_reconnects_after_a_restart(px4):
    f = px4_flight(px4)
    try:
        ready(f)
        subprocess.run([str(px4['script']), 'stop', px4['env']['PX4_WORKDIR']], timeout=30)
        t_stop = time.monotonic()
        f.spin(1.0)
        px4['env'] = start(px4['script'], px4['args'])         # same instance, same ports
        t_up = time.monotonic()
        assert f.spin(15.0, until=lambda: f.bridge.link.link_up and f.bridge.time_sync.synced
                      and f.bridge.rates.streams.complete and f.messages('HEARTBEAT', t_up))
        t_sync = time.monotonic()
        n0, t0 = len(f.messages('ATTITUDE_QUATERNION')), time.monotonic()
        f.spin(2.0)
        new = f.messages('ATTITUDE_QUATERNION')[n0:]
        rate = len(new) / (time.monotonic() - t0)
        # the interval PX4 sends at, in its own time: requested 10 ms (100 Hz), 20 ms by
        # default; a starved PX4 skips some (CI once: 79 Hz on average), not every other one
        interval_ms = float(np.median(np.diff([m.time_boot_ms for _, m in new])))
        print(f'\nPX4 restarted ({t_up - t_stop:.1f} s down): bridge synced and streams '
              f'requested again {t_sync - t_up:.2f} s after PX4 was ready; '
              f'ATTITUDE_QUATERNION at {rate:.0f} Hz, median interval {interval_ms:.0f} ms; '
              f'time sync resets {f.bridge.time_sync.resets}, reopens '
              f'{f.bridge.link.counters.reopens}')
        assert interval_ms <= 14.0 and f.bridge.link.counters.reopens == 0
    finally:
        f.truth.close()
        f.close()
