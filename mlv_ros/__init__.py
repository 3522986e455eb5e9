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
mlv_ros: dense 3D left-ventricle motion from tagged cardiac MRI as a ROS 2 Jazzy node graph.

``mlv_ros.core`` is a pure numpy/scipy/OpenCV library (no rclpy); ``mlv_ros.nodes`` holds one
thin rclpy node per file; ``mlv_ros.conversions`` is the only place numpy meets messages.
"""

__version__ = '0.1.0'
