"""Read a run from a ROS 2 bag (MCAP or sqlite3), matching joints by name.

Messages may list joints in any order or carry extra joints; every failure a
user can cause becomes a one-line :class:`BagError`.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.rosbag2 import Reader

from kvark_ros.core.pairing import JointColumns
from kvark_ros.io.common import (
    FLOAT64_ARRAY,
    JOINT_STATE,
    WRENCH_STAMPED,
    _NS,
    FloatArray,
    PathLike,
    _typestore,
)
from kvark_ros.io.runs import (
    BagError,
    CommandSeries,
    JointStateSeries,
    RecordedRun,
    SIMULATOR_SOURCE,
    SOURCE_KEY,
    TopicNames,
    WrenchSeries,
    _error,
)

__all__ = ["read_run"]


def _resolve(path: PathLike) -> tuple[Path, Path]:
    """Return (path as given, what rosbags should open): bag directory or storage file."""
    given = Path(path)
    if not given.exists():
        raise _error(
            given, "no such bag", "check the path (a rosbag2 bag is a directory with metadata.yaml)"
        )
    if given.is_dir():
        if (given / "metadata.yaml").is_file():
            return given, given
        files = sorted(given.glob("*.mcap")) + sorted(given.glob("*.db3"))
        if len(files) == 1:
            return given, files[0]
        problem = "is not a rosbag2 bag (no metadata.yaml"
        problem += f", {len(files)} storage files)" if files else ", no .mcap or .db3 file)"
        raise _error(
            given,
            problem,
            "pass a bag directory or its .mcap/.db3 file "
            "(`ros2 bag reindex` rebuilds metadata.yaml)",
        )
    if given.name == "metadata.yaml":
        return given, given.parent
    if given.suffix not in (".mcap", ".db3"):
        raise _error(
            given,
            "is not a rosbag2 bag (expected a directory, .mcap or .db3)",
            "pass the bag directory",
        )
    return given, given


def _corrupt(path: Path, exc: BaseException) -> BagError:
    """A read failure inside rosbags: the file is corrupt, truncated or not a bag."""
    if isinstance(exc, PermissionError):
        return _error(path, "cannot read bag (permission denied)", "check the file permissions")
    detail = str(exc) or type(exc).__name__
    is_mcap = any(path.glob("*.mcap")) if path.is_dir() else path.suffix == ".mcap"
    fix = (
        "re-record it, or try `mcap recover` on the .mcap file"
        if is_mcap
        else "re-record or re-export it"
    )
    return _error(path, f"cannot read bag, it is corrupt or truncated ({detail})", fix)


@contextmanager
def _open_reader(path: PathLike) -> Iterator[tuple[Path, Reader]]:
    """Open a bag for reading; every rosbags failure becomes a BagError."""
    given, target = _resolve(path)
    try:
        reader = Reader(target)
        reader.open()
    except BagError:
        raise
    except Exception as exc:  # rosbags raises ReaderError, OSError, sqlite3 and YAML errors
        raise _corrupt(given, exc) from exc
    try:
        yield given, reader
    finally:
        with suppress(Exception):
            reader.close()


def _topic_types(reader: Reader) -> dict[str, set[str]]:
    """topic → set of message types recorded on it."""
    out: dict[str, set[str]] = {}
    for conn in reader.connections:
        out.setdefault(conn.topic, set()).add(conn.msgtype)
    return out


def _describe_topics(types: dict[str, set[str]]) -> str:
    if not types:
        return "the bag has no topics"
    return "the bag has " + ", ".join(
        f"{t} [{'|'.join(sorted(v))}]" for t, v in sorted(types.items())
    )


class _Columns:
    """The run's joints in a message's name list (``core.pairing.JointColumns``); a bag error if a
    configured joint is missing or named twice."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...]) -> None:
        self.path, self.topic, self.wanted = path, topic, wanted
        self._joints = JointColumns(wanted)

    @property
    def seen(self) -> list[tuple[str, ...]]:
        """Distinct joint-name lists met so far."""
        return self._joints.seen

    def index(self, names: Sequence[str]) -> npt.NDArray[np.intp] | None:
        """Indices into the message's arrays; None for a message with none of the joints."""
        idx = self._joints.index(names)
        if not isinstance(idx, str):
            return idx
        missing, key = self._joints.missing, list(names)
        if missing:
            problem = (f"joint {missing[0]!r} is missing from {self.topic}"
                       + (f" (also {missing[1:]})" if len(missing) > 1 else "") + f", whose messages name {key}")
        else:
            problem = f"joint {self._joints.repeated!r} is named twice in a message of {self.topic}: {key}"
        raise _error(self.path, problem, "fix joint_names (or the config) to name joints the bag has")


