"""Packaging of ibvs_common (ament_python: colcon on Jazzy, pip in the project venv)."""
from setuptools import find_packages, setup

package_name = 'ibvs_common'

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
    description=(
        'The base shared by perception, control and the sim: frames, camera model, paper '
        'feature geometry, attitude buffer, configuration loading (vehicle, cameras, pad '
        'layout), the OpenCV compatibility layer and the common node helpers.'
    ),
    license='Apache-2.0',
)
