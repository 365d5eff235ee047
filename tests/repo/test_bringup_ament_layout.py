"""scripts/ament_layout.py: the install layout the ros2 CLI reads (colcon --symlink-install)."""
import os
from pathlib import Path

import pytest

from ibvs_bringup import ros2run
from script_module import load_script

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ('ibvs_common', 'ibvs_control', 'ibvs_perception', 'ibvs_sim', 'ibvs_bringup')


def load_ament_layout():
    return load_script(ROOT / 'scripts' / 'ament_layout.py', 'ament_layout')


@pytest.fixture()
def prefix(tmp_path):
    """A venv-like prefix: bin/<exe> for every console script, share/ in the OLD layout."""
    layout = load_ament_layout()
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    for package in PACKAGES:
        for exe in layout.console_scripts(package):
            script = bin_dir / exe
            script.write_text('#!/bin/sh\nexit 0\n')
            script.chmod(0o755)
    old = tmp_path / 'share' / 'ibvs_bringup'
    old.mkdir(parents=True)
    (old / 'launch').symlink_to(ROOT / 'ros2_ws/src/ibvs_bringup/launch')   # a directory link
    return tmp_path


def walked_files(root: Path) -> set:
    """What ``ros2 launch`` can find: os.walk does not enter symlinked directories."""
    return {f for _, _, files in os.walk(root) for f in files}


def test_layout_as_the_ros2_cli_reads_it(prefix, monkeypatch):
    layout = load_ament_layout()
    assert layout.main(['--prefix', str(prefix)]
                       + [str(ROOT / 'ros2_ws/src' / p) for p in PACKAGES]) == 0
    index = prefix / 'share/ament_index/resource_index/packages'
    assert sorted(p.name for p in index.iterdir()) == sorted(PACKAGES)
    share = prefix / 'share/ibvs_bringup'
    assert not (share / 'launch').is_symlink() and (share / 'launch').is_dir()
    assert {'sim.launch.py', 'onboard.launch.py', 'params.yaml',
            'package.xml'} <= walked_files(share)
    params = share / 'config/params.yaml'
    assert params.is_symlink() and params.resolve() == \
        (ROOT / 'ros2_ws/src/ibvs_bringup/config/params.yaml').resolve()
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    for package in PACKAGES:
        for exe in layout.console_scripts(package):
            path = prefix / 'lib' / package / exe
            assert os.access(path, os.X_OK), path
            assert ros2run.resolve(package, exe).source == str(path)
    assert layout.console_scripts('ibvs_perception')        # the packages do have executables


def test_layout_is_idempotent_and_prunes_stale_links(prefix):
    layout = load_ament_layout()
    bringup = ROOT / 'ros2_ws/src/ibvs_bringup'
    first = layout.install_layout(prefix, bringup)
    stale = prefix / 'share/ibvs_bringup/config/removed.yaml'
    stale.symlink_to(bringup / 'config' / 'removed.yaml')          # its source is gone
    again = layout.install_layout(prefix, bringup)
    assert again == first and not stale.is_symlink()


def test_a_package_that_is_not_installed_is_a_clear_error(prefix, tmp_path, capsys):
    layout = load_ament_layout()
    fake = tmp_path / 'src' / 'not_installed_pkg'
    fake.mkdir(parents=True)
    (fake / 'package.xml').write_text('<package format="3"><name>not_installed_pkg</name>'
                                      '</package>')
    assert layout.main(['--prefix', str(prefix), str(fake)]) == 1
    assert 'not_installed_pkg is not installed' in capsys.readouterr().err
