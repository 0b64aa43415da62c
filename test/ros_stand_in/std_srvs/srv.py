"""Stand-in std_srvs services (test suite, not ROS)."""
from ros_stand_in_core import Message


class Trigger:
    class Request(Message):
        FIELDS: dict = {}

    class Response(Message):
        FIELDS = {"success": "bool", "message": "string"}
