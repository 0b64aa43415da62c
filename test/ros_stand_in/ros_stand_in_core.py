"""Machinery of the rclpy stand-in owned by the kvark_ros test suite. This is NOT ROS.

Real rclpy is in the lock and tests the node as a process (test_ros_node.py). This stand-in fakes
the small part of the rclpy API that ``kvark_ros/ros`` uses, closely enough to drive the node's
callbacks in-process, for what real DDS cannot produce on demand: a chosen delivery order and a clock
the test moves:

- messages are plain Python objects whose fields are type-checked on assignment the way the
  rosidl-generated Python classes check them (``float64[]`` fields take ``array.array('d')`` or
  a sequence of floats, never a numpy array; ``bool`` fields take only ``bool``; ``byte``
  fields take a one-byte ``bytes``);
- serialised messages are CDR as rosbags writes it (:func:`to_cdr`, :func:`from_cdr`): a ``raw=True``
  subscription gets the bytes of what is delivered, and ``publish`` takes a message's bytes as rclpy
  does (the graph keeps the message they decode to);
- one in-process graph: ``publish`` calls every subscription of the resolved topic name
  synchronously, in the caller's thread (no executor, no QoS, no wait set: the node's input loop
  is not faked, its subscriptions' callbacks are called directly); an ``async def`` callback is run
  to completion before the call returns;
- one simulated clock shared by every node (like ``use_sim_time``), moved by the test with
  :func:`set_time`, which also fires the timers that fall due;
- parameters follow rclpy's rules (declare/override/descriptor/read-only/range/callbacks).

Only the tests put this directory on ``sys.path`` (see ``test/ros/test_node_logic_stand_in.py``); it is
never installed.
"""
from __future__ import annotations

import array
import copy
import inspect
import time
from collections import UserList
from collections.abc import Sequence, Set
from typing import Any

import numpy as np
import yaml
from rosbags.typesys import Stores, get_typestore

STAND_IN = True

# --------------------------------------------------------------------------- messages

