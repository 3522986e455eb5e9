"""The mlv_ros graph, one process per node, for users with a full ROS 2 Jazzy install:

    ros2 launch mlv_ros pipeline.launch.py [params_file:=/path/to/graph.yaml]

Without ROS's launch tools (e.g. a PyPI-only install) run the same graph in one process with
``mlv-ros run``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = ["recorder", "motion_analyzer", "meshless_solver", "registration", "tag_detector", "frame_source"]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("mlv_ros"), "config", "graph.yaml")
    params = LaunchConfiguration("params_file")
    return LaunchDescription(
        [DeclareLaunchArgument("params_file", default_value=default_params,
                               description="parameters of the whole graph")]
        + [Node(package="mlv_ros", executable=name, name=name, parameters=[params], output="screen")
           for name in NODES]
    )
