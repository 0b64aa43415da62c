"""The node's two threads (``kvark_ros.ros.input_loop``): the inputs' wait loop and the service thread.

The order in which one take hands messages on is checked with subscriptions whose queues the test fills (real
DDS cannot be made to hold a given set of messages at a given moment); what rclpy's executor does and does not
take, and how the two threads end, with the real rclpy in this process, on a ROS domain of its own.
"""
from __future__ import annotations

import platform
import sys
import threading
import time

import pytest

if not (sys.platform == "linux" and platform.machine() == "x86_64"):
    pytest.skip("the ROS 2 Jazzy wheels exist for linux x86_64 only", allow_module_level=True)

import rclpy  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from kvark_ros.ros import input_loop, node_process  # noqa: E402
from kvark_ros.ros.input_loop import InputGroup, InputLoop, ServiceThread  # noqa: E402

DOMAINS = iter(range(150, 160))


class Queue:
    """A subscription whose handle takes from a list: ``take_message`` gives (raw, info) until it is empty."""

    def __init__(self, messages: list[tuple[bytes, dict]], callback) -> None:
        self.msg_type, self.callback, self._messages = JointState, callback, list(messages)
        self.handle = self

    def take_message(self, kind: type, raw: bool):
        assert kind is JointState and raw
        return self._messages.pop(0) if self._messages else None


class Graphless:
    """A node as far as ``InputLoop`` needs one before it spins."""

    def create_guard_condition(self, callback, callback_group=None):
        return None


def test_one_take_hands_on_every_ready_message_in_publication_order_under_the_lock():
    """Twelve joint states and twelve commands ready at once, interleaved as published (by source timestamp, else
    reception time): one take hands on all 24, in that order, each topic in its own order, under the lock."""
    states = [(b"s%d" % k, {"source_timestamp": 10 * k, "received_timestamp": 10 * k + 1}) for k in range(12)]
    commands = [(b"c%d" % k, {"source_timestamp": None, "received_timestamp": 10 * k + 5}) for k in range(12)]
    lock, got = threading.Lock(), []

    def callback(raw: bytes, info: dict) -> None:
        got.append((raw, lock.locked()))

    loop = InputLoop(Graphless(), [Queue(states, callback), Queue(commands, callback)], InputGroup(), lock)
    assert loop.take_all() == 24
    assert [raw for raw, _ in got] == [raw for pair in zip(states, commands) for raw, _ in pair]
    assert all(held for _, held in got)
    assert loop.take_all() == 0 and len(got) == 24


@pytest.fixture
def domain(tmp_path):
    with node_process.joined(node_process.local_domain(next(DOMAINS), tmp_path / "log")):
        yield


def _node(name: str):
    """An rclpy node with what ``input_loop.spin`` runs: input subscriptions, their group and a lock."""
    node = rclpy.create_node(name)
    node.inputs, node.input_group, node.lock = [], InputGroup(), threading.Lock()
    return node


def test_rclpys_executor_never_takes_the_input_subscriptions(domain):
    """Messages on an input subscription stay for the input loop while the service thread's executor spins (with
    a timer of its own, which it does run); the loop then takes them all."""
    node, sender = _node("kvark_input_loop_test"), rclpy.create_node("kvark_input_loop_sender")
    taken, ticks = [], []
    node.inputs = [node.create_subscription(JointState, "joint_states", lambda raw, info: taken.append(raw),
                                            qos_profile_sensor_data, callback_group=node.input_group, raw=True)]
    node.create_timer(0.01, lambda: ticks.append(1))
    publisher = sender.create_publisher(JointState, "joint_states", qos_profile_sensor_data)
    loop = InputLoop(node, node.inputs, node.input_group, node.lock)
    services = ServiceThread(node, on_end=loop.stop)
    services.start()
    try:
        deadline = time.monotonic() + 20.0
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        for k in range(5):
            publisher.publish(JointState(name=[f"joint{k}"]))
        while len(ticks) < 20 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(ticks) >= 20 and not taken, "the executor ran its timer and took no input"
        while len(taken) < 5 and time.monotonic() < deadline:
            loop.take_all()
            time.sleep(0.01)
        assert len(taken) == 5 and all(isinstance(raw, bytes) for raw in taken)
    finally:
        services.stop()
        node.destroy_node()
        sender.destroy_node()


def test_an_error_on_the_service_thread_ends_the_input_loop_and_is_raised(domain):
    node = _node("kvark_input_loop_fault")

    def fail() -> None:
        raise ValueError("a service callback failed")

    node.create_timer(0.05, fail)
    with pytest.raises(ValueError, match="a service callback failed"):
        input_loop.spin(node)
    node.destroy_node()


def test_a_shutdown_ends_both_threads_without_an_error(domain):
    node = _node("kvark_input_loop_shutdown")
    node.create_timer(0.05, rclpy.shutdown)
    started = time.monotonic()
    input_loop.spin(node)
    assert not rclpy.ok() and time.monotonic() - started < 5.0
    node.destroy_node()


def test_a_stop_while_the_executor_builds_its_wait_set_ends_the_thread_without_a_fault(domain):
    """The race behind a node's exit code 1 on SIGTERM (a run of the suite on 2 busy cores): the service thread's
    executor past its shutdown check, gathering the entities of its next wait set, when ``stop`` comes. Made here
    on demand: the executor's ``get_nodes`` (called right after that check) holds once armed until the executor is
    shut down, or 0.5 s. ``stop`` must end the spin before it shuts the executor down (rclpy 7.1's shutdown
    destroys the guard conditions at once, and a spin that goes on then fails on them): no failure, no ``on_end``,
    the thread ended."""
    node = _node("kvark_input_loop_stop_race")
    node.create_timer(0.005, lambda: None)                    # keeps the executor going round its loop
    ended: list[bool] = []
    services = ServiceThread(node, on_end=lambda: ended.append(True))
    armed, inside, shut = threading.Event(), threading.Event(), threading.Event()
    get_nodes, shutdown = services.executor.get_nodes, services.executor.shutdown

    def held_get_nodes():
        if armed.is_set() and not inside.is_set():
            inside.set()
            shut.wait(0.5)
        return get_nodes()

    def marked_shutdown(*args, **kwargs):
        result = shutdown(*args, **kwargs)
        shut.set()
        return result

    services.executor.get_nodes, services.executor.shutdown = held_get_nodes, marked_shutdown
    services.start()
    armed.set()
    assert inside.wait(10.0), "the executor never came round its loop"
    services.stop()                                           # returns once the thread has ended
    assert services.failure is None, repr(services.failure)
    assert not ended and "kvark_services" not in {thread.name for thread in threading.enumerate()}
    node.destroy_node()
