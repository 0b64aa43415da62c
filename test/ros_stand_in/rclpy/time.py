"""Stand-in rclpy.time (test suite, not ROS)."""
from __future__ import annotations

from builtin_interfaces.msg import Time as TimeMsg


class Time:
    def __init__(self, *, seconds: float = 0, nanoseconds: int = 0, clock_type: int = 1) -> None:
        total = int(seconds * 1e9) + int(nanoseconds)
        if total < 0:
            raise ValueError("Negative times are not allowed")
        self._nanoseconds = total

    @property
    def nanoseconds(self) -> int:
        return self._nanoseconds

    def seconds_nanoseconds(self) -> tuple[int, int]:
        return divmod(self._nanoseconds, 1_000_000_000)

    def to_msg(self) -> TimeMsg:
        sec, nanosec = self.seconds_nanoseconds()
        return TimeMsg(sec=sec, nanosec=nanosec)

    @classmethod
    def from_msg(cls, msg: TimeMsg, clock_type: int = 1) -> "Time":
        return cls(nanoseconds=msg.sec * 1_000_000_000 + msg.nanosec)
