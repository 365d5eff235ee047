"""ibvs_bringup/systemd/: the units parse, and everything they name exists.

A parser test that always runs: sections and keys, the executables of ExecStart (the
project's wrapper, then a console script of the package's setup.py or the one external
driver), the units named by the dependencies (ours, standard targets, or device units our
udev rules make), one non-root user throughout, the log directory, the environment file
defines every variable the units use. Then ``systemd-analyze verify`` on the units where it
is installed (the units' install root rewritten to this checkout), and the wrapper run for
real. What no test here does: start the units under a running systemd (this machine's PID 1
is not systemd), open real cameras or a serial autopilot.
"""
from __future__ import annotations

import ast
import dataclasses
import os
from pathlib import Path
import re
import shlex
import shutil
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / 'ros2_ws' / 'src'
SYSTEMD = SRC / 'ibvs_bringup' / 'systemd'
INSTALL_ROOT = '/home/pilot/ibvs'            # where the units expect the repository
WRAPPER = f'{INSTALL_ROOT}/ros2_ws/src/ibvs_bringup/systemd/ibvs-run'
USER, LOG_DIR, ENV_FILE = 'pilot', '/var/log/ibvs', '/etc/ibvs/ibvs.env'
UNITS = sorted(SYSTEMD.glob('*.service'))
# targets and services of systemd itself that our units may name
STANDARD_UNITS = {'network-online.target', 'network.target', 'multi-user.target',
                  'time-sync.target', 'sysinit.target', 'basic.target', 'local-fs.target'}
# the example camera driver is the one executable that is not the project's: its apt package
EXTERNAL = {('v4l2_camera', 'v4l2_camera_node'): 'ros-jazzy-v4l2-camera'}
DEPENDENCY_KEYS = ('Wants', 'Requires', 'Requisite', 'BindsTo', 'PartOf', 'After', 'Before',
                   'WantedBy', 'RequiredBy', 'Conflicts')
# variables systemd itself sets, usable without the environment file
SYSTEMD_VARIABLES = {'MAINPID', 'INVOCATION_ID'}


def parse_unit(path: Path) -> dict[str, list[tuple[str, str]]]:
    """Sections of a unit file: (key, value) pairs in order (keys may repeat).

    systemd.syntax(7): comments start with # or ;, a line ending in a backslash goes on.
    """
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line[0] in '#;':
            continue
        while line.endswith('\\') and i < len(lines):
            line = line[:-1] + ' ' + lines[i].strip()
            i += 1
        if line.startswith('['):
            assert line.endswith(']'), (path, line)
            current = line[1:-1]
            assert current not in sections, (path, f'section [{current}] twice')
            sections[current] = []
            continue
        assert current is not None, (path, f'{line!r} before any section')
        key, sep, value = line.partition('=')
        assert sep, (path, f'not a key=value line: {line!r}')
        sections[current].append((key.strip(), value.strip()))
    return sections


def values(unit: dict, section: str, key: str) -> list[str]:
    return [v for k, v in unit.get(section, []) if k == key]


def value(unit: dict, section: str, key: str) -> str:
    found = values(unit, section, key)
    assert len(found) == 1, (section, key, found)
    return found[0]


def words(unit: dict, section: str, key: str) -> list[str]:
    return [w for v in values(unit, section, key) for w in v.split()]


def console_scripts(package: str) -> set[str]:
    return set(re.findall(r"'(\w+)\s*=\s*[\w.]+:\w+'", (SRC / package / 'setup.py').read_text()))


def command_of(exec_start: str) -> list[str]:
    """The argv the unit runs: the sh -c script's exec'd command, or ExecStart itself."""
    argv = shlex.split(exec_start)
    if argv[:2] == ['/bin/sh', '-c']:
        script = shlex.split(argv[2])
        assert script[0] == 'exec', f'the sh -c script must exec its command: {argv[2]!r}'
        argv = script[1:]
    return argv


