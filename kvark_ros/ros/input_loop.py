"""The node's two threads: the inputs on a wait loop of their own, everything else on rclpy's executor.

Why not rclpy's executor for the inputs: its Python ``SingleThreadedExecutor`` rebuilds its wait set, a task
and two coroutines for every message and wakes again for its own guard condition. With only the two raw input
subscriptions in a node it cost 140-165 µs of CPU per message on Fast DDS (a bag played at 1 kHz into a bare
node, rclpy 7.1.6), 205 µs with the node's other entities beside them. rclpy's ``EventsExecutor`` of 7.1.6
fails on a callback that takes the message info (``SystemError: null argument to internal routine``), which
the pairing needs, and takes no guard condition.

:class:`InputLoop` waits on the input subscriptions and one guard condition with rclpy's wait set, and at every
wake takes every message ready on either topic and hands them to the subscriptions' callbacks in publication
order: 18 µs per message in the measurement above. It calls the layer below rclpy's executors
(``rclpy.impl.implementation_singleton``: its ``WaitSet``, a subscription handle's ``take_message``) as
``rclpy.wait_for_message`` does. These entities are in an :class:`InputGroup`, which rclpy's executor never
waits on. That executor spins on a thread of its own (:class:`ServiceThread`) with the services, the parameter
services, the ``/diagnostics`` timer, the ``robot_description`` subscription and the model builds; it sleeps
in rcl's wait between their events, so they cost the inputs nothing. Both threads change the node's state only
under the node's lock.

The input subscriptions have no QoS event handlers. Their sensor-data QoS (best effort, volatile) is compatible
with every publisher's, Fast DDS reports no publisher of another type (none in 60 s with a String publisher on
``joint_states``), and an event handler in a wait set wakes it at every message its subscription receives: in
the executor's, beside the inputs, that rebuilt the wait set twice per sample (0.54 core at 500 Hz against 0.12);
in this loop it cost 11 % of the node's instructions per sample.
"""
from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import TYPE_CHECKING, Any, TypeVar

from rclpy.callback_groups import CallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerGuardCondition
from rclpy.task import Future

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.subscription import Subscription

WAIT_NS = 100_000_000        # a wait returns at least this often (ns) to notice a context shut down without a signal
__all__ = ["InputGroup", "InputLoop", "ServiceThread", "locked", "publication_ns", "spin"]
Method = TypeVar("Method", bound=Callable[..., Any])


def locked(method: Method) -> Method:
    """``method`` run under its object's ``lock``: on the service thread, between two batches of inputs."""
    @functools.wraps(method)
    def run(self: Any, *args: Any) -> Any:
        with self.lock:
            return method(self, *args)
    return run  # type: ignore[return-value]


class InputGroup(CallbackGroup):
    """The entities :class:`InputLoop` waits on (the input subscriptions, its guard condition): rclpy's executor
    never waits on them nor runs them."""

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


def publication_ns(info: dict) -> int | None:
    """When a message was published (ns) by its message info: the source timestamp, else the reception time (a
    middleware that gives neither: None)."""
    published = info.get("source_timestamp")
    return info.get("received_timestamp") if published is None else published


def _publication_order(taken: tuple[bytes, dict, Callable]) -> int:
    return publication_ns(taken[1]) or 0


