"""Stand-in rclpy.executors (test suite, not ROS)."""


class ExternalShutdownException(Exception):
    """Context has been shutdown."""


class MultiThreadedExecutor:
    """Stand-in: ``spin`` runs the test's spin hook once, like ``rclpy.spin`` here (no threads)."""

    def __init__(self, num_threads: int | None = None, *, context: object = None) -> None:
        self.num_threads = num_threads
        self.nodes: list = []

    def add_node(self, node: object) -> bool:
        self.nodes.append(node)
        return True

    def spin(self) -> None:
        import rclpy
        for node in self.nodes:
            rclpy.spin(node)

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        return True
