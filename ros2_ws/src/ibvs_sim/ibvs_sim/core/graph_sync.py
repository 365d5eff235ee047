"""Keeping the sim in step with the graph: what a frame waits for before it goes.

- :class:`FirstFrameHold`: frame 0 waits until the graph is there to answer it (image
  subscribers, the companion's setpoints), in both pacings;
- :class:`ImuBeforeImages`: lockstep, a frame's images wait until ``imu/data`` reached the
  newest sample the autopilot sent by their delivery;
- :class:`GraphProducts`: lockstep, the next frame waits until the graph published every
  product of the last one (:class:`~ibvs_sim.core.pacing.LockstepGate` asks it).

ROS-free: the sim node feeds them subscriber counts and message stamps.
"""
from __future__ import annotations

from typing import Collection, TYPE_CHECKING

from ibvs_common.core.frame_grid import GridFollower
from ibvs_common.core.modes import InputKind, Mode, MODE_INPUTS, modes_using

if TYPE_CHECKING:
    from ibvs_sim.core.sim_core import FrameOutput

STATUS_TOPIC = 'ibvs/supervisor_status'   # lockstep: the mode of each evaluated frame
STATUS_HISTORY = 8            # statuses kept by GraphProducts
# lockstep: what the graph publishes for each camera frame (docs/interfaces.md), by camera
PRODUCT_CAMERAS = {'window/corners': 'front', 'front_camera/translational_flow': 'front',
                   'pad/landmarks': 'down', 'pad/groups': 'down',
                   'down_camera/translational_flow': 'down'}
# the product behind each topic: its node computes it only in the modes that use it
PRODUCT_KINDS = {'window/corners': InputKind.WINDOW,
                 'front_camera/translational_flow': InputKind.FLOW_FRONT,
                 'pad/landmarks': InputKind.PAD, 'pad/groups': InputKind.PAD,
                 'down_camera/translational_flow': InputKind.FLOW_DOWN}


class FirstFrameHold:
    """Whether the first frame may go: the graph is there to answer it (docs/sim.md).

    Each counted topic needs its minimum number of subscribers (``min_counts``) and, with
    ``need_setpoints``, the companion must stream setpoints, both for ``settle_s`` before the
    release; after ``timeout_s`` the frame goes anyway (``timed_out``). Times are one monotonic
    clock (s); no minimum and no need_setpoints never holds.
    """

    def __init__(self, min_counts: dict, settle_s: float, timeout_s: float, now: float,
                 need_setpoints: bool = False) -> None:
        if any(int(c) < 0 for c in min_counts.values()) or settle_s < 0.0 \
                or not timeout_s > 0.0:
            raise ValueError(f'need counts >= 0, settle_s >= 0, timeout_s > 0; got '
                             f'{min_counts}, {settle_s}, {timeout_s}')
        self.min_counts = {k: int(c) for k, c in min_counts.items()}
        self.settle_s = float(settle_s)
        self.need_setpoints = bool(need_setpoints)
        self.deadline = now + timeout_s
        self.released = not any(self.min_counts.values()) and not need_setpoints
        self.timed_out = False
        self._since: float | None = None

    def ready(self, counts: dict, now: float, setpoints: bool = False) -> bool:
        """Update with the subscriber count per topic and whether setpoints stream.

        Return True once (and after) released.
        """
        if self.released:
            return True
        if (all(counts.get(k, 0) >= c for k, c in self.min_counts.items())
                and (setpoints or not self.need_setpoints)):
            self._since = now if self._since is None else self._since
            self.released = now - self._since >= self.settle_s
        else:
            self._since = None
            self.released = self.timed_out = now > self.deadline
        return self.released


