"""Stand-in geometry_msgs messages (test suite, not ROS)."""
from ros_stand_in_core import Message
from std_msgs.msg import Header


class Vector3(Message):
    FIELDS = {"x": "float64", "y": "float64", "z": "float64"}


class Wrench(Message):
    FIELDS = {"force": Vector3, "torque": Vector3}


class WrenchStamped(Message):
    FIELDS = {"header": Header, "wrench": Wrench}


class Twist(Message):
    FIELDS = {"linear": Vector3, "angular": Vector3}


class TwistWithCovariance(Message):
    FIELDS = {"twist": Twist, "covariance": "float64[]"}     # float64[36] in ROS


class TwistWithCovarianceStamped(Message):
    FIELDS = {"header": Header, "twist": TwistWithCovariance}
