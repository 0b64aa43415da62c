"""Stand-in rclpy.logging (test suite, not ROS): loggers record what they are told."""
from __future__ import annotations

from typing import Any

_LOGGERS: dict[str, "RcutilsLogger"] = {}


class RcutilsLogger:
    def __init__(self, name: str) -> None:
        self.name = name
        self.records: list[tuple[str, str]] = []

    def _log(self, level: str, message: str, **options: Any) -> bool:
        self.records.append((level, str(message)))
        return True

    def debug(self, message: str, **options: Any) -> bool:
        return self._log("DEBUG", message, **options)

    def info(self, message: str, **options: Any) -> bool:
        return self._log("INFO", message, **options)

    def warning(self, message: str, **options: Any) -> bool:
        return self._log("WARN", message, **options)

    warn = warning

    def error(self, message: str, **options: Any) -> bool:
        return self._log("ERROR", message, **options)

    def fatal(self, message: str, **options: Any) -> bool:
        return self._log("FATAL", message, **options)


def get_logger(name: str) -> RcutilsLogger:
    return _LOGGERS.setdefault(name, RcutilsLogger(name))
