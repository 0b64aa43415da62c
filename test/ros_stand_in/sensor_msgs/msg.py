"""Stand-in sensor_msgs messages (test suite, not ROS)."""
from ros_stand_in_core import Message
from std_msgs.msg import Header


class JointState(Message):
    FIELDS = {"header": Header, "name": "string[]", "position": "float64[]", "velocity": "float64[]",
              "effort": "float64[]"}
