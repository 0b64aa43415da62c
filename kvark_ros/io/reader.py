"""Read a run from a ROS 2 bag (MCAP or sqlite3), matching joints by name.

Messages may list joints in any order or carry extra joints; every failure a
user can cause becomes a one-line :class:`BagError`.

Messages are read undecoded, all at once (a bag that is one MCAP file through its
message indexes, ``mcap_bulk``; any other through rosbags), then decoded a topic at
a time in groups of messages that share a layout (``cdr_arrays``). The result, and
the error raised for a bad bag, are what decoding them one by one with rosbags in
read order gives (test/io/test_bulk_read_write.py).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.storage_mcap import McapReader

from kvark_ros.core.estimation.pairing import JointColumns
from kvark_ros.io.cdr_arrays import Layout, message_fields, windows
from kvark_ros.io.common import (
    FLOAT64_ARRAY,
    JOINT_STATE,
    NS_PER_SECOND,
    WRENCH_STAMPED,
    FloatArray,
    PathLike,
    typestore,
)
from kvark_ros.io.mcap_bulk import RawMessages, indexed_messages
from kvark_ros.io.runs import (
    BagError,
    CommandSeries,
    JointStateSeries,
    RecordedRun,
    SIMULATOR_SOURCE,
    SOURCE_KEY,
    TopicNames,
    WrenchSeries,
    bag_error,
)
from kvark_ros.io.topic_hints import missing_topic

__all__ = ["read_run"]

MAX_LAYOUTS = 8  # layouts per topic decoded in bulk; messages of further layouts are decoded one by one
Index = npt.NDArray[np.intp]
Int64s = npt.NDArray[np.int64]
Fields = dict[str, npt.NDArray[Any]]


def resolve_bag(path: PathLike) -> tuple[Path, Path]:
    """Return (path as given, what rosbags should open): bag directory or storage file."""
    given = Path(path)
    if not given.exists():
        raise bag_error(
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
        raise bag_error(
            given,
            problem,
            "pass a bag directory or its .mcap/.db3 file "
            "(`ros2 bag reindex` rebuilds metadata.yaml)",
        )
    if given.name == "metadata.yaml":
        return given, given.parent
    if given.suffix not in (".mcap", ".db3"):
        raise bag_error(
            given,
            "is not a rosbag2 bag (expected a directory, .mcap or .db3)",
            "pass the bag directory",
        )
    return given, given


def _corrupt(path: Path, exc: BaseException) -> BagError:
    """A read failure inside rosbags: the file is corrupt, truncated or not a bag."""
    if isinstance(exc, PermissionError):
        return bag_error(path, "cannot read bag (permission denied)", "check the file permissions")
    detail = str(exc) or type(exc).__name__
    is_mcap = any(path.glob("*.mcap")) if path.is_dir() else path.suffix == ".mcap"
    fix = (
        "re-record it, or try `mcap recover` on the .mcap file"
        if is_mcap
        else "re-record or re-export it"
    )
    return bag_error(path, f"cannot read bag, it is corrupt or truncated ({detail})", fix)


@contextmanager
def open_reader(path: PathLike) -> Iterator[tuple[Path, Reader]]:
    """Open a bag for reading; every rosbags failure becomes a BagError."""
    given, target = resolve_bag(path)
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


class _Columns:
    """The run's joints in a message's name list (``core.estimation.pairing.JointColumns``); a bag error if a
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
        raise bag_error(self.path, problem, "fix joint_names (or the config) to name joints the bag has")


def _check_matched(path: Path, topic: str, columns: _Columns) -> None:
    """Raise if ``topic`` had messages but none named the run's joints."""
    seen = sorted({n for names in columns.seen for n in names})
    if seen:
        raise bag_error(
            path,
            f"joints {list(columns.wanted)} are missing from {topic}, whose messages name {seen}",
            "fix joint_names (or the config) to name joints the bag has",
        )


