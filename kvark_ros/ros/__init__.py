"""The ROS 2 adapter of kvark_ros: the ``kvark_estimator`` node (``estimator_node``).

Only this package imports rclpy and ROS message types, and only in ``estimator_node``; helpers
such as ``contact`` are ROS-free so that the suite can test them without ROS. Importing
``kvark_ros.ros`` itself does not import rclpy.
"""