def env_file() -> dict[str, str]:
    out = {}
    for line in (SYSTEMD / 'ibvs.env').read_text().splitlines():
        line = line.strip()
        if line and not line.startswith('#'):
            name, sep, val = line.partition('=')
            assert sep and re.fullmatch(r'[A-Z_][A-Z0-9_]*', name), line
            out[name] = val.strip('"')
    return out


def udev_devices() -> set[str]:
    """Device units made by 99-ibvs.rules: /dev/<SYMLINK> of the rules tagged for systemd."""
    units = set()
    for line in (SYSTEMD / '99-ibvs.rules').read_text().splitlines():
        if line.strip().startswith('#') or 'TAG+="systemd"' not in line:
            continue
        link = re.search(r'SYMLINK\+="([^"]+)"', line).group(1)
        units.add('dev-' + link.replace('-', '\\x2d').replace('/', '-') + '.device')
    return units


def our_unit_file(name: str) -> Path | None:
    """The unit file for ``name``: itself, or the template of an instance."""
    m = re.fullmatch(r'([\w-]+)@([\w-]*)\.(service|target)', name)
    base = f'{m.group(1)}@.{m.group(3)}' if m else name
    path = SYSTEMD / base
    return path if path.is_file() else None


def test_the_three_units_are_shipped_and_installed_with_the_package():
    assert {p.name for p in UNITS} == {'ibvs-graph.service', 'ibvs-camera@.service',
                                       'ibvs-recorder.service'}
    setup = (SRC / 'ibvs_bringup' / 'setup.py').read_text()
    assert "'/systemd', glob('systemd/*'))" in setup


@pytest.mark.parametrize('path', UNITS, ids=lambda p: p.name)
def test_unit_sections_and_required_keys(path):
    unit = parse_unit(path)
    assert {'Unit', 'Service'} <= set(unit), set(unit)
    assert value(unit, 'Unit', 'Description')
    assert value(unit, 'Service', 'Type') == 'exec'       # a failed exec fails the start
    assert value(unit, 'Service', 'Restart') == 'on-failure'
    assert float(value(unit, 'Service', 'RestartSec')) > 0
    assert float(value(unit, 'Service', 'RestartMaxDelaySec')) >= \
        float(value(unit, 'Service', 'RestartSec'))
    assert int(value(unit, 'Service', 'RestartSteps')) > 0
    assert value(unit, 'Unit', 'StartLimitIntervalSec') == '0'   # never gives up
    assert value(unit, 'Service', 'KillSignal') == 'SIGINT'      # rclpy's clean shutdown
    if '@' not in path.name:            # a template is pulled in by the graph
        assert values(unit, 'Install', 'WantedBy') == ['multi-user.target']


@pytest.mark.parametrize('path', UNITS, ids=lambda p: p.name)
def test_one_non_root_user_its_groups_log_dir_and_environment_file(path):
    unit = parse_unit(path)
    assert value(unit, 'Service', 'User') == USER
    assert value(unit, 'Service', 'Group') == USER
    assert value(unit, 'Service', 'EnvironmentFile') == ENV_FILE      # required, no '-'
    assert f'ROS_LOG_DIR={LOG_DIR}' in values(unit, 'Service', 'Environment')
    # LogsDirectory= is relative to /var/log, made and given to User= by systemd
    logs = words(unit, 'Service', 'LogsDirectory')
    assert LOG_DIR.removeprefix('/var/log/') in logs, logs
    groups = set(words(unit, 'Service', 'SupplementaryGroups'))
    if path.name == 'ibvs-graph.service':
        assert groups == {'dialout'}                  # a serial autopilot link
    elif path.name == 'ibvs-camera@.service':
        assert groups == {'video'}                    # /dev/video*
    else:
        assert groups == set()