class _Rows:
    """Rows of one topic's messages in read order: numbers (m, width), header stamp and log time (ns), and
    whether a message counts (one naming none of the run's joints does not)."""

    def __init__(self, width: int, count: int) -> None:
        self.data = np.empty((count, width))
        self.ns = np.zeros((count, 2), dtype=np.int64)
        self.kept = np.zeros(count, dtype=bool)

    def fill(self, members: Index, stamp_ns: Int64s, log_ns: Int64s, data: FloatArray) -> None:
        """Rows ``members`` (ascending; stamped ``stamp_ns``, logged at ``log_ns``) hold ``data`` and count."""
        rows: Index | slice = members
        if len(members) and members[-1] - members[0] == len(members) - 1:      # a range: copy without an index
            rows = slice(int(members[0]), int(members[-1]) + 1)
        self.data[rows], self.ns[rows, 0], self.ns[rows, 1] = data, stamp_ns, log_ns
        self.kept[rows] = True

    def sorted(self) -> tuple[FloatArray, FloatArray] | None:
        """(stamps in s, rows) of the rows that count, stably sorted by stamp; None if none counts.

        Header stamps that are all zero (a driver that never fills them) are
        replaced by the bag log time, so time steps stay meaningful.
        """
        if not self.kept.any():
            return None
        ns, data = (self.ns, self.data) if self.kept.all() else (self.ns[self.kept], self.data[self.kept])
        stamp = ns[:, 0] if ns[:, 0].any() else ns[:, 1]
        if np.any(stamp[1:] < stamp[:-1]):
            order = np.argsort(stamp, kind="stable")
            stamp, data = stamp[order], data[order]
        return stamp.astype(np.float64) / 1e9, data


def _columns(values: FloatArray, idx: Index) -> FloatArray:
    """``values[:, idx]``, without a copy when ``idx`` takes every column in order."""
    return values if np.array_equal(idx, np.arange(values.shape[1])) else values[:, idx]


def _stamp_ns(values: Fields) -> Int64s:
    """Header stamps in integer nanoseconds."""
    return values["sec"][:, 0].astype(np.int64) * NS_PER_SECOND + values["nanosec"][:, 0]


class _JointStates:
    """JointState messages → a JointStateSeries (position|velocity|effort)."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...], count: int) -> None:
        self.path, self.topic, self.n = path, topic, len(wanted)
        self.columns = _Columns(path, topic, wanted)
        self.rows = _Rows(3 * self.n, count)

    def add(self, msg: Any, values: Fields, members: Index, log_ns: Int64s) -> None:
        """Messages ``members`` share ``msg``'s layout (names, array lengths); ``values`` their numbers."""
        idx = self.columns.index(msg.name)
        if idx is None:
            return
        count, n = len(msg.name), self.n
        data = np.empty((len(members), 3 * n))
        for k, field_name in enumerate(("position", "velocity", "effort")):
            found = values[field_name]
            if found.shape[1] == count:
                data[:, k * n:(k + 1) * n] = _columns(found, idx)
            elif found.shape[1] == 0:
                data[:, k * n:(k + 1) * n] = np.nan
            else:
                raise bag_error(
                    self.path,
                    f"malformed message on {self.topic}: "
                    f"{found.shape[1]} {field_name} values for {count} names",
                    "re-record with a driver that fills JointState consistently",
                )
        self.rows.fill(members, _stamp_ns(values), log_ns, data)

    def result(self, names: tuple[str, ...]) -> JointStateSeries | None:
        found = self.rows.sorted()
        if found is None:
            _check_matched(self.path, self.topic, self.columns)
            return None
        stamp, data = found
        n = self.n
        return JointStateSeries(stamp, names, data[:, :n], data[:, n : 2 * n], data[:, 2 * n :])


