"""Stand-in rclpy.executors (test suite, not ROS)."""


class ExternalShutdownException(Exception):
    """Context has been shutdown."""
