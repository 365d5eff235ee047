"""Run a command that is sent SIGTERM when the process that started it dies.

``python -m ibvs_bringup.parent_death PARENT_PID -- COMMAND [ARG ...]`` sets Linux's parent
death signal (``prctl(PR_SET_PDEATHSIG, SIGTERM)``), checks that its parent is still
``PARENT_PID`` (it may have died before the call), then execs ``COMMAND``: the same process,
which keeps the signal across the exec.

Why: ``ProcessRunner`` starts each node in a process group of its own, so that a Ctrl-C in a
terminal reaches the runner only and the runner stops the nodes in order. If the runner itself is
killed (SIGKILL, the OOM killer), it cannot stop them: without this, the nodes would run on
without their supervisor (no respawn, no stop), and a runner started again would start a second
graph beside the first. Under systemd the unit's control group is killed either way
(``KillMode=control-group``, the default); this gives a runner in a terminal or a container the
same rule: the graph ends with its runner, the bridge falls silent, and the autopilot's own
offboard-loss failsafe takes the vehicle (docs/mavlink.md).

Linux sends the signal when the *thread* that forked the child ends, not the process: start
children from a thread that lives as long as the runner (the runner's and run_scenario's main
thread). Elsewhere than Linux, :func:`wrap` returns the command unchanged. The launch files
give their nodes the same rule (:func:`launch_prefix`).
"""
from __future__ import annotations

import ctypes
import os
import shlex
import signal
import sys

PR_SET_PDEATHSIG = 1          # <linux/prctl.h>
EXIT_PARENT_GONE = 143        # as a process ended by SIGTERM: 128 + 15


def supported() -> bool:
    """Return whether the parent death signal exists here (Linux)."""
    return sys.platform.startswith('linux')


def wrap(argv: list, parent_pid: int | None = None) -> list:
    """Return ``argv`` run through this module, to end with ``parent_pid`` (default: us)."""
    if not supported():
        return list(argv)
    pid = os.getpid() if parent_pid is None else parent_pid
    return [sys.executable, '-m', 'ibvs_bringup.parent_death', str(pid), '--', *argv]


def launch_prefix() -> str | None:
    """Return a launch_ros ``Node(prefix=...)`` that ends the node with this (launch) process.

    ``ros2 launch`` starts its nodes from its main thread (asyncio), which lives as long as it
    does. None elsewhere than Linux.
    """
    words = wrap([])
    return ' '.join(shlex.quote(w) for w in words) if words else None


def set_parent_death_signal(sig: int = signal.SIGTERM) -> None:
    """Ask the kernel to send ``sig`` to this process when its parent (thread) ends."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f'prctl(PR_SET_PDEATHSIG): {os.strerror(err)}')


def main(argv: list | None = None) -> int:
    """Set the signal, check the parent, exec the command; return only on an error."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 3 or args[1] != '--' or not args[0].isdigit():
        print('usage: python -m ibvs_bringup.parent_death PARENT_PID -- COMMAND [ARG ...]',
              file=sys.stderr)
        return 2
    parent, command = int(args[0]), args[2:]
    set_parent_death_signal()
    if os.getppid() != parent:         # the parent died before prctl: nobody will signal us
        print(f'parent_death: parent {parent} is gone, {command[0]} not started',
              file=sys.stderr)
        return EXIT_PARENT_GONE
    try:
        os.execvp(command[0], command)
    except OSError as exc:
        print(f'parent_death: cannot run {command[0]}: {exc}', file=sys.stderr)
        return 127


if __name__ == '__main__':
    sys.exit(main())
