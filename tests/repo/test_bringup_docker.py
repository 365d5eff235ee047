"""docker/: everything the Dockerfile and compose.yaml reference exists, parsed (no engine here).

There is no Docker engine on the machines that run this: the image is not built and no
container starts here. What is checked is what the files say: the commands, users, groups,
folders, devices and restart policies they name exist or agree with each other.
"""
from pathlib import Path
import re
import shlex
import xml.etree.ElementTree as ET

import pytest
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


# the example camera driver: the one executable that is not the project's, and its apt package
EXTERNAL = {('v4l2_camera', 'v4l2_camera_node'): 'ros-jazzy-v4l2-camera'}


def _check_command(cmd: list) -> None:
    if cmd[:2] == ['sh', '-c']:             # a shell that execs one of the commands below
        script = shlex.split(cmd[2])
        assert script[0] == 'exec', cmd
        _check_command(script[1:])
    elif cmd[:2] == ['ros2', 'launch']:
        assert cmd[2] in PACKAGES and cmd[3] in _launch_files(cmd[2]), cmd
    elif cmd[:2] == ['ros2', 'run'] and tuple(cmd[2:4]) in EXTERNAL:
        assert EXTERNAL[tuple(cmd[2:4])] in ' '.join(a for op, a in _instructions()
                                                     if op in ('RUN', 'ARG')), cmd
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


VEHICLE_SERVICES = {'onboard', 'onboard-serial', 'camera-front', 'camera-down', 'recorder'}


def _compose() -> dict:
    return yaml.safe_load((DOCKER / 'compose.yaml').read_text())


def _default(text: str) -> str:
    """A compose value with every ${NAME:-default} replaced by its default."""
    return re.sub(r'\$\{\w+:-([^}]*)\}', r'\1', text)


def _made_dirs() -> set:
    """The folders the Dockerfile makes for its user (install -d -o USER ...)."""
    run = ' '.join(a for op, a in _instructions() if op == 'RUN')
    made = re.search(r'install -d -o (\w+) -g \1 ((?:/\S+ ?)+)', run)
    assert made, 'the Dockerfile makes no folders for its user'
    return set(made.group(2).split())


def test_every_service_runs_as_the_non_root_user_the_dockerfile_makes():
    ins = _instructions()
    run = ' '.join(a for op, a in ins if op == 'RUN')
    useradd = re.search(r'useradd (.*?)(?:\s&&|$)', run).group(1).split()
    user = useradd[-1]
    assert user == 'pilot'
    groups = set(useradd[useradd.index('--groups') + 1].split(','))
    assert {'dialout', 'video'} <= groups
    assert '--uid' in useradd and useradd[useradd.index('--uid') + 1] == '"${PILOT_UID}"'
    assert ['ARG', 'PILOT_UID=1000'] in ins
    # the image's last user is pilot: nothing of the image runs as root
    assert [a for op, a in ins if op == 'USER'][-1] == user
    assert ins.index(['USER', user]) > max(i for i, (op, _) in enumerate(ins) if op == 'RUN')
    for name, service in _compose()['services'].items():
        assert service['user'] == user, name
        assert set(service.get('group_add', [])) <= groups, name
        assert 'PILOT_UID' in service['build']['args'], name


def test_vehicle_services_restart_and_the_others_do_not():
    for name, service in _compose()['services'].items():
        if name in VEHICLE_SERVICES:
            assert service['restart'] == 'unless-stopped', name
        else:
            assert 'restart' not in service, name


RUN_OUTPUT_DIRS = {'../results'}
GITIGNORED = (DOCKER.parent / '.gitignore').read_text().split()


