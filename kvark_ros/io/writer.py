"""Write runs and estimator outputs as ROS 2 bags (MCAP or sqlite3), atomically.

Stamps are stored in a bag as integer nanoseconds, so a stamp ``t`` survives a
write/read round trip bit for bit when ``t == round(t * 1e9) / 1e9`` (stamps
built as ``ns / 1e9``); others are rounded to the nearest nanosecond.

Messages are serialised a topic at a time (:class:`Messages`): rosbags serialises
the first, and the others are copies of it with their own numbers
(``cdr_arrays.Layout``); MCAP bags are written in bulk by ``mcap_bulk.McapStorage``.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer

from kvark_ros.core.files import check_output, replace_path
from kvark_ros.io.common import (
    BOOL,
    FLOAT64_ARRAY,
    JOINT_STATE,
    NS_PER_SECOND,
    WRENCH_STAMPED,
    FloatArray,
    PathLike,
    typestore,
)
from kvark_ros.io.cdr_arrays import Layout
from kvark_ros.io.mcap_bulk import McapStorage
from kvark_ros.io.runs import SOURCE_KEY, RecordedRun, TopicNames, bag_error

__all__ = ["BagWriter", "Messages", "bool_messages", "float64_array_messages", "joint_state_messages",
           "wrench_messages", "write_run", "write_run_messages"]

Index = npt.NDArray[np.intp]

_STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


class _Writer(Writer):
    """rosbags' bag writer with MCAP written in bulk (``mcap_bulk.McapStorage``)."""

    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: McapStorage}
_BAG_VERSION: Literal[9] = 9  # rosbag2 metadata version written by Jazzy


def _float_vector(value: Any, size: int | None, what: str) -> FloatArray:
    """Coerce to a 1-D float64 array of the given size (None: any size)."""
    arr = np.array(value, dtype=np.float64, copy=True).reshape(-1)
    if size is not None and arr.shape[0] != size:
        raise ValueError(f"{what} has {arr.shape[0]} values, expected {size}")
    return arr


def _parse_storage(storage: str, path: Path) -> StoragePlugin:
    """Map 'mcap' / 'sqlite3' to the rosbags plugin."""
    try:
        return _STORAGES[storage.lower()]
    except (KeyError, AttributeError):
        raise bag_error(
            path, f"unknown bag storage {storage!r}", f"use one of {sorted(_STORAGES)}"
        ) from None