class _Commands:
    """Float64MultiArray (or JointState effort) commands in run order, stamped with their log time."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...], count: int) -> None:
        self.path, self.topic, self.wanted = path, topic, wanted
        self.columns = _Columns(path, topic, wanted)
        self.rows = _Rows(len(wanted), count)

    def add(self, msg: Any, values: Fields, members: Index, log_ns: Int64s) -> None:
        """Messages ``members`` share ``msg``'s layout (labels or names, lengths); ``values`` their numbers."""
        if hasattr(msg, "layout"):
            self._add_array(msg, values["data"], members, log_ns)
            return
        idx = self.columns.index(msg.name)
        if idx is None:
            return
        if len(msg.effort) != len(msg.name):
            raise bag_error(
                self.path,
                f"JointState on {self.topic} has {len(msg.effort)} effort values "
                f"for {len(msg.name)} names",
                "publish the commanded torque in the effort field",
            )
        self.rows.fill(members, log_ns, log_ns, _columns(values["effort"], idx))

    def _add_array(self, msg: Any, data: FloatArray, members: Index, log_ns: Int64s) -> None:
        dims = msg.layout.dim
        if (
            len(dims) == 1
            and dims[0].label
            and len(labels := dims[0].label.split(",")) == data.shape[1]
        ):
            idx = self.columns.index(labels)
            if idx is not None:  # None: commands for other joints; checked in result()
                self.rows.fill(members, log_ns, log_ns, _columns(data, idx))
        elif data.shape[1] == len(self.wanted):
            self.rows.fill(members, log_ns, log_ns, data)
        else:
            raise bag_error(
                self.path,
                f"{self.topic} has {data.shape[1]} values but the run has "
                f"{len(self.wanted)} joints {list(self.wanted)}",
                "pass joint_names in the effort controller's joint order",
            )

    def result(self) -> CommandSeries | None:
        found = self.rows.sorted()
        if found is None:
            _check_matched(self.path, self.topic, self.columns)
            return None
        return CommandSeries(*found)


class _Wrenches:
    """WrenchStamped messages; all must share one frame_id."""

    def __init__(self, path: Path, topic: str, count: int) -> None:
        self.path, self.topic = path, topic
        self.frame_id: str | None = None
        self.rows = _Rows(6, count)

    def add(self, msg: Any, values: Fields, members: Index, log_ns: Int64s) -> None:
        """Messages ``members`` share ``msg``'s layout (frame_id); ``values`` their numbers."""
        frame = msg.header.frame_id
        if self.frame_id is None:
            self.frame_id = frame
        elif frame != self.frame_id:
            raise bag_error(
                self.path,
                f"{self.topic} mixes frames {self.frame_id!r} and {frame!r}",
                "split the topic or re-record in one frame",
            )
        self.rows.fill(members, _stamp_ns(values), log_ns, values["wrench"])

    def result(self) -> WrenchSeries | None:
        found = self.rows.sorted()
        if found is None:
            return None
        stamp, data = found
        return WrenchSeries(stamp, self.frame_id or "", data[:, :3], data[:, 3:])


_Handler = _JointStates | _Commands | _Wrenches


class _Failure(Exception):
    """A BagError met at message ``rank`` of the read order (the earliest one is raised)."""

    def __init__(self, rank: int, error: BagError) -> None:
        super().__init__(str(error))
        self.rank, self.error = rank, error


def _check_type(path: Path, topic: str, found: set[str], allowed: set[str]) -> None:
    if not found <= allowed:
        raise bag_error(
            path,
            f"topic {topic} has type {'|'.join(sorted(found))}, "
            f"expected {' or '.join(sorted(allowed))}",
            "record the joint states as sensor_msgs/msg/JointState on that topic (remap when recording)",
        )


