"""Packaging of ibvs_sim (ament_python: colcon on Jazzy, pip in the project venv)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'ibvs_sim'

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
    description=('Simulated AscTec Pelican-class quadrotor with two cameras and a MAVLink '
                 'autopilot (PX4 offboard-like) for the IBVS stack.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sim = ibvs_sim.sim_node:main',
            'px4_sim = ibvs_sim.px4_sim_node:main',
        ],
    },
)
