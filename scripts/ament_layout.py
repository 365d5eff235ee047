#!/usr/bin/env python3
"""Give a venv the install layout ``colcon build --symlink-install`` makes, for the ros2 CLI.

``make install`` pip-installs the packages (editable) into the venv; this script then adds
what the ros2 CLI and launch look for under a prefix of ``AMENT_PREFIX_PATH``:

- ``share/ament_index/resource_index/packages/<pkg>``: the package marker (``ros2 pkg``);
- ``share/<pkg>/package.xml`` and every file under the package's ``config/`` and ``launch/``
  as a per-file symlink into the source tree, in real directories
  (``ros2 launch`` searches ``share/<pkg>`` with ``os.walk``, which does not enter a
  symlinked directory: the launch files were not found when ``launch`` was one);
- ``lib/<pkg>/<executable>`` for each console script of the package: a symlink to the
  venv's ``bin/<executable>`` (``ros2 run`` runs ``lib/<pkg>/<executable>``; the project's
  runner, ``ibvs_bringup.ros2run``, looks there first too).

Stale entries (a symlinked directory of the old layout, a symlink to a file that no longer
exists) are removed. Run with the venv's python after the pip install:
``.venv/bin/python scripts/ament_layout.py --prefix .venv ros2_ws/src/<pkg> ...``.
"""
from __future__ import annotations

import argparse
import importlib.metadata as md
import os
from pathlib import Path
import sys
import xml.etree.ElementTree as ET

DATA_DIRS = ('config', 'launch')


def package_name(package_dir: Path) -> str:
    """Return the <name> of the package.xml in ``package_dir``."""
    name = ET.parse(package_dir / 'package.xml').getroot().findtext('name')
    if not name:
        raise ValueError(f'{package_dir / "package.xml"} has no <name>')
    return name.strip()


def console_scripts(package: str) -> list[str]:
    """Return the console-script names of the installed distribution ``package``."""
    try:
        dist = md.distribution(package)
    except md.PackageNotFoundError as exc:
        raise ValueError(f'{package} is not installed in this python ({sys.executable}): '
                         f'pip-install it first') from exc
    return sorted(ep.name for ep in dist.entry_points if ep.group == 'console_scripts')


def _link(target: Path, link: Path) -> None:
    """Make ``link`` a symlink to ``target`` (replacing a file, link or old directory link)."""
    if link.is_symlink() or link.is_file():
        if link.is_symlink() and Path(os.readlink(link)) == target:
            return
        link.unlink()
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(target)


def _real_dir(path: Path) -> None:
    """Make ``path`` a real directory (an old layout had it as a symlinked directory)."""
    if path.is_symlink():
        path.unlink()
    path.mkdir(parents=True, exist_ok=True)


def _prune(root: Path) -> None:
    """Remove symlinks under ``root`` whose target no longer exists, then empty directories."""
    for dirpath, dirnames, filenames in os.walk(root, topdown=False):
        for name in filenames + dirnames:
            p = Path(dirpath) / name
            if p.is_symlink() and not p.exists():
                p.unlink()
        if Path(dirpath) != root and not any(Path(dirpath).iterdir()):
            Path(dirpath).rmdir()


def install_layout(prefix: Path, package_dir: Path) -> list[Path]:
    """Lay out one package under ``prefix``; return the links made or kept."""
    prefix, package_dir = prefix.absolute(), package_dir.absolute()
    name = package_name(package_dir)
    marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / name
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    share = prefix / 'share' / name
    _real_dir(share)
    links = []
    _link(package_dir / 'package.xml', share / 'package.xml')
    links.append(share / 'package.xml')
    for data in DATA_DIRS:
        source = package_dir / data
        if not source.is_dir():
            continue
        _real_dir(share / data)
        for path in sorted(source.rglob('*')):
            if path.is_file() and '__pycache__' not in path.parts:
                link = share / data / path.relative_to(source)
                _real_dir(link.parent)
                _link(path, link)
                links.append(link)
        _prune(share / data)
    lib = prefix / 'lib' / name
    _real_dir(lib)
    for exe in console_scripts(name):
        script = prefix / 'bin' / exe
        if not script.is_file():
            raise ValueError(f'console script {script} of {name} is missing')
        _link(script, lib / exe)
        links.append(lib / exe)
    _prune(lib)
    return links


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--prefix', type=Path, required=True, help='the venv (install prefix)')
    parser.add_argument('packages', type=Path, nargs='+', help='package source directories')
    args = parser.parse_args(argv)
    try:
        for package_dir in args.packages:
            links = install_layout(args.prefix, package_dir)
            print(f'{package_name(package_dir)}: {len(links)} files linked under {args.prefix}')
    except (OSError, ValueError) as exc:
        print(f'ament_layout: {exc}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