class BagWriter:
    """Write a rosbag2 bag atomically; use as a context manager.

    Messages go into a temporary sibling directory that is renamed to ``path``
    only when the block exits without an exception, so a failed or interrupted
    write never leaves a partial bag at ``path``. ``path`` follows every command's
    output rule (``kvark_ros.core.files.check_output``): new or an empty directory,
    else replaced whole only with ``force``. Stamps are seconds; for messages with
    a header the header stamp is also the bag log time.
    """

    def __init__(self, path: PathLike, storage: str = "mcap", force: bool = False, source: str = "") -> None:
        self.path = Path(path)
        self.source = source          # metadata custom_data kvark_ros.source ("" = none): what wrote the bag
        self._plugin = _parse_storage(storage, self.path)
        self.force = force
        check_output(self.path, force)
        self._tmpdir: Path | None = None
        self._writer: Writer | None = None
        self._connections: dict[str, tuple[str, Any]] = {}

    # -- lifecycle

    def open(self) -> BagWriter:
        """Start writing into a temporary directory next to ``path``."""
        if self._writer is not None:
            raise RuntimeError("BagWriter is already open")
        check_output(self.path, self.force)
        parent = self.path.absolute().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=parent))
        except OSError as exc:
            raise bag_error(
                self.path,
                f"cannot create output ({exc.strerror})",
                "check the directory and permissions",
            ) from exc
        # The bag directory inside tmpdir has the final name, so the storage
        # file is '<name>.mcap' / '<name>.db3' as ros2 bag tools expect.
        writer = _Writer(tmpdir / self.path.name, version=_BAG_VERSION, storage_plugin=self._plugin)
        if self.source:
            writer.set_custom_data(SOURCE_KEY, self.source)
        try:
            writer.open()
        except BaseException:
            shutil.rmtree(tmpdir, ignore_errors=True)
            raise
        self._tmpdir, self._writer = tmpdir, writer
        return self

    def close(self) -> None:
        """Finish the bag and move it to ``path`` (replacing it only with force=True)."""
        writer, tmpdir = self._require_open(), self._tmpdir
        assert tmpdir is not None
        try:
            writer.close()
            check_output(self.path, self.force)            # an output that appeared while writing
            replace_path(tmpdir / self.path.name, self.path)
        except BaseException:
            self._discard()
            raise
        self._writer = None
        shutil.rmtree(tmpdir, ignore_errors=True)
        self._tmpdir = None

    def abort(self) -> None:
        """Drop everything written so far; ``path`` is left untouched."""
        self._discard()

    def _discard(self) -> None:
        writer, tmpdir = self._writer, self._tmpdir
        self._writer, self._tmpdir = None, None
        if writer is not None:
            with suppress(Exception):
                writer.abort()
        if tmpdir is not None:
            shutil.rmtree(tmpdir, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._writer is None:
            return
        if exc_type is None:
            self.close()
        else:
            self._discard()

    # -- messages

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise RuntimeError("BagWriter is not open; use it as a context manager")
        return self._writer

    def _connection(self, topic: str, msgtype: str) -> Connection:
        """The connection of ``topic`` (added at first use); a topic carries one message type."""
        entry = self._connections.get(topic)
        if entry is None:
            conn = self._require_open().add_connection(topic, msgtype, typestore=typestore())
            entry = self._connections[topic] = (msgtype, conn)
        elif entry[0] != msgtype:
            raise ValueError(f"topic {topic} already carries {entry[0]}, cannot write {msgtype}")
        return entry[1]

    def write_messages(self, blocks: Sequence[Messages], which: Index, row: Index) -> None:
        """Write message ``row[k]`` of ``blocks[which[k]]`` for every k, in that order (each at its log time).

        A topic's connection is added just before its first message, as writing one by one would."""
        self._require_open()
        offsets = np.cumsum([0] + [len(block.log_ns) for block in blocks])[:-1]
        log_ns = np.concatenate([block.log_ns for block in blocks])[offsets[which] + row]
        ids = np.zeros(len(blocks), dtype=np.int64)
        starts = sorted(int(np.argmax(mask)) for mask in (which == k for k in range(len(blocks))) if mask.any())
        for start, end in zip(starts, [*starts[1:], len(which)]):
            block = blocks[which[start]]
            ids[which[start]] = self._connection(block.topic, block.msgtype).id
            self._write_part(blocks, ids, which[start:end], row[start:end], log_ns[start:end])

    def _write_part(self, blocks: Sequence[Messages], ids: npt.NDArray[np.int64], which: Index, row: Index,
                    log_ns: npt.NDArray[np.int64]) -> None:
        """``write_messages`` once the connections are added (``ids``: connection id per block)."""
        writer = self._require_open()
        if not isinstance(writer.storage, McapStorage):        # sqlite3: rosbags writes one at a time
            conns = {conn.id: conn for conn in writer.connections}
            for block, k, ns in zip(which.tolist(), row.tolist(), log_ns.tolist()):
                writer.write(conns[ids[block]], ns, blocks[block].data[k].tobytes())
            return
        writer.storage.write_many(ids[which], log_ns, [block.data for block in blocks], which, row)
        for block, count in zip(*np.unique(which, return_counts=True)):     # what rosbags' Writer.write counts
            writer.counts[int(ids[block])] += int(count)
        writer.min_timestamp = min(writer.min_timestamp, int(log_ns.min()))
        writer.max_timestamp = max(writer.max_timestamp, int(log_ns.max()))

    def write_block(self, block: Messages) -> None:
        """Write ``block``'s messages in row order."""
        self.write_messages([block], np.zeros(len(block.log_ns), dtype=np.intp), np.arange(len(block.log_ns)))

    def joint_state(
        self,
        topic: str,
        stamp: float,
        names: Sequence[str],
        position: Any = None,
        velocity: Any = None,
        effort: Any = None,
    ) -> None:
        """Write a sensor_msgs/JointState; a field left None is written empty (ROS convention)."""
        fields = [None if value is None else _float_vector(value, len(names), f"{topic} {key}")[None]
                  for key, value in (("position", position), ("velocity", velocity), ("effort", effort))]
        self.write_block(joint_state_messages(topic, np.array([stamp], dtype=float), names, *fields))

    def wrench(self, topic: str, stamp: float, frame_id: str, force: Any, torque: Any) -> None:
        """Write a geometry_msgs/WrenchStamped: force (3,) N, torque (3,) N·m in frame_id."""
        f = _float_vector(force, 3, f"{topic} force")
        t = _float_vector(torque, 3, f"{topic} torque")
        self.write_block(wrench_messages(topic, np.array([stamp], dtype=float), frame_id, f[None], t[None]))

    def float64_array(
        self, topic: str, stamp: float, data: Any, names: Sequence[str] | None = None
    ) -> None:
        """Write a std_msgs/Float64MultiArray at log time ``stamp`` (it has no header).

        ``names`` (optional) labels the values: one layout dimension whose label is
        the comma-joined names, so readers can match joints by name.
        """
        values = _float_vector(data, None if names is None else len(names), f"{topic} data")
        self.write_block(float64_array_messages(topic, np.array([stamp], dtype=float), values[None], names))

    def boolean(self, topic: str, stamp: float, value: bool) -> None:
        """Write a std_msgs/Bool at log time ``stamp`` (e.g. the contact flag)."""
        self.write_block(bool_messages(topic, np.array([stamp], dtype=float), np.array([bool(value)])))


@dataclass(frozen=True)
class Messages:
    """Messages of one topic and type, serialised: row k of ``data`` (m, size) is logged at ``log_ns[k]``."""

    topic: str
    msgtype: str
    log_ns: npt.NDArray[np.int64]
    data: npt.NDArray[np.uint8]


def _messages(topic: str, msgtype: str, log_ns: npt.NDArray[np.int64], first: Any,
              values: dict[str, npt.ArrayLike]) -> Messages:
    """Messages like ``first`` (the first, as a rosbags message) with the numbers ``values`` (name → rows)."""
    if not len(log_ns):
        return Messages(topic, msgtype, log_ns, np.zeros((0, 0), dtype=np.uint8))
    raw = bytes(typestore().serialize_cdr(first, msgtype))
    layout = Layout.read(raw, msgtype, first)
    assert layout is not None, f"{msgtype}: a message rosbags serialised must have a layout"
    return Messages(topic, msgtype, log_ns, layout.encode(values, len(log_ns)))


def _header(stamp_ns: npt.NDArray[np.int64], frame_id: str = "") -> tuple[Any, dict[str, npt.ArrayLike]]:
    """The first row's std_msgs/Header, and every row's stamp fields."""
    types = typestore().types
    sec, nanosec = np.divmod(stamp_ns, NS_PER_SECOND)
    time = types["builtin_interfaces/msg/Time"](sec=int(sec[0]), nanosec=int(nanosec[0]))
    header = types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)
    return header, {"sec": sec[:, None], "nanosec": nanosec[:, None]}