def _check_matched(path: Path, topic: str, columns: _Columns) -> None:
    """Raise if ``topic`` had messages but none named the run's joints."""
    seen = sorted({n for names in columns.seen for n in names})
    if seen:
        raise _error(
            path,
            f"joints {list(columns.wanted)} are missing from {topic}, whose messages name {seen}",
            "fix joint_names (or the config) to name joints the bag has",
        )


class _Rows:
    """Growable (T, width) float64 buffer; per row a header stamp and a log time (ns)."""

    def __init__(self, width: int, capacity: int) -> None:
        self.width, self.size = width, 0
        self.data = np.empty((max(capacity, 16), width))
        self.ns = np.empty((max(capacity, 16), 2), dtype=np.int64)

    def append(self, ns: int, log_ns: int) -> FloatArray:
        """Reserve a row stamped ``ns`` (logged at ``log_ns``) and return it to be filled."""
        if self.size == self.ns.shape[0]:
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
            self.ns = np.concatenate([self.ns, np.empty_like(self.ns)])
        self.ns[self.size] = ns, log_ns
        self.size += 1
        row: FloatArray = self.data[self.size - 1]
        return row

    def sorted(self) -> tuple[FloatArray, FloatArray]:
        """(stamps in s, rows), stably sorted by stamp.

        Header stamps that are all zero (a driver that never fills them) are
        replaced by the bag log time, so time steps stay meaningful.
        """
        ns, data = self.ns[: self.size, 0], self.data[: self.size]
        if not ns.any():
            ns = self.ns[: self.size, 1]
        order = np.argsort(ns, kind="stable")
        return ns[order].astype(np.float64) / 1e9, data[order]


class _JointStates:
    """Accumulates JointState messages into a JointStateSeries (position|velocity|effort)."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...], capacity: int) -> None:
        self.path, self.topic, self.n = path, topic, len(wanted)
        self.columns = _Columns(path, topic, wanted)
        self.rows = _Rows(3 * self.n, capacity)

    def add(self, msg: Any, log_ns: int) -> None:
        idx = self.columns.index(msg.name)
        if idx is None:
            return
        stamp = msg.header.stamp
        row = self.rows.append(stamp.sec * _NS + stamp.nanosec, log_ns)
        count = len(msg.name)
        for k, values in enumerate((msg.position, msg.velocity, msg.effort)):
            block = row[k * self.n : (k + 1) * self.n]
            if len(values) == count:
                block[:] = values[idx]
            elif len(values) == 0:
                block[:] = np.nan
            else:
                field_name = ("position", "velocity", "effort")[k]
                raise _error(
                    self.path,
                    f"malformed message on {self.topic}: "
                    f"{len(values)} {field_name} values for {count} names",
                    "re-record with a driver that fills JointState consistently",
                )

    def result(self, names: tuple[str, ...]) -> JointStateSeries | None:
        if self.rows.size == 0:
            _check_matched(self.path, self.topic, self.columns)
            return None
        stamp, data = self.rows.sorted()
        n = self.n
        return JointStateSeries(stamp, names, data[:, :n], data[:, n : 2 * n], data[:, 2 * n :])


class _Commands:
    """Accumulates Float64MultiArray (or JointState effort) commands in run order."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...], capacity: int) -> None:
        self.path, self.topic, self.wanted = path, topic, wanted
        self.columns = _Columns(path, topic, wanted)
        self.rows = _Rows(len(wanted), capacity)

    def add(self, msg: Any, log_ns: int) -> None:
        if hasattr(msg, "layout"):
            self._add_array(msg, log_ns)
            return
        idx = self.columns.index(msg.name)
        if idx is None:
            return
        if len(msg.effort) != len(msg.name):
            raise _error(
                self.path,
                f"JointState on {self.topic} has {len(msg.effort)} effort values "
                f"for {len(msg.name)} names",
                "publish the commanded torque in the effort field",
            )
        self.rows.append(log_ns, log_ns)[:] = msg.effort[idx]

    def _add_array(self, msg: Any, log_ns: int) -> None:
        data = msg.data
        dims = msg.layout.dim
        if (
            len(dims) == 1
            and dims[0].label
            and len(labels := dims[0].label.split(",")) == len(data)
        ):
            idx = self.columns.index(labels)
            if idx is not None:  # None: commands for other joints; checked in result()
                self.rows.append(log_ns, log_ns)[:] = data[idx]
        elif len(data) == len(self.wanted):
            self.rows.append(log_ns, log_ns)[:] = data
        else:
            raise _error(
                self.path,
                f"{self.topic} has {len(data)} values but the run has "
                f"{len(self.wanted)} joints {list(self.wanted)}",
                "pass joint_names in the effort controller's joint order",
            )

    def result(self) -> CommandSeries | None:
        if self.rows.size == 0:
            _check_matched(self.path, self.topic, self.columns)
            return None
        stamp, data = self.rows.sorted()
        return CommandSeries(stamp, data)