_INT_RANGES = {"int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int32": (-2**31, 2**31 - 1),
               "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
_FLOAT_MAX = 1.7976931348623157e+308


def _is_sequence(value: Any) -> bool:
    return (isinstance(value, (Sequence, Set, UserList)) and not isinstance(value, (str, bytes)))


def _check(owner: str, name: str, kind: Any, value: Any) -> Any:
    """Validate ``value`` for a field of ``kind`` like rosidl's setters do; return what is stored."""
    where = f"The '{name}' field of {owner}"
    if isinstance(kind, type):                                   # nested message
        assert isinstance(value, kind), f"{where} must be a sub message of type '{kind.__name__}'"
        return value
    if isinstance(kind, list):                                   # sequence of messages
        inner = kind[0]
        assert _is_sequence(value) and all(isinstance(v, inner) for v in value), \
            f"{where} must be a set or sequence and each value of type '{inner.__name__}'"
        return list(value)
    if kind == "float64":
        assert isinstance(value, float), f"{where} must be of type 'float'"
        assert -_FLOAT_MAX <= value <= _FLOAT_MAX or value != value or abs(value) == float("inf"), where
        return value
    if kind in _INT_RANGES:
        low, high = _INT_RANGES[kind]
        assert isinstance(value, int) and not isinstance(value, bool), f"{where} must be of type 'int'"
        assert low <= value <= high, f"{where} must be an integer in [{low}, {high}]"
        return value
    if kind == "bool":
        assert isinstance(value, bool), f"{where} must be of type 'bool'"
        return value
    if kind == "byte":
        assert isinstance(value, bytes) and len(value) == 1, f"{where} must be of type 'bytes' of length 1"
        return value
    if kind == "string":
        assert isinstance(value, str), f"{where} must be of type 'str'"
        return value
    if kind == "float64[]":
        if isinstance(value, array.array):
            assert value.typecode == "d", f"{where} array.array() must have the type code of 'd'"
            return value
        assert _is_sequence(value) and all(isinstance(v, float) for v in value), \
            f"{where} must be a set or sequence and each value of type 'float'"
        return array.array("d", value)
    if kind == "string[]":
        assert _is_sequence(value) and all(isinstance(v, str) for v in value), \
            f"{where} must be a set or sequence and each value of type 'str'"
        return list(value)
    raise TypeError(f"stand-in: unknown field kind {kind!r}")


def _default(kind: Any) -> Any:
    if isinstance(kind, type):
        return kind()
    if isinstance(kind, list) or kind == "string[]":
        return []
    return {"float64": 0.0, "bool": False, "byte": b"\x00", "string": "", "float64[]": array.array("d")}.get(kind, 0)


class Message:
    """Base of the stand-in messages: ``FIELDS`` maps field name to kind; kwargs set fields."""

    FIELDS: dict[str, Any] = {}

    def __init__(self, **kwargs: Any) -> None:
        unknown = sorted(set(kwargs) - set(self.FIELDS))
        assert not unknown, f"Invalid arguments passed to constructor: {', '.join(unknown)}"
        for name, kind in self.FIELDS.items():
            setattr(self, name, kwargs[name] if name in kwargs else _default(kind))

    def __setattr__(self, name: str, value: Any) -> None:
        if name not in self.FIELDS:
            raise AttributeError(f"'{type(self).__name__}' object has no attribute '{name}'")
        object.__setattr__(self, name, _check(type(self).__name__, name, self.FIELDS[name], value))

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and all(getattr(self, f) == getattr(other, f) for f in self.FIELDS)

    def __repr__(self) -> str:
        body = ", ".join(f"{f}={getattr(self, f)!r}" for f in self.FIELDS)
        return f"{type(self).__module__}.{type(self).__name__}({body})"

    def __deepcopy__(self, memo: dict) -> "Message":
        clone = type(self).__new__(type(self))
        for name in self.FIELDS:
            object.__setattr__(clone, name, copy.deepcopy(getattr(self, name), memo))
        return clone


# --------------------------------------------------------------------------- serialised messages

_STORE = get_typestore(Stores.ROS2_JAZZY)


def msgtype(kind: type) -> str:
    """The ROS name of a stand-in message class: ``sensor_msgs/msg/JointState``."""
    return f"{kind.__module__.replace('.', '/')}/{kind.__name__}"


def _to_rosbags(message: Message) -> Any:
    values = {}
    for name, kind in message.FIELDS.items():
        value = getattr(message, name)
        if isinstance(kind, type):
            value = _to_rosbags(value)
        elif isinstance(kind, list):
            value = [_to_rosbags(item) for item in value]
        elif kind == "float64[]":
            value = np.array(value, dtype=np.float64)
        elif kind == "byte":
            value = value[0]
        values[name] = value
    return _STORE.types[msgtype(type(message))](**values)


def _from_rosbags(value: Any, kind: Any) -> Any:
    if isinstance(kind, type):
        return kind(**{name: _from_rosbags(getattr(value, name), inner) for name, inner in kind.FIELDS.items()})
    if isinstance(kind, list):
        return [_from_rosbags(item, kind[0]) for item in value]
    if kind == "float64[]":
        return array.array("d", np.asarray(value, dtype=np.float64).tobytes())
    if kind == "float64":
        return float(value)
    if kind == "bool":
        return bool(value)
    if kind == "byte":
        return bytes([int(value)])
    if kind == "string[]":
        return [str(item) for item in value]
    return value if kind == "string" else int(value)


def to_cdr(message: Message) -> bytes:
    """A stand-in message serialised as CDR (little endian), by rosbags."""
    return bytes(_STORE.serialize_cdr(_to_rosbags(message), msgtype(type(message))))


def from_cdr(raw: bytes, kind: type) -> Message:
    """The stand-in message of class ``kind`` that CDR bytes ``raw`` hold."""
    return _from_rosbags(_STORE.deserialize_cdr(raw, msgtype(kind)), kind)


# --------------------------------------------------------------------------- context and clock


class _Context:
    def __init__(self) -> None:
        self.initialized = False
        self.overrides: list[tuple[str, dict[str, Any]]] = []   # (node spec, dotted parameters)


CONTEXT = _Context()
_CLOCK_NS = [0]


def now_ns() -> int:
    return _CLOCK_NS[0]


def set_time(seconds: float | None = None, nanoseconds: int | None = None) -> None:
    """Move the shared simulated clock (never backwards unless asked) and fire due timers."""
    target = int(nanoseconds) if nanoseconds is not None else int(round(float(seconds) * 1e9))
    while True:
        due = [t for t in GRAPH.timers if not t.canceled and t.next_due_ns <= target]
        if not due:
            break
        timer = min(due, key=lambda t: t.next_due_ns)
        _CLOCK_NS[0] = max(_CLOCK_NS[0], timer.next_due_ns)
        timer.next_due_ns += timer.timer_period_ns
        timer.callback()
    _CLOCK_NS[0] = target


def _flatten(tree: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _node_specs(tree: dict, prefix: str = "") -> list[tuple[str, dict[str, Any]]]:
    """(node spec, parameters) from a ROS 2 parameter file's nested node keys."""
    found = []
    for key, value in tree.items():
        if not isinstance(value, dict):
            continue
        name = f"{prefix}/{str(key).strip('/')}"
        if "ros__parameters" in value:
            found.append((name, _flatten(value["ros__parameters"])))
        else:
            found.extend(_node_specs(value, name))
    return found


def parse_arguments(args: list[str] | None) -> None:
    """The ``--ros-args --params-file FILE -p name:=value`` subset of ROS arguments."""
    CONTEXT.overrides = []
    if not args or "--ros-args" not in args:
        return
    rest = args[args.index("--ros-args") + 1:]
    k = 0
    while k < len(rest):
        flag = rest[k]
        if flag == "--params-file":
            with open(rest[k + 1]) as stream:
                CONTEXT.overrides.extend(_node_specs(yaml.safe_load(stream) or {}))
            k += 2
        elif flag in ("-p", "--param"):
            name, _, text = rest[k + 1].partition(":=")
            CONTEXT.overrides.append(("/**", {name: yaml.safe_load(text)}))
            k += 2
        else:
            k += 1


def overrides_for(fully_qualified_name: str) -> dict[str, Any]:
    """Parameter overrides that apply to a node: '/**' first, then its exact name."""
    merged: dict[str, Any] = {}
    for spec, parameters in CONTEXT.overrides:
        if spec == "/**":
            merged.update(parameters)
    for spec, parameters in CONTEXT.overrides:
        if spec == fully_qualified_name:
            merged.update(parameters)
    return merged


# --------------------------------------------------------------------------- graph


class Graph:
    """Every publisher, subscription, service and timer of every live stand-in node."""

    def __init__(self) -> None:
        self.subscriptions: dict[str, list[Any]] = {}
        self.publishers: dict[str, list[Any]] = {}
        self.services: dict[str, Any] = {}
        self.timers: list[Any] = []
        self.sequence = 0

    def deliver(self, topic: str, message: Any, published_ns: int | None = None) -> None:
        """Hand ``message`` to every subscription of ``topic`` now, as rclpy's executor would.

        ``published_ns``: when the message was published (its message info's ``source_timestamp``);
        default now. A test that delivers messages late or out of order passes their publication time,
        as DDS reports it; the stand-in clock is the reception time. A ``raw`` subscription gets the
        message's CDR bytes (``message`` may be them already).
        """
        self.sequence += 1
        info = {"source_timestamp": now_ns() if published_ns is None else int(published_ns),
                "received_timestamp": now_ns(), "publication_sequence_number": self.sequence,
                "reception_sequence_number": self.sequence}
        for subscription in list(self.subscriptions.get(topic, ())):
            if not isinstance(message, (subscription.msg_type, bytes)):
                raise TypeError(f"stand-in: {topic} carries {subscription.msg_type.__name__}, "
                                f"got {type(message).__name__}")
            taken = message
            if subscription.raw and not isinstance(message, bytes):
                taken = to_cdr(message)
            elif not subscription.raw and isinstance(message, bytes):
                taken = from_cdr(message, subscription.msg_type)
            if subscription.with_message_info:
                run_to_completion(subscription.callback(taken, dict(info)))
            else:
                run_to_completion(subscription.callback(taken))

    def published(self, topic: str) -> list[Any]:
        """Every message published on ``topic`` (resolved name) so far, in order."""
        return [m for publisher in self.publishers.get(topic, ()) for m in publisher.messages]

    def call(self, name: str, request: Any = None) -> Any:
        """Call a service by resolved name and return its response."""
        service = self.services[name]
        return run_to_completion(service.callback(request if request is not None else service.srv_type.Request(),
                                                  service.srv_type.Response()))


def run_to_completion(result: Any, timeout: float = 60.0) -> Any:
    """A callback's return value; a coroutine (an ``async def`` callback) is resumed until it finishes, as
    rclpy's executor resumes its task, the caller's thread waiting for what it awaits (a worker thread's
    ``rclpy.task.Future``)."""
    if not inspect.iscoroutine(result):
        return result
    deadline = time.monotonic() + timeout
    while True:
        try:
            result.send(None)
        except StopIteration as finished:
            return finished.value
        if time.monotonic() > deadline:
            result.close()
            raise TimeoutError(f"stand-in: a coroutine callback did not finish within {timeout} s")
        time.sleep(0.001)


GRAPH = Graph()


def reset() -> None:
    """Forget every node, the clock and the context (between tests)."""
    GRAPH.__init__()
    _CLOCK_NS[0] = 0
    CONTEXT.__init__()


def resolve(name: str, namespace: str, node_name: str) -> str:
    """ROS name resolution: absolute, private (``~/x``) or relative to the namespace."""
    base = namespace.rstrip("/")
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        return f"{base}/{node_name}{name[1:]}"
    return f"{base}/{name}"