@pytest.mark.parametrize('path', UNITS, ids=lambda p: p.name)
def test_exec_start_runs_an_executable_the_project_installs(path):
    unit = parse_unit(path)
    argv = command_of(value(unit, 'Service', 'ExecStart'))
    assert argv[0] == WRAPPER, argv
    wrapper = ROOT / Path(WRAPPER).relative_to(INSTALL_ROOT)
    assert wrapper.is_file() and os.access(wrapper, os.X_OK), wrapper
    package, executable = argv[1], argv[2]
    if (package, executable) in EXTERNAL:
        apt = EXTERNAL[(package, executable)]
        assert apt in path.read_text()                      # the unit says what to install
        assert apt in (ROOT / 'docker' / 'Dockerfile').read_text()
    else:
        assert (SRC / package / 'setup.py').is_file(), package
        assert executable in console_scripts(package), (package, executable)


def test_the_graph_unit_runs_the_onboard_runner_with_the_mavlink_url():
    unit = parse_unit(SYSTEMD / 'ibvs-graph.service')
    argv = command_of(value(unit, 'Service', 'ExecStart'))
    assert argv[1:4] == ['ibvs_bringup', 'runner', 'onboard']
    runner = (SRC / 'ibvs_bringup' / 'ibvs_bringup' / 'runner.py').read_text()
    options = [a for a in argv[4:] if a.startswith('--')]
    assert options == ['--mavlink-url']
    assert "add_argument('--mavlink-url'" in runner
    assert argv[argv.index('--mavlink-url') + 1] == '${IBVS_MAVLINK_URL}'
    # TimeoutStopSec covers the runner's own SIGINT, SIGTERM, SIGKILL stop of its nodes
    tree = ast.parse(runner)
    init = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)
                and n.name == '__init__' and any(a.arg == 'stop_timeouts'
                                                 for a in n.args.args))
    stop = ast.literal_eval(init.args.defaults[-1])
    assert float(value(unit, 'Service', 'TimeoutStopSec')) > sum(stop), stop


@pytest.mark.parametrize('url, rc', [('', 1), ('/dev/ibvs/autopilot,921600', 0)])
def test_the_graph_unit_refuses_to_start_without_a_mavlink_url(url, rc):
    # the runner would otherwise fly on the simulator's URL (graph.onboard_graph)
    unit = parse_unit(SYSTEMD / 'ibvs-graph.service')
    (pre,) = values(unit, 'Service', 'ExecStartPre')
    argv = shlex.split(pre.replace('$$', '$'))        # systemd's escape of the shell's $
    assert argv[:2] == ['/bin/sh', '-c']
    result = subprocess.run(argv, env={'IBVS_MAVLINK_URL': url}, capture_output=True,
                            text=True, timeout=10)
    assert result.returncode == rc, result.stderr
    assert ('IBVS_MAVLINK_URL is not set' in result.stderr) == (rc == 1)


def test_the_recorder_unit_writes_a_new_bag_under_the_log_dir_with_known_parameters():
    from ibvs_harness.recorder_node import RecorderNodeConfig
    unit = parse_unit(SYSTEMD / 'ibvs-recorder.service')
    argv = command_of(value(unit, 'Service', 'ExecStart'))
    assert argv[1:3] == ['ibvs_harness', 'recorder'] and argv[3] == '--ros-args'
    params = dict(a.split(':=', 1) for a in argv[4:] if ':=' in a)
    assert set(params) <= {f.name for f in dataclasses.fields(RecorderNodeConfig)}, params
    assert {'bag_path', 'image_every', 'max_image_mb'} <= set(params)
    # a fresh bag each start (the recorder refuses an existing bag_path): the UTC time, with
    # the unit file's escapes ($$ and %%) for the shell's $(date ...)
    assert f'bag_path:={LOG_DIR}/bags/$$(date -u +%%Y%%m%%dT%%H%%M%%SZ) ' in \
        value(unit, 'Service', 'ExecStart')
    assert 'ibvs/bags' in words(unit, 'Service', 'LogsDirectory')
    assert int(value(unit, 'Service', 'Nice')) > 0      # below the graph


