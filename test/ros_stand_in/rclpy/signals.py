"""Stand-in rclpy.signals (test suite, not ROS): no signal handling; the input loop that would wait on the
signal guard condition is never started here (see ``rclpy.impl.implementation_singleton``)."""


class SignalHandlerGuardCondition:
    def __init__(self, context: object = None) -> None:
        raise NotImplementedError("stand-in: the node's input loop runs under real rclpy only")
