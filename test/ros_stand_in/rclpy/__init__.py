"""Stand-in for rclpy, owned by the kvark_ros test suite. This is NOT ROS.

Implements only what ``kvark_ros/ros`` uses (init/shutdown/try_shutdown/ok, Node, QoS,
parameters, clock, logging) on the in-process machinery of ``ros_stand_in_core``.
"""
from __future__ import annotations

from typing import Any

import ros_stand_in_core as _core

STAND_IN = True


def init(*, args: list[str] | None = None, context: Any = None, domain_id: int | None = None,
         signal_handler_options: Any = None) -> None:
    if _core.CONTEXT.initialized:
        raise RuntimeError("Context.init() must only be called once")
    _core.CONTEXT.initialized = True
    _core.parse_arguments(list(args) if args is not None else None)


def ok(*, context: Any = None) -> bool:
    return _core.CONTEXT.initialized


def shutdown(*, context: Any = None, uninstall_handlers: bool | None = None) -> None:
    if not _core.CONTEXT.initialized:
        raise RuntimeError("failed to shutdown: rcl_shutdown already called on the given context")
    _core.CONTEXT.initialized = False


def try_shutdown(*, context: Any = None, uninstall_handlers: bool | None = None) -> None:
    _core.CONTEXT.initialized = False
