"""The packages' layering, checked on the source: who may import whom.

ibvs_common is the base: frames, camera model, feature geometry, attitude buffer, config
loading, the MAVLink connection, node helpers. Perception, control and the sim depend on it
and not on each other; bringup (launch, node list, runner) starts them; only the experiment
harness (ibvs_harness: scenario runs, campaigns, the feature-level loop) sees everything.
Every ibvs_* package a package imports is an exec_depend of its package.xml, so rosdep and
colcon order the build as Python does.
"""
import ast
from pathlib import Path
import xml.etree.ElementTree as ET

import pytest

SRC = Path(__file__).resolve().parents[2] / 'ros2_ws' / 'src'
OURS = ('ibvs_common', 'ibvs_control', 'ibvs_perception', 'ibvs_sim', 'ibvs_bringup',
        'ibvs_harness')
ALLOWED = {
    'ibvs_common': set(),
    'ibvs_control': {'ibvs_common'},
    'ibvs_perception': {'ibvs_common'},
    'ibvs_sim': {'ibvs_common'},
    'ibvs_bringup': {'ibvs_common', 'ibvs_control', 'ibvs_perception', 'ibvs_sim'},
    'ibvs_harness': {'ibvs_common', 'ibvs_control', 'ibvs_perception', 'ibvs_sim',
                     'ibvs_bringup'},
}


def imported_packages(package: str, folder: str | None = None) -> dict[str, list[str]]:
    """Map each other ibvs_* package that ``package``'s modules import to the importers.

    ``folder``: the package's subfolder to read (default: its Python package; 'test': its
    tests).
    """
    found: dict[str, list[str]] = {}
    for path in sorted((SRC / package / (folder or package)).rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top in OURS and top != package:
                    found.setdefault(top, []).append(str(path.relative_to(SRC)))
    return found


def exec_depends(package: str, tags: tuple = ('exec_depend',)) -> set[str]:
    root = ET.parse(SRC / package / 'package.xml').getroot()
    return {e.text.strip() for tag in tags for e in root.findall(tag)}


def test_the_checker_sees_a_known_import():
    # the controller node imports the shared attitude buffer: the walk must find it
    assert 'ibvs_control/ibvs_control/force_controller_node.py' in \
        imported_packages('ibvs_control')['ibvs_common']


@pytest.mark.parametrize('package', OURS)
def test_a_package_imports_only_the_layers_below_it(package):
    wrong = {k: v for k, v in imported_packages(package).items() if k not in ALLOWED[package]}
    assert not wrong, f'{package} must not import {sorted(wrong)}: {wrong}'


@pytest.mark.parametrize('package', OURS)
def test_every_imported_package_is_an_exec_depend(package):
    missing = set(imported_packages(package)) - exec_depends(package)
    assert not missing, f'{package}/package.xml lacks exec_depend {sorted(missing)}'


@pytest.mark.parametrize('package', OURS)
def test_every_package_a_test_imports_is_an_exec_or_test_depend(package):
    # colcon test runs each package's test/ with only its declared dependencies installed
    deps = exec_depends(package, ('exec_depend', 'test_depend'))
    missing = set(imported_packages(package, 'test')) - deps
    assert not missing, f'{package}/package.xml lacks test_depend {sorted(missing)}'


def test_the_dependencies_with_the_tests_ones_have_no_cycle():
    # colcon orders packages on every dependency kind: a test_depend on a package above
    # would make a cycle it cannot build
    graph = {p: exec_depends(p, ('exec_depend', 'test_depend')) & set(OURS) for p in OURS}
    done, path = set(), []

    def visit(p):
        assert p not in path, f'dependency cycle: {" -> ".join(path + [p])}'
        if p in done:
            return
        path.append(p)
        for q in sorted(graph[p]):
            visit(q)
        path.pop()
        done.add(p)
    for p in OURS:
        visit(p)


def test_only_the_sim_side_reads_the_world_file():
    # world.yaml is the sim's scenario: the onboard packages get the window size and pad
    # layout as their own configuration
    for package in ('ibvs_common', 'ibvs_control', 'ibvs_perception'):
        for path in (SRC / package / package).rglob('*.py'):
            text = path.read_text(encoding='utf-8')
            assert 'load_world' not in text and "'world.yaml'" not in text, path
