"""Packaging of ibvs_bringup (ament_python: colcon on Jazzy, pip in the project venv)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'ibvs_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        # systemd units, their wrapper, environment file and udev rules (docs/onboard.md)
        ('share/' + package_name + '/systemd', glob('systemd/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='IBVS team',
    maintainer_email='ibvs-team@example.com',
    description=('Launch files, parameters, node list, runner, composed container and '
                 'preflight check of the IBVS window-and-landing stack.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'runner = ibvs_bringup.runner:main',
            'composed = ibvs_bringup.composed:main',
            'preflight = ibvs_bringup.preflight:main',
            'print_pad = ibvs_bringup.print_pad:main',
        ],
    },
)
