"""Packaging of ibvs_control (ament_python: colcon on Jazzy, pip in the project venv)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'ibvs_control'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='IBVS team',
    maintainer_email='ibvs-team@example.com',
    description=(
        'IBVS control core (the paper\'s control laws, mode state machine, timing model, '
        'MAVLink pieces) and the control nodes: mode supervisor, outer-loop force '
        'controller, MAVLink bridge.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'mode_supervisor = ibvs_control.mode_supervisor_node:main',
            'force_controller = ibvs_control.force_controller_node:main',
            'mavlink_bridge = ibvs_control.mavlink_bridge_node:main',
        ],
    },
)