class ImuBeforeImages:
    """Lockstep: hold a delivery until ``imu/data`` has reached its IMU time (docs/sim.md).

    That is ``FrameOutput.imu_ns``: the newest sample the autopilot had sent by the delivery
    (the delivery time itself when not given), so every node has the same IMU with the images.

    Before any IMU sample was seen nothing is held; a frame waits at most ``timeout_s`` (wall
    clock, s) and is then released anyway. ``silent_after`` time-outs in a row (imu/data
    stopped: the bridge that publishes it died) and nothing is held until a newer sample
    comes. Disabled (pass-through) outside lockstep.
    """

    def __init__(self, timeout_s: float, enabled: bool = True, silent_after: int = 2) -> None:
        if not timeout_s > 0.0:
            raise ValueError(f'timeout_s must be > 0, got {timeout_s}')
        self.timeout_s = float(timeout_s)
        self.enabled = bool(enabled)
        self.silent_after = int(silent_after)
        self.silent = False                        # imu/data stopped: nothing held
        self.imu_through_ns: int | None = None     # newest IMU stamp seen
        self.timed_out = False
        self.timeouts = 0
        self._in_a_row = 0
        self.held_s = 0.0                          # wall s frames were held, in all
        self._held: FrameOutput | None = None
        self._since = 0.0

    @property
    def holding(self) -> bool:
        """Whether a frame is held."""
        return self._held is not None

    def note_imu(self, stamp_ns: int) -> None:
        """Note an imu/data stamp (ns, ROS clock = sim time)."""
        if self.imu_through_ns is None or stamp_ns > self.imu_through_ns:
            self.imu_through_ns = int(stamp_ns)
            self.silent = False

    def hold(self, frame: FrameOutput, now: float) -> FrameOutput | None:
        """Return the frame if it may go now, else keep it (:meth:`release` gives it later)."""
        if not self.enabled or self.silent:
            return frame
        if self._covered(frame):
            self._in_a_row = 0
            return frame
        self._held, self._since = frame, now
        return None

    def release(self, now: float) -> FrameOutput | None:
        """Return the held frame once the IMU reached it or the wait timed out, else None."""
        frame = self._held
        self.timed_out = False
        if frame is None:
            return None
        if not self._covered(frame):
            if now - self._since < self.timeout_s:
                return None
            self.timed_out = True
            self.timeouts += 1
            self._in_a_row += 1
            if self._in_a_row >= self.silent_after:
                self.silent, self._in_a_row = True, 0
        else:
            self._in_a_row = 0
        self._held = None
        self.held_s += max(0.0, now - self._since)
        return frame

    def _covered(self, frame: FrameOutput) -> bool:
        """Whether imu/data reached the frame's ``imu_ns`` (its delivery time when None)."""
        target = frame.t_ns if frame.imu_ns is None else frame.imu_ns
        return self.imu_through_ns is None or self.imu_through_ns >= target


