"""Packaging of ibvs_harness (ament_python: colcon on Jazzy, pip in the project venv)."""
from setuptools import find_packages, setup

package_name = 'ibvs_harness'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='IBVS team',
    maintainer_email='ibvs-team@example.com',
    description=('Experiment harness of the IBVS window-and-landing stack: scenario runs, '
                 'campaigns, reports, plots, bag record/replay and the feature-level loop.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'run_scenario = ibvs_harness.run_scenario:main',
            'campaign = ibvs_harness.campaign:main',
            'recorder = ibvs_harness.recorder_node:main',
            'bag_player = ibvs_harness.bag_player_node:main',
        ],
    },
)
