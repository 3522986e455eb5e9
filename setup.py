# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""ament_python package setup: `colcon build` on a ROS 2 Jazzy install, or `pip install -e .`."""

from glob import glob
import os
import runpy

from setuptools import find_packages, setup

package_name = 'mlv_ros'

# The graph's nodes, from its one table (read by path: nothing of the package is imported here).
NODES = runpy.run_path(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), 'mlv_ros', 'graph_table.py')
)['NODES']

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.json')),
        ('share/' + package_name + '/config/phantoms', glob('config/phantoms/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mlv_ros developers',
    maintainer_email='mlv-ros-dev@example.org',
    description='Dense 3D LV motion from tagged MRI with meshless deformable models (ROS 2 '
    'Jazzy).',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [f'{n.name} = {n.entry_point}' for n in NODES]
        + ['mlv-ros = mlv_ros.cli:main'],
    },
)
