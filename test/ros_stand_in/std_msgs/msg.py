"""Stand-in std_msgs messages (test suite, not ROS)."""
from builtin_interfaces.msg import Time
from ros_stand_in_core import Message


class Header(Message):
    FIELDS = {"stamp": Time, "frame_id": "string"}


class String(Message):
    FIELDS = {"data": "string"}


class Bool(Message):
    FIELDS = {"data": "bool"}


class MultiArrayDimension(Message):
    FIELDS = {"label": "string", "size": "uint32", "stride": "uint32"}


class MultiArrayLayout(Message):
    FIELDS = {"dim": [MultiArrayDimension], "data_offset": "uint32"}


class Float64MultiArray(Message):
    FIELDS = {"layout": MultiArrayLayout, "data": "float64[]"}