class GraphProducts:
    """Lockstep: the products the graph makes of a frame, waited for before the next.

    ``products``: topic -> the camera it is made from; ``used_in``: topic -> the modes that
    use it (mode gating; a topic not in it is made in every mode). Expected: the products of
    the cameras whose images went out, with a publisher, that the mode at their image's stamp
    uses (from the supervisor's status of the frame, waited for first when the image of the
    mode's camera went out); a missing one is given up until it is published again
    (docs/sim.md "Loop, pacing and events"). A camera's image off the graph's frame grid
    (``ibvs/frame_grid``: the rate governor computes every 2nd or 4th frame) is owed
    nothing: no status, no product, no answer; nor is a flow (``flow_topics``) off its
    camera's flow grid (the governor sheds the flows).
    """

    def __init__(self, products: dict, used_in: dict | None = None,
                 flow_topics: Collection[str] = ()) -> None:
        self.products = dict(products)
        self.flow_topics = frozenset(flow_topics)
        self.used_in = {t: frozenset(int(m) for m in modes)
                        for t, modes in (used_in or {}).items()}
        self.newest_ns: dict[str, int] = {}
        self.given_up: set[str] = set()
        self.expected: set[str] = set()
        self.frame_ns: int | None = None
        self.stamps_ns: dict[str, int] = {}           # camera -> its image's stamp
        self.status_expected = False
        self.statuses: list[tuple[int, int]] = []     # (stamp ns, mode), newest last
        self.grids: dict[str, GridFollower] = {}      # camera -> the graph's frame grid

    def note_grid(self, camera: str, period_ns: int, stride: int, ref_ns: int,
                  flow: bool = False) -> None:
        """Take the graph's frame grid of ``camera`` (``period_ns``: its frame period).

        ``flow``: the camera's flow grid (the frames its flow is computed on).
        """
        key = (camera, bool(flow))
        follower = self.grids.get(key)
        if follower is None or follower.grid.period_ns != int(period_ns):
            follower = self.grids[key] = GridFollower(int(period_ns))
        follower.update(int(stride), int(ref_ns))

    def on_grid(self, camera: str, stamp_ns: int, flow: bool = False) -> bool:
        """Whether the graph computes the frame of ``camera`` stamped ``stamp_ns``.

        ``flow``: whether it computes that frame's flow (its flow grid, else its frame grid).
        """
        follower = self.grids.get((camera, bool(flow))) or self.grids.get((camera, False))
        return follower is None or follower.on_grid_at(int(stamp_ns))

    def expect(self, frame_ns: int, cameras: Collection[str], publishers: dict,
               stamps_ns: dict | None = None, status: bool = True) -> None:
        """Expect the products of the frame at ``frame_ns`` (images of ``cameras`` went out).

        ``stamps_ns``: camera -> its image's stamp where not ``frame_ns`` (a camera's time
        offset, cameras at other rates); ``status``: whether the frame's status (stamp
        ``frame_ns``) is awaited: the image of the camera the mode is evaluated on went out.
        """
        self.frame_ns = int(frame_ns)
        self.stamps_ns = {c: int((stamps_ns or {}).get(c, frame_ns)) for c in cameras}
        self.expected = {t for t, cam in self.products.items()
                         if cam in self.stamps_ns
                         and self.on_grid(cam, self.stamps_ns[cam], t in self.flow_topics)
                         and publishers.get(t, 0) > 0
                         and t not in self.given_up}
        self.status_expected = status and bool(self.used_in) \
            and publishers.get(STATUS_TOPIC, 0) > 0 and STATUS_TOPIC not in self.given_up \
            and self.on_grid(self.mode_camera(), self.frame_ns)

    def mode_camera(self) -> str:
        """Return the camera the newest status's mode is evaluated on (IDLE's before any)."""
        mode = self.statuses[-1][1] if self.statuses else Mode.IDLE
        return MODE_INPUTS[Mode(mode)].camera.value

    def note_status(self, stamp_ns: int, mode: int) -> None:
        """Note the supervisor's mode of the frame at ``stamp_ns``."""
        self.statuses = self.statuses[-(STATUS_HISTORY - 1):] + [(int(stamp_ns), int(mode))]
        self.given_up.discard(STATUS_TOPIC)

    def mode_at(self, stamp_ns: int) -> int | None:
        """Mode of the newest status stamped at or before ``stamp_ns``, or None."""
        older = [mode for t, mode in self.statuses if t <= stamp_ns]
        return older[-1] if older else None

    def off_grid(self, answer_ns: int | None) -> bool:
        """Whether the frame at ``answer_ns`` of the mode's camera is off the graph's grid."""
        return answer_ns is not None and not self.on_grid(self.mode_camera(), answer_ns)

    def handed_over(self, answer_ns: int, stamps_ns: dict) -> bool:
        """Whether the frame at ``answer_ns`` is owed no answer: it handed the mode over.

        Its status switched to a mode of another camera, which delivered no image of that
        stamp (``stamps_ns``: camera -> the stamp of its image in the delivery): the new mode
        is first flown at that camera's next frame (ibvs_control timing, "Camera handover").
        """
        mode = next((m for t, m in reversed(self.statuses) if t == int(answer_ns)), None)
        if mode is None:
            return False
        return stamps_ns.get(MODE_INPUTS[Mode(mode)].camera.value) != int(answer_ns)

    def note(self, topic: str, stamp_ns: int) -> bool:
        """Note a published product stamped ``stamp_ns``; return True if it was given up."""
        if stamp_ns > self.newest_ns.get(topic, -1):
            self.newest_ns[topic] = int(stamp_ns)
        back = topic in self.given_up
        self.given_up.discard(topic)
        return back

    def missing(self) -> list[str]:
        """Return the expected products of the last frame not yet published.

        The frame's status first, when one is expected; then the products that the mode at
        their image's stamp uses.
        """
        if self.frame_ns is None:
            return []
        if self.status_expected and not any(t >= self.frame_ns for t, _ in self.statuses):
            return [STATUS_TOPIC]
        stamps = {t: self.stamps_ns[self.products[t]] for t in self.expected}
        return sorted(t for t, stamp in stamps.items()
                      if self.newest_ns.get(t, -1) < stamp and self._uses(t, stamp))

    def _uses(self, topic: str, stamp_ns: int) -> bool:
        """Whether the mode at ``stamp_ns`` uses ``topic`` (all of them before any status)."""
        mode = self.mode_at(stamp_ns)
        return mode is None or topic not in self.used_in or mode in self.used_in[topic]

    def give_up(self) -> list[str]:
        """Stop waiting for the missing status and products (until they come again)."""
        gone: list[str] = []
        while (now_missing := self.missing()):
            gone += now_missing
            self.given_up.update(now_missing)
            self.expected.difference_update(now_missing)
            if STATUS_TOPIC in now_missing:
                self.status_expected = False
        return gone


def graph_products() -> GraphProducts:
    """Return the products of this project's graph: by camera, mode-gated (PRODUCT_KINDS)."""
    return GraphProducts(dict(PRODUCT_CAMERAS),
                         {t: modes_using(k) for t, k in PRODUCT_KINDS.items()},
                         {t for t, k in PRODUCT_KINDS.items()
                          if k in (InputKind.FLOW_FRONT, InputKind.FLOW_DOWN)})
