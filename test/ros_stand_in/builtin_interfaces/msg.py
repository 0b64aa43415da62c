"""Stand-in builtin_interfaces messages (test suite, not ROS)."""
from ros_stand_in_core import Message


class Time(Message):
    FIELDS = {"sec": "int32", "nanosec": "uint32"}


class Duration(Message):
    FIELDS = {"sec": "int32", "nanosec": "uint32"}
