"""``ros2 run <package> <executable> [args]`` where the ros2 CLI is absent.

Resolution order, as ``ros2 run`` plus a fallback for pip/venv installs:
1. ``<prefix>/lib/<package>/<executable>`` for each prefix of ``AMENT_PREFIX_PATH`` (colcon);
2. the console-script entry point ``<executable>`` of the installed distribution ``<package>``
   (``importlib.metadata``), run as ``python -c 'from module import func; ...'``.
``scripts/ros2run`` and ``ibvs_bringup.runner`` both use ``command_for``.
"""
from __future__ import annotations

from dataclasses import dataclass
import importlib.metadata as md
import importlib.util
import os
import sys


class ResolveError(LookupError):
    """No executable of that name in that package."""


@dataclass(frozen=True)
class Resolved:
    """How to start one executable: an argv prefix and where it was found."""

    argv: tuple
    source: str                 # file path, or 'entry point module:func'
    module: str | None = None   # entry-point module (None for a file)


def _normalise(name: str) -> str:
    return name.replace('-', '_').lower()


def _prefix_executable(package: str, executable: str) -> str | None:
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        path = os.path.join(prefix, 'lib', package, executable)
        if os.path.isfile(path) and os.access(path, os.X_OK):
            return path
    return None


def _entry_point(package: str, executable: str) -> md.EntryPoint | None:
    for dist in md.distributions():
        if _normalise(dist.metadata.get('Name', '') or '') != _normalise(package):
            continue
        for ep in dist.entry_points:
            if ep.group == 'console_scripts' and ep.name == executable:
                return ep
    return None


def resolve(package: str, executable: str) -> Resolved:
    """Return how to start ``executable`` of ``package``; raise ResolveError if unknown."""
    path = _prefix_executable(package, executable)
    if path:
        return Resolved((path,), path)
    ep = _entry_point(package, executable)
    if ep is None:
        raise ResolveError(f'no executable {executable!r} in package {package!r} (neither '
                           f'lib/{package}/{executable} under AMENT_PREFIX_PATH nor a console '
                           f'script of an installed distribution {package!r})')
    module, _, attr = ep.value.partition(':')
    attr = attr.strip() or 'main'
    code = (f'import sys; sys.argv[0] = {executable!r}; from {module.strip()} import '
            f'{attr.split(".")[0]} as _m; sys.exit(_m())')
    return Resolved((sys.executable, '-c', code), f'entry point {ep.value}', module.strip())


def command_for(package: str, executable: str, args: list | tuple = ()) -> list[str]:
    """Return the argv that runs ``executable`` of ``package`` with ``args``."""
    return list(resolve(package, executable).argv) + list(args)


def unavailable_reason(package: str, executable: str) -> str | None:
    """Return why ``executable`` cannot run here (not installed, module missing), or None."""
    try:
        res = resolve(package, executable)
    except ResolveError as exc:
        return str(exc)
    if res.module is not None:
        try:
            found = importlib.util.find_spec(res.module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            return f'{package}/{executable}: module {res.module} is not written yet'
    return None


def main(argv: list | None = None) -> int:
    """Exec ``<package> <executable> [args...]`` in place (signals reach the node directly)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 2 or argv[0] in ('-h', '--help'):
        print('usage: ros2run <package> <executable> [--ros-args ...]', file=sys.stderr)
        return 2
    try:
        cmd = command_for(argv[0], argv[1], argv[2:])
    except ResolveError as exc:
        print(f'ros2run: {exc}', file=sys.stderr)
        return 1
    sys.stdout.flush()
    os.execv(cmd[0], cmd)
    return 1  # not reached


if __name__ == '__main__':
    sys.exit(main())