def test_volumes_mount_folders_that_exist_on_both_sides():
    made = _made_dirs()
    for name, service in _compose()['services'].items():
        mounts = {}
        for volume in service['volumes']:
            host, container = _default(volume).split(':')[:2]
            mounts[container] = host
            if host in RUN_OUTPUT_DIRS:
                # a run's outputs (not in git: a fresh clone has no such folder; docker makes a
                # missing bind-mount folder, run_scenario makes it too)
                assert (DOCKER / host).resolve().name + '/' in GITIGNORED, (name, volume)
            elif host.startswith('.'):             # relative to docker/: in the repository
                assert (DOCKER / host).resolve().is_dir(), (name, volume)
            else:
                assert host.startswith('/'), (name, volume)
            # what the container writes to is made by the Dockerfile for its user; a
            # read-only mount needs no owner
            assert volume.endswith(':ro') or container in made, (name, container, made)
        # ROS logs go to a mounted folder
        log_dir = service['environment']['ROS_LOG_DIR']
        assert log_dir in mounts and log_dir in made, name
    run_scenario = _compose()['services']['scenario']
    assert _default(run_scenario['volumes'][-1]) == '../results:/results-root/results'
    # the recorder's bags land in the bag volume
    recorder = _compose()['services']['recorder']
    bag_dirs = [v.split(':')[-1] for v in recorder['volumes'] if 'BAG' in v]
    assert bag_dirs == ['/var/log/ibvs/bags']
    assert 'bag_path:=/var/log/ibvs/bags/$$(date' in recorder['command'][2]


def test_camera_services_get_their_device_and_the_video_group():
    services = _compose()['services']
    for name, topic in (('camera-front', '/front_camera'), ('camera-down', '/down_camera')):
        service = services[name]
        (device,) = service['devices']
        host, container = _default(device).split(':')
        assert host.startswith('/dev/video') and container == '/dev/video0', device
        cmd = service['command']
        assert f'video_device:={container}' in cmd and f'__ns:={topic}' in cmd, cmd
        assert service['group_add'] == ['video']
        # the project's Fast DDS profile, where colcon installs it in the image (WORKDIR /ws)
        profile = service['environment']['FASTRTPS_DEFAULT_PROFILES_FILE']
        assert ['WORKDIR', '/ws'] in _instructions()
        assert profile == '/ws/install/ibvs_bringup/share/ibvs_bringup/config/fastdds.xml'
        assert (SRC / 'ibvs_bringup' / 'config' / 'fastdds.xml').is_file()
        assert "glob('config/*.xml')" in (SRC / 'ibvs_bringup' / 'setup.py').read_text()
    # the host's two cameras are distinct devices by default
    assert _default(services['camera-front']['devices'][0]).split(':')[0] != \
        _default(services['camera-down']['devices'][0]).split(':')[0]


def _install_lines(path: Path, heading: str) -> list:
    """The command lines of the first code block after ``heading`` (comments dropped)."""
    doc = path.read_text()
    block = doc[doc.index(heading):]
    block = block[block.index('```') + 3:]
    block = block[:block.index('```')].replace('\\\n', ' ')
    return [ln.split('#')[0].strip() for ln in block.splitlines() if ln.strip()]


@pytest.mark.parametrize('path, heading, init', [
    ('docs/onboard.md', '## 1. Install', True),
    ('README.md', '## On a ROS 2 Jazzy install', False)])
def test_the_documented_native_install_matches_the_dockerfile_and_the_pins(path, heading, init):
    """docs/onboard.md section 1 and the README's Jazzy block (native Ubuntu 24.04): rosdep
    initialised and updated (onboard.md), the same keys skipped as the Dockerfile, each
    skipped key's package pip-installed with PIP_BREAK_SYSTEM_PACKAGES at requirements.txt's
    pin (issue 49 item 5)."""
    lines = _install_lines(ROOT / path, heading)
    if init:
        assert any(ln.startswith('sudo rosdep init') for ln in lines)
        assert 'rosdep update' in lines
    install = [ln for ln in lines if 'rosdep install' in ln]
    assert len(install) == 1 and '--from-paths src' in install[0]
    doc_skipped = set(re.search(r'--skip-keys "([^"]+)"', install[0]).group(1).split())
    run = ' '.join(a for op, a in _instructions() if op == 'RUN')
    docker_skipped = set(re.search(r'--skip-keys "([^"]+)"', run).group(1).split())
    assert doc_skipped == docker_skipped
    pins = dict(ln.split('==') for ln in (ROOT / 'requirements.txt').read_text().splitlines()
                if '==' in ln and not ln.startswith('#'))
    pip = [ln for ln in lines if 'pip3 install' in ln]
    assert len(pip) == 1 and pip[0].startswith('PIP_BREAK_SYSTEM_PACKAGES=1 ')
    for key in doc_skipped:
        name = key[len('python3-'):-len('-pip')] if key.endswith('-pip') \
            else key[len('python3-'):]
        assert f'{name}=={pins[name]}' in pip[0].split(), (key, pip[0])
