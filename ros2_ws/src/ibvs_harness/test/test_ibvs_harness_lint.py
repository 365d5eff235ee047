"""Lint of this package as ament does it and `colcon test` runs it: flake8, pep257.

The same settings as the project's `make lint` (flake8 at 99 columns; pydocstyle, pep257
convention, D100-D107 not required), on this package's directory only. flake8 and
pydocstyle come with the package.xml test dependencies ament_flake8 and ament_pep257.
"""
from pathlib import Path
import subprocess
import sys

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1]
PEP257_IGNORE = 'D100,D101,D102,D103,D104,D105,D107'


def run_tool(module: str, *args: str) -> subprocess.CompletedProcess:
    pytest.importorskip(module, reason=f'{module} is not installed (test_depend ament_*)')
    return subprocess.run([sys.executable, '-m', module, *args, str(PACKAGE_DIR)],
                          capture_output=True, text=True, timeout=300)


def test_flake8():
    result = run_tool('flake8', '--max-line-length', '99')
    assert result.returncode == 0, result.stdout + result.stderr


def test_pep257():
    result = run_tool('pydocstyle', '--convention=pep257', f'--add-ignore={PEP257_IGNORE}')
    assert result.returncode == 0, result.stdout + result.stderr