def _indexed(reader: Reader, conns: list[Any]) -> tuple[RawMessages, dict[int, Any]] | None:
    """``conns``' messages read in bulk (``mcap_bulk.indexed_messages``) from a bag that is one MCAP file
    without per-message compression, and channel id → connection; None for any other bag."""
    storage = reader.storage
    if isinstance(storage, McapReader):
        mcap, by_id = storage, {conn.id: conn for conn in conns}
    else:
        storages = getattr(storage, "storages", [])
        if len(storages) != 1 or not isinstance(storages[0], McapReader) or reader.compression_mode == "message":
            return None
        mcap = storages[0]
        # the storage's channels that rosbags' directory reader maps onto ``conns``
        by_id = {}
        for channel in mcap.connections:
            same = [conn for conn in conns if conn.topic == channel.topic and conn.msgtype == channel.msgtype
                    and conn.ext == channel.ext and (not channel.digest or not conn.digest
                                                     or conn.digest == channel.digest)]
            if same:
                by_id[channel.id] = same[0]
    if not mcap.chunks:
        return None
    try:
        raw = indexed_messages(Path(mcap.path), mcap.chunks, by_id)
    except (IndexError, ValueError, OverflowError, MemoryError):   # a corrupt index or chunk: rosbags reads it
        return None                                                  # record by record, and names what is wrong
    return None if raw is None else (raw, by_id)


def _raw_messages(path: Path, reader: Reader, conns: list[Any]) -> tuple[RawMessages, dict[int, Any], list[_Failure]]:
    """Every message of ``conns`` undecoded, in read order; channel id → connection; and a read error met
    after the messages returned (as a failure ranked after them)."""
    found = _indexed(reader, conns)
    if found is not None:
        return (*found, [])
    parts, log_ns, ids = [], [], []
    failures = []
    try:
        for conn, stamp, data in reader.messages(connections=conns):
            parts.append(data)
            log_ns.append(stamp)
            ids.append(conn.id)
    except Exception as exc:  # ReaderError, sqlite3 errors, decompression errors
        failures.append(_Failure(len(parts), _corrupt(path, exc)))
    size = np.array([len(part) for part in parts], dtype=np.int64)
    raw = RawMessages.join(parts, np.cumsum(size) - size, size, np.array(log_ns, dtype=np.int64),
                           np.array(ids, dtype=np.int64))
    return raw, {conn.id: conn for conn in conns}, failures


def _by_topic(raw: RawMessages, by_id: dict[int, Any], names: set[str]
              ) -> tuple[dict[str, Index], dict[str, Index], dict[str, list[str]]]:
    """Per topic: its messages (indices into ``raw``, read order), the index of each one's message type in
    the topic's list of types, and that list."""
    rows, kinds, msgtypes = {}, {}, {}
    for topic in names:
        ids = {cid: conn.msgtype for cid, conn in by_id.items() if conn.topic == topic}
        rows[topic] = np.flatnonzero(np.isin(raw.channel, list(ids)))
        msgtypes[topic] = sorted(set(ids.values()))
        channel_ids = np.array(sorted(ids), dtype=np.int64)
        type_of = np.array([msgtypes[topic].index(ids[cid]) for cid in channel_ids], dtype=np.intp)
        kinds[topic] = type_of[np.searchsorted(channel_ids, raw.channel[rows[topic]])]
    return rows, kinds, msgtypes


