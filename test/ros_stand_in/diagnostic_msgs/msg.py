"""Stand-in diagnostic_msgs messages (test suite, not ROS). ``level`` is a one-byte ``bytes`` as in rclpy."""
from ros_stand_in_core import Message
from std_msgs.msg import Header


class KeyValue(Message):
    FIELDS = {"key": "string", "value": "string"}


class DiagnosticStatus(Message):
    OK = b"\x00"
    WARN = b"\x01"
    ERROR = b"\x02"
    STALE = b"\x03"
    FIELDS = {"level": "byte", "name": "string", "message": "string", "hardware_id": "string",
              "values": [KeyValue]}


class DiagnosticArray(Message):
    FIELDS = {"header": Header, "status": [DiagnosticStatus]}
