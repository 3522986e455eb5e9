"""
mlv_ros: dense 3D left-ventricle motion from tagged cardiac MRI as a ROS 2 Jazzy node graph.

``mlv_ros.core`` is a pure numpy/scipy/OpenCV library (no rclpy); ``mlv_ros.nodes`` holds one
thin rclpy node per file; ``mlv_ros.conversions`` is the only place numpy meets messages.
"""

__version__ = '0.1.0'