class InputLoop:
    """Waits on ``subscriptions`` (raw, of ``node``, in an :class:`InputGroup`) on the calling thread and hands every
    message to its subscription's callback ``(raw bytes, message info)`` under ``lock`` (module docstring)."""

    def __init__(self, node: Node, subscriptions: Sequence[Subscription], group: InputGroup,
                 lock: threading.Lock) -> None:
        self._node = node
        self._subscriptions = list(subscriptions)
        # (take, message class, callback) per subscription, looked up once: the loop runs them at every wake
        self._takers = [(subscription.handle.take_message, subscription.msg_type, subscription.callback)
                        for subscription in self._subscriptions]
        self._lock = lock
        self._stopping = False
        self._wake = node.create_guard_condition(lambda: None, callback_group=group)

    def stop(self) -> None:
        """Make ``spin`` return (from any thread)."""
        self._stopping = True
        self._wake.trigger()

    def spin(self) -> None:
        """Take and hand on inputs until ``stop`` or until the context shuts down (SIGINT, SIGTERM, rclpy.shutdown)."""
        context = self._node.context
        sigint = SignalHandlerGuardCondition(context)
        try:
            with ExitStack() as held:
                subscriptions = [subscription.handle for subscription in self._subscriptions]
                guards = [guard.handle for guard in (self._wake, sigint)]
                for handle in (*subscriptions, *guards):
                    held.enter_context(handle)          # in use: not destroyed while waited on
                wait_set = _rclpy.WaitSet(len(subscriptions), len(guards), 0, 0, 0, 0, context.handle)
                while not self._stopping and context.ok():
                    wait_set.clear_entities()
                    for handle in subscriptions:
                        wait_set.add_subscription(handle)
                    for handle in guards:
                        wait_set.add_guard_condition(handle)
                    wait_set.wait(WAIT_NS)
                    self.take_all()
        finally:
            sigint.destroy()

    def take_all(self) -> int:
        """Take every message ready on the subscriptions and hand them on in publication order (each topic keeps its
        own order; across topics the pairing needs it once more states wait than it holds); how many."""
        taken: list[tuple[bytes, dict, Callable]] = []
        topics = 0
        for take, kind, callback in self._takers:
            before = len(taken)
            while (message := take(kind, True)) is not None:
                taken.append((message[0], message[1], callback))
            topics += len(taken) > before
        if not taken:
            return 0
        if topics > 1:
            taken.sort(key=_publication_order)
        with self._lock:
            for raw, info, callback in taken:
                callback(raw, info)
        return len(taken)


class ServiceThread:
    """rclpy's ``SingleThreadedExecutor`` spinning ``node`` (all but its :class:`InputGroup` subscriptions) on a thread;
    ``on_end`` is called when it stops for another reason than a shutdown (a callback raised: ``failure``)."""

    def __init__(self, node: Node, on_end: Callable[[], None]) -> None:
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self.failure: BaseException | None = None
        self._context = node.context
        self._on_end = on_end
        self._stopped = Future()
        self._thread = threading.Thread(target=self._spin, name="kvark_services", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin_until_future_complete(self._stopped)
        except ExternalShutdownException:
            return
        except BaseException as exc:
            # A RuntimeError once the context is shut down is rclpy's signal handler racing the executor
            # (ros2/rclpy#398): a stop, not a fault.
            if self._context.ok() or not isinstance(exc, RuntimeError):
                self.failure = exc
        if self.failure is not None or (self._context.ok() and not self._stopped.done()):
            self._on_end()

    def stop(self, timeout: float = 5.0) -> None:
        """End the thread's spin, wait up to ``timeout`` s for it, then shut the executor down. In that order:
        rclpy 7.1's ``Executor.shutdown`` destroys the executor's guard conditions at once, whatever its timeout,
        and a spin between its shutdown check and its next wait set then fails on them (``AttributeError``, seen
        as exit code 1 on SIGTERM)."""
        self._stopped.set_result(True)                # wakes the executor: its spin returns at this wake
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.executor.shutdown(timeout_sec=0.0)


def spin(node: Node) -> None:
    """Run ``node`` on the two threads (module docstring) until ``rclpy`` shuts down: its ``inputs`` (an
    :class:`InputGroup`'s raw subscriptions) on this thread under its ``lock``, the rest on a :class:`ServiceThread`;
    a callback's error on either thread is raised here."""
    loop = InputLoop(node, node.inputs, node.input_group, node.lock)
    services = ServiceThread(node, on_end=loop.stop)
    try:
        services.start()
        loop.spin()
    finally:
        services.stop()
    if services.failure is not None:
        raise services.failure
