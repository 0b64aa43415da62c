"""Stand-in rclpy.callback_groups (test suite, not ROS): the stand-in calls back synchronously."""


class CallbackGroup:
    """Base of the callback groups (no scheduling in the stand-in); subclasses define when an executor may run
    an entity, as rclpy's do."""

    def can_execute(self, entity: object) -> bool:
        raise NotImplementedError()

    def beginning_execution(self, entity: object) -> bool:
        raise NotImplementedError()

    def ending_execution(self, entity: object) -> None:
        raise NotImplementedError()


class MutuallyExclusiveCallbackGroup(CallbackGroup):
    """Callbacks of one group never run at the same time."""


class ReentrantCallbackGroup(CallbackGroup):
    """Callbacks of one group may run at the same time."""
