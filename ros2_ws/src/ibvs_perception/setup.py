"""Packaging of ibvs_perception (ament_python: colcon on Jazzy, pip in the project venv)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'ibvs_perception'

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
    description=('Window detection, pad (ArUco) detection and translational optical flow '
                 'nodes for IBVS.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'window_detector = ibvs_perception.window_detector_node:main',
            'pad_detector = ibvs_perception.pad_detector_node:main',
            'optical_flow = ibvs_perception.optical_flow_node:main',
        ],
    },
)
