"""Command-line tools built on the ROS-free core (no rclpy here)."""
