"""
One rclpy node per module; each module's ``main()`` is a console script and a ``ros2 run`` target.

Nodes are thin: parameters, message conversion (``mlv_ros.conversions``), a call into
``mlv_ros.core``, publish.
"""
