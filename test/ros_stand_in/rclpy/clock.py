"""Stand-in rclpy.clock (test suite, not ROS): every node reads the shared simulated clock."""
import ros_stand_in_core as _core
from rclpy.time import Time


class Clock:
    def now(self) -> Time:
        return Time(nanoseconds=_core.now_ns())
