"""docker/: everything the Dockerfile and compose.yaml reference exists in the repository."""
from pathlib import Path
import re
import shlex
import xml.etree.ElementTree as ET

import yaml

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / 'docker'
SRC = ROOT / 'ros2_ws' / 'src'
PACKAGES = tuple(sorted(p.parent.name for p in SRC.glob('*/package.xml')))
# Keys checked against ros/rosdistro rosdep/python.yaml (2026-08): present for Ubuntu ...
ROSDEP_PYTHON_KEYS = {'python3-numpy', 'python3-opencv', 'python3-yaml', 'python3-matplotlib',
                      'python3-pytest', 'python3-pymavlink-pip', 'python3-rosbags-pip',
                      'python3-serial'}
# ... and absent (the Dockerfile must skip them and install the dependency itself).
NOT_ROSDEP_KEYS = {'python3-pymavlink': 'pymavlink', 'python3-rosbags': 'rosbags'}


def _instructions() -> list:
    text = (DOCKER / 'Dockerfile').read_text().replace('\\\n', ' ')
    return [line.strip().split(None, 1) for line in text.splitlines()
            if line.strip() and not line.strip().startswith('#')]


def _depends(package: str) -> set:
    root = ET.parse(SRC / package / 'package.xml').getroot()
    return {e.text.strip() for e in root if e.tag.endswith('depend')}


def test_dockerfile_base_copies_and_entrypoint_exist():
    ins = _instructions()
    assert ins[0] == ['FROM', 'ros:jazzy-ros-base']
    for op, arg in ins:
        if op == 'COPY':
            src = shlex.split(arg)[0]
            assert (ROOT / src).exists(), src
    entry = [a for op, a in ins if op == 'ENTRYPOINT'][0]
    assert '/entrypoint.sh' in entry
    script = (DOCKER / 'entrypoint.sh').read_text()
    assert 'source /opt/ros/jazzy/setup.bash' in script and '/ws/install/setup.bash' in script
    run = ' '.join(a for op, a in ins if op == 'RUN')
    assert 'rosdep install --from-paths src' in run and 'colcon build' in run


def test_dockerfile_copies_every_package_xml_before_rosdep():
    copied = {shlex.split(arg)[0] for op, arg in _instructions() if op == 'COPY'}
    assert len(PACKAGES) >= 6, PACKAGES
    for package in PACKAGES:
        assert f'ros2_ws/src/{package}/package.xml' in copied, package


def test_dockerfile_skips_and_installs_every_key_rosdep_lacks():
    run = ' '.join(a for op, a in _instructions() if op == 'RUN')
    skipped = set(re.search(r'--skip-keys "([^"]+)"', run).group(1).split())
    for package in PACKAGES:
        for key in _depends(package):
            if key.startswith('python3-'):
                assert key in ROSDEP_PYTHON_KEYS or key in skipped, (package, key)
            if key in NOT_ROSDEP_KEYS:
                assert key in skipped and NOT_ROSDEP_KEYS[key] in run, (package, key)
    for key in skipped:
        pip_name = {'python3-opencv': 'opencv-python-headless'}.get(key, key[len('python3-'):])
        assert pip_name in run, f'{key} skipped but {pip_name} not installed'


def test_dockerfile_uses_the_systems_opencv():
    """rosdep's python3-opencv (OpenCV 4.6 on Ubuntu 24.04) is what the image runs on.

    The code supports it through ibvs_common/core/cv_compat.py; `make unit-cv46` tests it.
    """
    run = ' '.join(a for op, a in _instructions() if op == 'RUN')
    skipped = set(re.search(r'--skip-keys "([^"]+)"', run).group(1).split())
    assert 'python3-opencv' not in skipped and 'opencv' not in run.replace('--skip-keys', '')


def _launch_files(package: str) -> set:
    return {p.name for p in (SRC / package / 'launch').glob('*.launch.py')}


def _console_scripts(package: str) -> set:
    return set(re.findall(r"'(\w+)\s*=", (SRC / package / 'setup.py').read_text()))


def _check_command(cmd: list) -> None:
    if cmd[:2] == ['ros2', 'launch']:
        assert cmd[2] in PACKAGES and cmd[3] in _launch_files(cmd[2]), cmd
    elif cmd[:2] == ['ros2', 'run']:
        assert cmd[3] in _console_scripts(cmd[2]), cmd
    elif cmd[:2] == ['python3', '-m']:
        module = cmd[2].split('.')
        assert (SRC / module[0] / Path(*module).with_suffix('.py')).exists(), cmd
    else:
        raise AssertionError(f'unexpected command {cmd}')


def test_default_command_and_compose_services_reference_what_exists():
    cmd = [a for op, a in _instructions() if op == 'CMD'][0]
    _check_command(yaml.safe_load(cmd))
    compose = yaml.safe_load((DOCKER / 'compose.yaml').read_text())
    assert {'sim', 'onboard'} <= set(compose['services'])
    for name, service in compose['services'].items():
        build = service['build']
        assert (DOCKER / build['context'] / build['dockerfile']).resolve() == \
            (DOCKER / 'Dockerfile').resolve(), name
        _check_command([re.sub(r'\$\{(\w+):-[^}]*\}', 'x', c) for c in service['command']])
    onboard = ' '.join(compose['services']['onboard']['command'])
    assert 'mavlink_url:=' in onboard
    # the onboard service's default link is the launch file's (PX4's companion port, udpin:
    # a udpout URL to PX4 never links, issue 13)
    launch = (SRC / 'ibvs_bringup' / 'launch' / 'onboard.launch.py').read_text()
    default = re.search(r"DEFAULT_MAVLINK_URL = '([^']+)'", launch).group(1)
    assert re.search(r'\$\{MAVLINK_URL:-([^}]*)\}', onboard).group(1) == default


def test_launch_arguments_used_by_compose_are_declared():
    compose = yaml.safe_load((DOCKER / 'compose.yaml').read_text())
    for service in compose['services'].values():
        cmd = service['command']
        if cmd[:2] == ['ros2', 'launch']:
            text = (SRC / cmd[2] / 'launch' / cmd[3]).read_text()
            for arg in cmd[4:]:
                name = arg.split(':=')[0]
                assert f"DeclareLaunchArgument('{name}'" in text, (cmd[3], name)


def test_compose_maps_the_serial_autopilot_device_for_the_serial_service():
    """The onboard graph on a serial autopilot link gets the device and the dialout group."""
    compose = yaml.safe_load((DOCKER / 'compose.yaml').read_text())
    service = compose['services']['onboard-serial']
    assert any('/dev/tty' in d for d in service['devices']), service
    assert 'dialout' in service['group_add'], service
    command = ' '.join(service['command'])
    assert 'mavlink_url:=' in command and 'MAVLINK_DEVICE' in command, command
    assert service['restart'] == 'unless-stopped'
