"""ROS 2 bag input/output (rosbags only, no rclpy)."""
