"""Stand-in rclpy.impl (test suite, not ROS)."""
