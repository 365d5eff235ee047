"""Whether the preflight's verdict lets a mission start (ROS-free).

The preflight (``ibvs_bringup.preflight``) publishes its go / no-go on ``ibvs/preflight``
when it ends. :class:`PreflightGate` keeps the latest verdict and says whether a start must
be refused: while the latest verdict is no-go (or unreadable), unless the gate is off
(``require_preflight_go: false``, the operator's override). Without any verdict (the
preflight not run since the supervisor started: the sim, a bench, a scripted run with its
own checks) a start is not refused; the node says so in its log.
"""
from __future__ import annotations

from dataclasses import dataclass

OVERRIDE_HINT = ('fix it and run the preflight again, or start the graph with '
                 'require_preflight_go: false to override')


@dataclass(frozen=True)
class Verdict:
    """One preflight verdict: go or not, its summary line, when it came (node clock, s)."""

    go: bool
    summary: str
    t: float


class PreflightGate:
    """The latest preflight verdict and the start refusal it implies."""

    def __init__(self, required: bool) -> None:
        """Keep no verdict yet; ``required``: refuse a start while the latest one is no-go."""
        self.required = bool(required)
        self.verdict: Verdict | None = None

    def on_verdict(self, go: bool | None, summary: str, t: float) -> None:
        """Take a verdict (``go`` None: unreadable, ``summary`` why): it counts as no-go."""
        if go is None:
            go, summary = False, f'unreadable preflight verdict ({summary})'
        self.verdict = Verdict(bool(go), str(summary), float(t))

    def refusal(self) -> str | None:
        """Return why a start must be refused now, or None to let it go on."""
        v = self.verdict
        if not self.required or v is None or v.go:
            return None
        return f'preflight no-go: {v.summary}; {OVERRIDE_HINT}'

    def note(self) -> str | None:
        """Return what to log about a start that is not refused (None: a go, nothing to say)."""
        v = self.verdict
        if v is None:
            return 'no preflight verdict received (ibvs/preflight): started without one'
        if not v.go:
            return f'preflight no-go overridden (require_preflight_go: false): {v.summary}'
        return None
