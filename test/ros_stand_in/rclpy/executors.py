"""Stand-in rclpy.executors (test suite, not ROS)."""


class ExternalShutdownException(Exception):
    """Context has been shutdown."""


class SingleThreadedExecutor:
    """Stand-in: nothing to wait on (the graph calls back synchronously), so ``spin`` returns at once."""

    def __init__(self, *, context: object = None) -> None:
        self.nodes: list = []

    def add_node(self, node: object) -> bool:
        self.nodes.append(node)
        return True

    def spin(self) -> None:
        return None

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        return True