class _Wrenches:
    """Accumulates WrenchStamped messages; all must share one frame_id."""

    def __init__(self, path: Path, topic: str, capacity: int) -> None:
        self.path, self.topic = path, topic
        self.frame_id: str | None = None
        self.rows = _Rows(6, capacity)

    def add(self, msg: Any, log_ns: int) -> None:
        frame = msg.header.frame_id
        if self.frame_id is None:
            self.frame_id = frame
        elif frame != self.frame_id:
            raise _error(
                self.path,
                f"{self.topic} mixes frames {self.frame_id!r} and {frame!r}",
                "split the topic or re-record in one frame",
            )
        stamp = msg.header.stamp
        row = self.rows.append(stamp.sec * _NS + stamp.nanosec, log_ns)
        f, t = msg.wrench.force, msg.wrench.torque
        row[:] = (f.x, f.y, f.z, t.x, t.y, t.z)

    def result(self) -> WrenchSeries | None:
        if self.rows.size == 0:
            return None
        stamp, data = self.rows.sorted()
        return WrenchSeries(stamp, self.frame_id or "", data[:, :3], data[:, 3:])


def _check_type(path: Path, topic: str, found: set[str], allowed: set[str]) -> None:
    if not found <= allowed:
        raise _error(
            path,
            f"topic {topic} has type {'|'.join(sorted(found))}, "
            f"expected {' or '.join(sorted(allowed))}",
            "record the joint states as sensor_msgs/msg/JointState on that topic (remap when recording)",
        )


def _stream(
    path: Path, reader: Reader, conns: list[Any]
) -> Generator[tuple[Any, int, Any], None, None]:
    """Yield (connection, log time ns, decoded message); decoding errors become BagError."""
    store = _typestore()
    it = iter(reader.messages(connections=conns))
    while True:
        try:
            conn, log_ns, raw = next(it)
            msg = store.deserialize_cdr(raw, conn.msgtype)
        except StopIteration:
            return
        except Exception as exc:  # ReaderError, SerdeError, sqlite3 errors, decompression errors
            raise _corrupt(path, exc) from exc
        yield conn, log_ns, msg


