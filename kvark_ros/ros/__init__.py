"""The ROS 2 adapter of kvark_ros: the ``kvark_estimator`` node (``estimator_node``), its parameters
(``parameters``), its estimate topics (``publishers``) and its ``/diagnostics`` statuses (``diagnostics``).

Only this package imports rclpy and ROS message types; every rule it applies (pairing, contact
test, config) lives in ``kvark_ros.core``, ROS-free, so the suite tests it without ROS. Importing
``kvark_ros.ros`` itself does not import rclpy.
"""
