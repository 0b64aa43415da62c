"""Stand-in rclpy.executors (test suite, not ROS)."""


class ExternalShutdownException(Exception):
    """Context has been shutdown."""


class SingleThreadedExecutor:
    """Stand-in: ``spin`` runs the test's spin hook once, like ``rclpy.spin`` here."""

    def __init__(self, *, context: object = None) -> None:
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