def read_run(
    path: PathLike,
    joint_names: Sequence[str] | None = None,
    topics: TopicNames = TopicNames(),
) -> RecordedRun:
    """Read a run from a bag directory (or its .mcap/.db3 file), sorted by stamp.

    ``joint_names`` fixes the column order and selects joints by name (messages
    may list joints in any order, or extra joints such as fingers); without it
    the first /joint_states message decides. Messages naming none of the joints
    (another publisher on the topic) are skipped; a missing joint is a BagError.
    Unlabelled Float64MultiArray commands are taken to be in ``joint_names``
    order. Optional topics that are absent or empty read as None. Header
    stamps that are all zero fall back to the bag log time. ``source`` is the
    bag metadata's ``kvark_ros.source``; a bag without it that records the true
    external torque is taken to come from the simulator (a robot cannot measure it).
    """
    wanted = None if joint_names is None else tuple(str(n) for n in joint_names)
    if wanted is not None and (not wanted or len(set(wanted)) != len(wanted)):
        raise _error(path, f"joint_names {list(wanted)} are empty or repeat", "fix the config")
    with _open_reader(path) as (given, reader):
        types = _topic_types(reader)
        custom = getattr(getattr(getattr(reader, "storage", None), "metadata", None), "custom", None) or {}
        source = str(custom.get(SOURCE_KEY, ""))
        if topics.joint_states not in types:
            raise _error(
                given,
                f"topic {topics.joint_states} is absent ({_describe_topics(types)})",
                "record the joint states on /joint_states (remap the topic when recording)",
            )
        _check_type(given, topics.joint_states, types[topics.joint_states], {JOINT_STATE})
        optional = {
            topics.effort_commands: {FLOAT64_ARRAY, JOINT_STATE},
            topics.wrench: {WRENCH_STAMPED},
            topics.external_torque: {JOINT_STATE},
        }
        for topic, allowed in optional.items():
            if topic in types:
                _check_type(given, topic, types[topic], allowed)

        by_topic: dict[str, list[Any]] = {}
        for conn in reader.connections:
            by_topic.setdefault(conn.topic, []).append(conn)

        def count(topic: str) -> int:
            return sum(c.msgcount for c in by_topic.get(topic, []))

        js_conns = by_topic[topics.joint_states]
        if wanted is None:
            peek = _stream(given, reader, js_conns)
            first = next(peek, None)
            peek.close()
            if first is None:
                raise _error(
                    given,
                    f"topic {topics.joint_states} has no messages",
                    "record joint states in the bag",
                )
            wanted = tuple(first[2].name)

        handlers: dict[str, _JointStates | _Commands | _Wrenches] = {
            topics.joint_states: _JointStates(
                given, topics.joint_states, wanted, count(topics.joint_states)
            ),
        }
        if topics.effort_commands in by_topic:
            handlers[topics.effort_commands] = _Commands(
                given, topics.effort_commands, wanted, count(topics.effort_commands)
            )
        if topics.wrench in by_topic:
            handlers[topics.wrench] = _Wrenches(given, topics.wrench, count(topics.wrench))
        if topics.external_torque in by_topic:
            handlers[topics.external_torque] = _JointStates(
                given, topics.external_torque, wanted, count(topics.external_torque)
            )

        conns = [c for topic in handlers for c in by_topic[topic]]
        dispatch: dict[str, Callable[[Any, int], None]] = {t: h.add for t, h in handlers.items()}
        for conn, log_ns, msg in _stream(given, reader, conns):
            dispatch[conn.topic](msg, log_ns)

    js_handler = handlers[topics.joint_states]
    assert isinstance(js_handler, _JointStates)
    joint_states = js_handler.result(wanted)
    if joint_states is None:
        raise _error(
            given, f"topic {topics.joint_states} has no messages", "record joint states in the bag"
        )
    cmd = handlers.get(topics.effort_commands)
    wr = handlers.get(topics.wrench)
    ext = handlers.get(topics.external_torque)
    return RecordedRun(
        joint_states=joint_states,
        commands=cmd.result() if isinstance(cmd, _Commands) else None,
        wrench=wr.result() if isinstance(wr, _Wrenches) else None,
        external_torque=ext.result(wanted) if isinstance(ext, _JointStates) else None,
        source=source or (f"{SIMULATOR_SOURCE} (inferred: {topics.external_torque} recorded)"
                          if isinstance(ext, _JointStates) else ""),
    )