def _feed(path: Path, raw: RawMessages, rows: Index, kinds: Index, msgtypes: list[str], handler: _Handler) -> None:
    """Decode one topic's messages ``rows`` (read order; type ``msgtypes[kinds[k]]``) and hand them to ``handler``
    in groups of one layout (``cdr_arrays``), taken in the order of their first messages: rosbags decodes
    each group's first message, the rest of the group is decoded in bulk. The first ``MAX_LAYOUTS`` layouts
    are grouped; messages of further ones are decoded one by one. Errors are raised as ``_Failure``."""
    store = typestore()
    size, log_ns = raw.size[rows], raw.log_ns[rows]

    def decode(k: int) -> tuple[bytes, str, Any]:
        data, msgtype = raw.message(int(rows[k])), msgtypes[kinds[k]]
        try:
            return data, msgtype, store.deserialize_cdr(data, msgtype)
        except Exception as exc:  # SerdeError
            raise _Failure(int(rows[k]), _corrupt(path, exc)) from exc

    def hand(k: int, msg: Any, values: Fields, members: Index) -> None:
        try:
            handler.add(msg, values, members, log_ns[members])
        except BagError as exc:
            raise _Failure(int(rows[k]), exc) from exc

    pending = np.ones(len(rows), dtype=bool)
    for _ in range(MAX_LAYOUTS):
        rest = np.flatnonzero(pending)
        if not rest.size:
            return
        first = int(rest[0])
        data, msgtype, msg = decode(first)
        layout = Layout.read(data, msgtype, msg)
        members, values = rest[:1], message_fields(msg, msgtype)
        if layout is not None:
            same = rest[(size[rest] == layout.size) & (kinds[rest] == kinds[first])]
            block = windows(raw.buffer, raw.start[rows[same]], layout.width)
            match = layout.matches(block)
            members, values = same[match], layout.decode(block[match])
        hand(first, msg, values, members)
        pending[members] = False
    for k in np.flatnonzero(pending):
        data, msgtype, msg = decode(int(k))
        hand(int(k), msg, message_fields(msg, msgtype), np.array([k]))


def _first_names(path: Path, raw: RawMessages, rows: Index, failures: list[_Failure], topic: str) -> tuple[str, ...]:
    """The joint names of the first joint state; a read error met before it, or none, is a BagError."""
    if not len(rows) or any(failure.rank < rows[0] for failure in failures):
        if failures:
            raise min(failures, key=lambda failure: failure.rank).error
        raise bag_error(path, f"topic {topic} has no messages", "record joint states in the bag")
    try:
        return tuple(typestore().deserialize_cdr(raw.message(int(rows[0])), JOINT_STATE).name)
    except Exception as exc:  # SerdeError
        raise _corrupt(path, exc) from exc


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
        raise bag_error(path, f"joint_names {list(wanted)} are empty or repeat", "fix the config")
    with open_reader(path) as (given, reader):
        types = _topic_types(reader)
        custom = getattr(getattr(getattr(reader, "storage", None), "metadata", None), "custom", None) or {}
        source = str(custom.get(SOURCE_KEY, ""))
        if topics.joint_states not in types:
            raise missing_topic(given, f"topic {topics.joint_states} (input.joint_states_topic) is absent",
                                topics.joint_states, "input.joint_states_topic", types, {JOINT_STATE})
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

        conns = [c for topic in (topics.joint_states, *optional) if topic in by_topic for c in by_topic[topic]]
        raw, by_id, failures = _raw_messages(given, reader, conns)

    rows, kinds, msgtypes = _by_topic(raw, by_id, {conn.topic for conn in conns})
    if wanted is None:  # the first joint state names the joints
        wanted = _first_names(given, raw, rows[topics.joint_states], failures, topics.joint_states)

    def count(topic: str) -> int:
        return len(rows[topic])

    handlers: dict[str, _Handler] = {
        topics.joint_states: _JointStates(given, topics.joint_states, wanted, count(topics.joint_states)),
    }
    if topics.effort_commands in rows:
        handlers[topics.effort_commands] = _Commands(
            given, topics.effort_commands, wanted, count(topics.effort_commands)
        )
    if topics.wrench in rows:
        handlers[topics.wrench] = _Wrenches(given, topics.wrench, count(topics.wrench))
    if topics.external_torque in rows:
        handlers[topics.external_torque] = _JointStates(
            given, topics.external_torque, wanted, count(topics.external_torque)
        )
    for topic, handler in handlers.items():
        try:
            _feed(given, raw, rows[topic], kinds[topic], msgtypes[topic], handler)
        except _Failure as failure:
            failures.append(failure)
    if failures:  # the error a message-by-message read would have met first
        raise min(failures, key=lambda failure: failure.rank).error

    js_handler = handlers[topics.joint_states]
    assert isinstance(js_handler, _JointStates)
    joint_states = js_handler.result(wanted)
    if joint_states is None:
        raise bag_error(
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