def test_every_unit_named_by_a_dependency_exists():
    devices = udev_devices()
    assert devices == {'dev-ibvs-front.device', 'dev-ibvs-down.device'}
    for path in UNITS:
        unit = parse_unit(path)
        instance = 'front' if '@' in path.name else None
        for section in ('Unit', 'Install'):
            for key in DEPENDENCY_KEYS:
                for name in words(unit, section, key):
                    if '%i' in name:
                        assert instance, (path.name, name)
                        name = name.replace('%i', instance)
                    assert name in STANDARD_UNITS or our_unit_file(name) or name in devices, \
                        (path.name, key, name)


def test_the_graph_starts_after_network_and_both_cameras_which_bind_to_their_devices():
    graph = parse_unit(SYSTEMD / 'ibvs-graph.service')
    cameras = {'ibvs-camera@front.service', 'ibvs-camera@down.service'}
    assert cameras | {'network-online.target'} <= set(words(graph, 'Unit', 'Wants'))
    assert cameras | {'network-online.target'} <= set(words(graph, 'Unit', 'After'))
    assert not words(graph, 'Unit', 'BindsTo') and not words(graph, 'Unit', 'Requires')
    camera = parse_unit(SYSTEMD / 'ibvs-camera@.service')
    assert words(camera, 'Unit', 'BindsTo') == ['dev-ibvs-%i.device']
    assert 'dev-ibvs-%i.device' in words(camera, 'Unit', 'After')
    argv = command_of(value(camera, 'Service', 'ExecStart'))
    # the topics the graph subscribes: /<name>_camera/image_raw and camera_info
    assert '__ns:=/%i_camera' in argv and 'video_device:=/dev/ibvs/%i' in argv


def test_the_environment_file_defines_every_variable_the_units_use():
    env = env_file()
    assert env['IBVS_MAVLINK_URL'] and env['IBVS_SETUP'].split()[0] == \
        '/opt/ros/jazzy/setup.bash'
    for path in UNITS:
        for exec_start in values(parse_unit(path), 'Service', 'ExecStart'):
            used = set(re.findall(r'(?<!\$)\$\{?([A-Za-z_]\w*)', exec_start))
            assert used <= set(env) | SYSTEMD_VARIABLES, (path.name, used - set(env))


def test_the_units_install_root_is_the_documented_clone():
    onboard = (ROOT / 'docs' / 'onboard.md').read_text()
    assert 'git clone <this repository> ~/ibvs' in onboard
    for path in UNITS:
        for rel in re.findall(re.escape(INSTALL_ROOT) + r'/([^\s\'"]+)', path.read_text()):
            assert (ROOT / rel).exists(), (path.name, rel)


# --- systemd-analyze verify, where it is installed -------------------------------------------

def systemd_version() -> int | None:
    exe = shutil.which('systemd-analyze')
    if not exe:
        return None
    out = subprocess.run([exe, '--version'], capture_output=True, text=True).stdout
    return int(re.match(r'systemd (\d+)', out).group(1))


def test_systemd_analyze_verify(tmp_path):
    version = systemd_version()
    if version is None:
        pytest.skip('systemd-analyze is not installed here: only the parser tests ran')
    for path in UNITS:   # the install root rewritten to this checkout, so ExecStart exists
        (tmp_path / path.name).write_text(path.read_text().replace(INSTALL_ROOT, str(ROOT)))
    names = [str(tmp_path / n) for n in ('ibvs-graph.service', 'ibvs-recorder.service',
                                         'ibvs-camera@front.service')]
    (tmp_path / 'ibvs-camera@front.service').symlink_to(tmp_path / 'ibvs-camera@.service')
    result = subprocess.run(['systemd-analyze', 'verify', '--man=no', *names],
                            capture_output=True, text=True, timeout=60)
    lines = [ln for ln in (result.stdout + result.stderr).splitlines() if ln.strip()]
    # keys of systemd >= 254 that an older one ignores (the units say so)
    newer = ("Unknown key 'RestartSteps'", "Unknown key 'RestartMaxDelaySec'")
    problems = [ln for ln in lines if not (version < 254 and any(k in ln for k in newer))]
    assert result.returncode == 0 and not problems, '\n'.join(lines)


