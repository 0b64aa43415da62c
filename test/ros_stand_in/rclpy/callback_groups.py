"""Stand-in rclpy.callback_groups (test suite, not ROS): the stand-in calls back synchronously."""


class CallbackGroup:
    """Base of the callback groups (no scheduling in the stand-in)."""


class MutuallyExclusiveCallbackGroup(CallbackGroup):
    """Callbacks of one group never run at the same time."""


class ReentrantCallbackGroup(CallbackGroup):
    """Callbacks of one group may run at the same time."""
