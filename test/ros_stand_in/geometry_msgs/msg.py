"""Stand-in geometry_msgs messages (test suite, not ROS)."""
from ros_stand_in_core import Message
from std_msgs.msg import Header


class Vector3(Message):
    FIELDS = {"x": "float64", "y": "float64", "z": "float64"}


class Wrench(Message):
    FIELDS = {"force": Vector3, "torque": Vector3}


class WrenchStamped(Message):
    FIELDS = {"header": Header, "wrench": Wrench}
