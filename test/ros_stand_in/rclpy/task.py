"""Stand-in rclpy.task (test suite, not ROS): a Future a worker thread completes and a coroutine awaits."""
from __future__ import annotations

import threading
from typing import Any, Callable


class Future:
    """rclpy's Future as the node uses it: ``set_result`` from any thread, ``await`` in a callback."""

    def __init__(self, *, executor: Any = None) -> None:
        self._done = threading.Event()
        self._result: Any = None
        self._exception: BaseException | None = None
        self._callbacks: list[Callable[[Future], None]] = []

    def done(self) -> bool:
        return self._done.is_set()

    def result(self) -> Any:
        return self._result

    def set_result(self, result: Any) -> None:
        self._result = result
        self._done.set()
        for callback in self._callbacks:
            callback(self)

    def set_exception(self, exception: BaseException) -> None:
        self._exception = exception
        self.set_result(None)

    def add_done_callback(self, callback: Callable[[Future], None]) -> None:
        self._callbacks.append(callback)

    def __await__(self):
        while not self._done.is_set():
            yield
        if self._exception is not None:
            raise self._exception
        return self._result
