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

"""
The mlv_ros graph, one process per node, for users with a full ROS 2 Jazzy install.

Launch it with::

    ros2 launch mlv_ros pipeline.launch.py                                  # a phantom
    ros2 launch mlv_ros pipeline.launch.py source:=dicom path:=/data/study  # a DICOM study
    ros2 launch mlv_ros pipeline.launch.py source:=bag path:=runs/old       # a recording's frames
        [output_dir:=runs/mine] [namespace:=study2] [params_file:=/path/to/graph.yaml]
        [live:=true [live_port:=8765]]                                      # watch in Foxglove

Each launch records to a fresh ``runs/<YYYYmmdd-HHMMSS>/run.mcap`` under the directory it was
started from unless ``output_dir`` says where (what the arguments become:
:mod:`mlv_ros.launch_settings`). Without ROS's launch tools (e.g. a PyPI-only install) run the
same graph in one process with ``mlv-ros run``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from mlv_ros.graph_table import RUN_NODES
from mlv_ros.launch_settings import graph_settings


def launch_setup(context, *args, **kwargs):
    """Return the graph's nodes, for the arguments as given at launch time."""
    arg = {
        name: LaunchConfiguration(name).perform(context)
        for name in (
            'source',
            'path',
            'output_dir',
            'namespace',
            'params_file',
            'live',
            'live_port',
        )
    }
    settings = graph_settings(arg['source'], arg['path'], arg['output_dir'], arg['namespace'])
    print(
        f'[mlv_ros] recording to {settings.output_dir / "run.mcap"}'
        + (f' (namespace {settings.namespace})' if settings.namespace else '')
    )
    nodes = [*RUN_NODES, *(['live_view'] if arg['live'] == 'true' else [])]
    if arg['live'] == 'true':  # the live view's port; the node refuses one out of range at start
        settings.overrides['live_view'] = {
            **settings.overrides.get('live_view', {}),
            'port': int(arg['live_port']),
        }
        print(
            f'[mlv_ros] live view on port {arg["live_port"]} (Foxglove: Open connection, '
            'Foxglove WebSocket)'
        )
    return [
        Node(
            package='mlv_ros',
            executable=name,
            name=name,
            namespace=settings.namespace or None,
            parameters=[arg['params_file'], settings.overrides.get(name, {})],
            output='screen',
        )
        for name in nodes
    ]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('mlv_ros'), 'config', 'graph.yaml')
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'source',
                default_value='phantom',
                choices=['phantom', 'dicom', 'bag'],
                description='where frames come from: a simulated phantom, a DICOM directory, '
                'or the frames of a recording',
            ),
            DeclareLaunchArgument(
                'path',
                default_value='',
                description='the DICOM directory (source:=dicom) or recording (source:=bag)',
            ),
            DeclareLaunchArgument(
                'output_dir',
                default_value='',
                description='run directory for run.mcap; empty: a fresh runs/<YYYYmmdd-HHMMSS>',
            ),
            DeclareLaunchArgument(
                'namespace',
                default_value='',
                description='ROS namespace of every node and topic (e.g. study2); empty: the root',
            ),
            DeclareLaunchArgument(
                'params_file',
                default_value=default_params,
                description='parameters of the whole graph (keys /**/<node>, as in '
                'config/graph.yaml)',
            ),
            DeclareLaunchArgument(
                'live',
                default_value='false',
                choices=['true', 'false'],
                description='also start live_view: the run served to Foxglove over a WebSocket '
                '(layout config/foxglove_layout.json)',
            ),
            DeclareLaunchArgument(
                'live_port',
                default_value='8765',
                description="the live view's WebSocket port (live:=true)",
            ),
            OpaqueFunction(function=launch_setup),
        ]
    )