def _rows(value: Any, rows: int, width: int | None, what: str) -> FloatArray:
    """Coerce to a (rows, width) float64 array (width None: any)."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] != rows or (width is not None and arr.shape[1] != width):
        raise ValueError(f"{what} has shape {arr.shape}, expected ({rows}, {width if width is not None else 'n'})")
    return arr


def joint_state_messages(topic: str, stamp: FloatArray, names: Sequence[str], position: Any = None,
                         velocity: Any = None, effort: Any = None) -> Messages:
    """sensor_msgs/JointState at ``stamp`` (s): each given field (rows, len(names)); None is written empty."""
    ns = _stamps_ns(stamp)
    names = [str(n) for n in names]
    fields = {key: np.empty((len(ns), 0)) if value is None else _rows(value, len(ns), len(names), f"{topic} {key}")
              for key, value in (("position", position), ("velocity", velocity), ("effort", effort))}
    if not len(ns):
        return _messages(topic, JOINT_STATE, ns, None, {})
    header, values = _header(ns)
    first = typestore().types[JOINT_STATE](header=header, name=names,
                                            **{key: value[0] for key, value in fields.items()})
    return _messages(topic, JOINT_STATE, ns, first, {**values, **fields})


def wrench_messages(topic: str, stamp: FloatArray, frame_id: str, force: Any, torque: Any) -> Messages:
    """geometry_msgs/WrenchStamped at ``stamp`` (s): force (rows, 3) N, torque (rows, 3) N·m in ``frame_id``."""
    ns = _stamps_ns(stamp)
    wrench = np.hstack((_rows(force, len(ns), 3, f"{topic} force"), _rows(torque, len(ns), 3, f"{topic} torque")))
    if not len(ns):
        return _messages(topic, WRENCH_STAMPED, ns, None, {})
    types = typestore().types
    header, values = _header(ns, str(frame_id))
    vec = types["geometry_msgs/msg/Vector3"]
    x, y, z, tx, ty, tz = map(float, wrench[0])
    first = types[WRENCH_STAMPED](header=header, wrench=types["geometry_msgs/msg/Wrench"](
        force=vec(x=x, y=y, z=z), torque=vec(x=tx, y=ty, z=tz)))
    return _messages(topic, WRENCH_STAMPED, ns, first, {**values, "wrench": wrench})


def float64_array_messages(topic: str, stamp: FloatArray, data: Any, names: Sequence[str] | None = None) -> Messages:
    """std_msgs/Float64MultiArray logged at ``stamp`` (s): data (rows, k), labelled with ``names`` if given
    (one layout dimension whose label is the comma-joined names)."""
    ns = _stamps_ns(stamp)
    values = _rows(data, len(ns), None if names is None else len(names), f"{topic} data")
    if not len(ns):
        return _messages(topic, FLOAT64_ARRAY, ns, None, {})
    types = typestore().types
    width = values.shape[1]
    dims = [] if names is None else [types["std_msgs/msg/MultiArrayDimension"](
        label=",".join(str(n) for n in names), size=width, stride=width)]
    layout = types["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    return _messages(topic, FLOAT64_ARRAY, ns, types[FLOAT64_ARRAY](layout=layout, data=values[0]), {"data": values})


def bool_messages(topic: str, stamp: FloatArray, value: Any) -> Messages:
    """std_msgs/Bool logged at ``stamp`` (s), one per value (e.g. the contact flag)."""
    ns = _stamps_ns(stamp)
    flags = np.asarray(value, dtype=bool).reshape(len(ns), 1)
    if not len(ns):
        return _messages(topic, BOOL, ns, None, {})
    return _messages(topic, BOOL, ns, typestore().types[BOOL](data=bool(flags[0, 0])), {"data": flags})


def write_run(
    path: PathLike,
    run: RecordedRun,
    storage: str = "mcap",
    topics: TopicNames = TopicNames(),
    force: bool = False,
) -> None:
    """Write ``run`` as a bag at ``path`` (atomic; see BagWriter; an existing output is replaced only with
    ``force``); ``run.source`` goes into its metadata.

    Messages are interleaved in log-time order like a live recording. Commands
    are a Float64MultiArray in the run's joint order, labelled with the joint
    names so the order survives a reader that asks for another one.
    """
    with BagWriter(path, storage=storage, force=force, source=run.source) as bag:
        write_run_messages(bag, run, topics)


def write_run_messages(bag: BagWriter, run: RecordedRun, topics: TopicNames = TopicNames()) -> None:
    """Write ``run``'s messages into an open ``bag``, interleaved in log-time order (at equal times joint
    states, commands, wrenches, true torques, each in row order)."""
    names = run.joint_names
    js, cmd, wr, ext = run.joint_states, run.commands, run.wrench, run.external_torque
    blocks = [joint_state_messages(topics.joint_states, js.stamp, names, js.position, js.velocity, js.effort)]
    if cmd is not None:
        blocks.append(float64_array_messages(topics.effort_commands, cmd.stamp, cmd.effort, names))
    if wr is not None:
        blocks.append(wrench_messages(topics.wrench, wr.stamp, wr.frame_id, wr.force, wr.torque))
    if ext is not None:
        blocks.append(joint_state_messages(topics.external_torque, ext.stamp, names, ext.position, ext.velocity,
                                           ext.effort))
    which = np.concatenate([np.full(len(block.log_ns), k, dtype=np.intp) for k, block in enumerate(blocks)])
    rows = np.concatenate([np.arange(len(block.log_ns)) for block in blocks])
    order = np.lexsort((rows, which, np.concatenate([block.log_ns for block in blocks])))
    bag.write_messages(blocks, which[order], rows[order])


def _stamps_ns(stamp: Any) -> npt.NDArray[np.int64]:
    """Seconds → integer nanoseconds (nearest); rejects stamps that are not finite, negative, or past the
    int32 seconds of a ROS time."""
    stamp = np.asarray(stamp, dtype=np.float64).reshape(-1)
    bad = stamp[~(np.isfinite(stamp) & (stamp >= 0.0) & (stamp < 2.0**31))]
    ns = np.rint(stamp * 1e9).astype(np.int64) if not bad.size else np.zeros(0, dtype=np.int64)
    if bad.size or (ns.size and ns.max() >= 2**31 * NS_PER_SECOND):
        raise ValueError(f"stamps must be finite and in [0, 2**31) s, got {bad[0] if bad.size else stamp.max()!r}")
    return ns
