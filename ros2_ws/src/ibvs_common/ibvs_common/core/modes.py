"""Flight modes (paper section 4.3, docs/spec.md section 3) and the camera products each one uses.

This is the interface between perception and control: the supervisor publishes the mode of
every frame it evaluates (``ibvs/supervisor_status``), the supervisor and the controller wait
for the products a mode *needs* (docs/design.md, "Time"), and each perception node computes
its product only for the frames of a mode that *uses* it (docs/interfaces.md, "Mode gating").
A mode uses what it needs, plus the products it takes as cues without waiting for them (the
pad seen in CROSSING is the cue for LANDING), plus its frame clock: the supervisor opens a
frame when a product of the mode's camera arrives, so SHUTDOWN and FAILSAFE, which need
nothing, are clocked by the floor flow and still evaluate, and answer, every frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum


class Mode(IntEnum):
    """The value published on ``ibvs/mode`` (std_msgs/UInt8)."""

    IDLE = 0        # before start: the autopilot holds the vehicle
    WINDOW = 1      # window approach, F_w (eq:Fw)
    CROSSING = 2    # blind crossing (forward camera lost the window)
    LANDING = 3     # landing, F_t (eq:FT)
    SHUTDOWN = 4    # motors ramped down, then disarm
    FAILSAFE = 5    # an input went stale or an abort: level, slow descent


FLYING_MODES = (Mode.WINDOW, Mode.CROSSING, Mode.LANDING)


def mode_name(mode: int | None) -> str:
    """Return a mode's name (WINDOW, ...) for people to read; '?' for None, else the number."""
    try:
        return Mode(int(mode)).name
    except (TypeError, ValueError):
        return '?' if mode is None else str(mode)


class Camera(str, Enum):
    """The two cameras whose frames the modes are evaluated on."""

    FRONT = 'front'
    DOWN = 'down'


class InputKind(Enum):
    """The products of one camera frame."""

    WINDOW = 'window'             # window/corners (front)
    PAD = 'pad'                   # pad/landmarks + pad/groups (down)
    FLOW_FRONT = 'flow_front'     # front_camera/translational_flow
    FLOW_DOWN = 'flow_down'       # down_camera/translational_flow


CAMERA_OF = {InputKind.WINDOW: Camera.FRONT, InputKind.FLOW_FRONT: Camera.FRONT,
             InputKind.PAD: Camera.DOWN, InputKind.FLOW_DOWN: Camera.DOWN}
FLOW_OF = {Camera.FRONT: InputKind.FLOW_FRONT, Camera.DOWN: InputKind.FLOW_DOWN}


@dataclass(frozen=True)
class ModeInputs:
    """The camera a mode is evaluated on, the products it waits for and all it uses."""

    camera: Camera
    needed: frozenset
    cues: frozenset = frozenset()     # used when present (or as the frame clock), not waited for

    @property
    def used(self) -> frozenset:
        """Every product the mode uses: the needed ones and the cues."""
        return self.needed | self.cues


MODE_INPUTS = {
    Mode.IDLE: ModeInputs(Camera.FRONT, frozenset({InputKind.WINDOW})),
    Mode.WINDOW: ModeInputs(Camera.FRONT, frozenset({InputKind.WINDOW, InputKind.FLOW_FRONT})),
    Mode.CROSSING: ModeInputs(Camera.DOWN, frozenset({InputKind.FLOW_DOWN}),
                              frozenset({InputKind.PAD})),
    Mode.LANDING: ModeInputs(Camera.DOWN, frozenset({InputKind.PAD, InputKind.FLOW_DOWN})),
    # no product needed; the floor flow clocks their frames
    Mode.SHUTDOWN: ModeInputs(Camera.DOWN, frozenset(), frozenset({InputKind.FLOW_DOWN})),
    Mode.FAILSAFE: ModeInputs(Camera.DOWN, frozenset(), frozenset({InputKind.FLOW_DOWN})),
}


def modes_using(kind: InputKind) -> frozenset:
    """Return the modes that use the product ``kind`` (needed or as a cue)."""
    return frozenset(m for m, inputs in MODE_INPUTS.items() if kind in inputs.used)