# --- the wrapper -------------------------------------------------------------------------------

def run_wrapper(args: list, env: dict) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items()
            if k not in ('IBVS_VENV', 'IBVS_SETUP', 'FASTRTPS_DEFAULT_PROFILES_FILE')}
    return subprocess.run([str(SYSTEMD / 'ibvs-run'), *args], env={**base, **env},
                          capture_output=True, text=True, timeout=120)


@pytest.fixture()
def fake_package(tmp_path):
    """A prefix with lib/fakepkg/show: prints its DDS profile variable and arguments."""
    lib = tmp_path / 'prefix' / 'lib' / 'fakepkg'
    lib.mkdir(parents=True)
    show = lib / 'show'
    show.write_text('#!/bin/sh\necho "profile=$FASTRTPS_DEFAULT_PROFILES_FILE args=$*"\n')
    show.chmod(0o755)
    return tmp_path / 'prefix'


def venv() -> Path:
    path = Path(sys.prefix)
    if not (path / 'share' / 'ibvs_bringup' / 'config' / 'fastdds.xml').exists():
        pytest.skip('the project venv (make install) is not this python')
    return path


def test_wrapper_runs_a_package_executable_from_the_venv_with_the_dds_profile(fake_package):
    prefix = venv()
    result = run_wrapper(['fakepkg', 'show', 'a', 'b c'],
                         {'IBVS_VENV': str(prefix), 'AMENT_PREFIX_PATH': str(fake_package)})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == \
        f'profile={prefix}/share/ibvs_bringup/config/fastdds.xml args=a b c'


def test_wrapper_sources_the_setup_files_in_order(tmp_path, fake_package):
    prefix = venv()
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    (bin_dir / 'python3').write_text(f'#!/bin/sh\nexec {prefix}/bin/python "$@"\n')
    (bin_dir / 'python3').chmod(0o755)
    first, second = tmp_path / 'ros.bash', tmp_path / 'ws.bash'
    first.write_text(f'export PATH="{bin_dir}:$PATH"\nexport AMENT_PREFIX_PATH={prefix}\n')
    second.write_text(f'export AMENT_PREFIX_PATH={fake_package}:$AMENT_PREFIX_PATH\n'
                      'echo "$UNSET_IN_ROS_SETUP" >/dev/null\n')
    result = run_wrapper(['fakepkg', 'show', 'x'], {'IBVS_SETUP': f'{first} {second}'})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith('args=x')


def test_wrapper_runs_a_console_script_of_ours(tmp_path):
    prefix = venv()
    result = run_wrapper(['ibvs_bringup', 'print_pad', str(tmp_path / 'pad.png'), '--dpi', '50'],
                         {'IBVS_VENV': str(prefix)})
    assert result.returncode == 0, result.stderr
    assert (tmp_path / 'pad.png').stat().st_size > 0


@pytest.mark.parametrize('args, env, message', [
    ([], {}, 'usage: ibvs-run PACKAGE EXECUTABLE'),
    (['a', 'b'], {'IBVS_SETUP': '/no/such/setup.bash'},
     '/no/such/setup.bash (IBVS_SETUP) does not exist'),
    (['a', 'b'], {'IBVS_VENV': '/no/such/venv'}, 'IBVS_VENV=/no/such/venv has no bin/python'),
])
def test_wrapper_refuses_with_a_message(args, env, message):
    result = run_wrapper(args, env)
    assert result.returncode == 2 and message in result.stderr, result.stderr
