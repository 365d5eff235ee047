"""Whether the preflight's verdict lets a mission start (ROS-free).

The preflight (``ibvs_bringup.preflight``) publishes its go / no-go on ``ibvs/preflight``
when it ends. :class:`PreflightGate` keeps the latest verdict and says whether a start must
be refused: while the latest verdict is no-go (or unreadable), or a go older than
``max_age_s`` (``preflight_max_age_s``: the checks describe the vehicle as it was when they
ran; a battery, a camera or a parameter may have changed since), unless the gate is off
(``require_preflight_go: false``, the operator's override). Without any verdict (the
preflight not run since the supervisor started: the sim, a bench, a scripted run with its
own checks) a start is not refused; the node says so in its log. Times are the node's clock
(s).
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

    def __init__(self, required: bool, max_age_s: float = 0.0) -> None:
        """Keep no verdict yet; ``required``: refuse a start while the latest one is no-go.

        ``max_age_s`` > 0: a go older than this at the start refuses it too (0: never).
        """
        self.required = bool(required)
        self.max_age_s = float(max_age_s)
        self.verdict: Verdict | None = None

    def on_verdict(self, go: bool | None, summary: str, t: float) -> None:
        """Take a verdict (``go`` None: unreadable, ``summary`` why): it counts as no-go."""
        if go is None:
            go, summary = False, f'unreadable preflight verdict ({summary})'
        self.verdict = Verdict(bool(go), str(summary), float(t))

    def refusal(self, now: float | None = None) -> str | None:
        """Return why a start at ``now`` must be refused, or None to let it go on.

        ``now`` None: the verdict's age is not judged.
        """
        v = self.verdict
        if not self.required or v is None:
            return None
        if not v.go:
            return f'preflight no-go: {v.summary}; {OVERRIDE_HINT}'
        if self.max_age_s > 0.0 and now is not None and now - v.t > self.max_age_s:
            return (f'preflight go is {now - v.t:.0f} s old (preflight_max_age_s '
                    f'{self.max_age_s:g} s): {OVERRIDE_HINT}')
        return None

    def note(self) -> str | None:
        """Return what to log about a start that is not refused (None: a go, nothing to say)."""
        v = self.verdict
        if v is None:
            return 'no preflight verdict received (ibvs/preflight): started without one'
        if not v.go:
            return f'preflight no-go overridden (require_preflight_go: false): {v.summary}'
        return None
