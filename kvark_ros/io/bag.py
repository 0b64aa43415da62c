"""Read and write ROS 2 bags (MCAP or sqlite3) with rosbags; never rclpy.

A *run* is what the estimator and the trainer consume: measured joint states,
commanded joint torque, and optionally the simulator's ground truth (wrist F/T
wrench and true external joint torque). Joints are matched by name, never by
position in a message (DESIGN.md §1); units are SI; stamps are seconds.

Stamps are stored in a bag as integer nanoseconds, so a stamp ``t`` survives a
write/read round trip bit for bit when ``t == round(t * 1e9) / 1e9`` (stamps
built as ``ns / 1e9``); others are rounded to the nearest nanosecond.

Every failure a user can cause (bad path, not a bag, corrupt file, missing
topic or joint, wrong message type, existing output) raises :class:`BagError`
with a one-line message naming the file, the problem and the fix.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

__all__ = [
    "BagError",
    "BagWriter",
    "CommandSeries",
    "JointStateSeries",
    "RecordedRun",
    "TopicNames",
    "WrenchSeries",
    "bag_info",
    "read_run",
    "write_run",
]

PathLike = str | os.PathLike[str]
FloatArray = npt.NDArray[np.float64]

JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64_ARRAY = "std_msgs/msg/Float64MultiArray"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
BOOL = "std_msgs/msg/Bool"

_STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_BAG_VERSION: Literal[9] = 9  # rosbag2 metadata version written by Jazzy
_NS = 1_000_000_000


class BagError(ValueError):
    """A bag cannot be read or written; the message names file, problem and fix."""


def _error(path: PathLike, problem: str, fix: str) -> BagError:
    """Build a one-line BagError: '<path>: <problem>; <fix>'."""
    text = f"{os.fspath(path)}: {problem}; {fix}"
    return BagError(" ".join(text.split()))


@cache
def _typestore() -> Any:
    """The single Jazzy typestore: message classes, CDR (de)serialisation."""
    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class TopicNames:
    """Topic names of a run; rename to match a recording."""

    joint_states: str = "/joint_states"
    effort_commands: str = "/effort_commands"
    wrench: str = "/ft_sensor/wrench"
    external_torque: str = "/ground_truth/external_joint_torque"


def _as_matrix(value: Any, rows: int, cols: int, what: str) -> FloatArray:
    """Coerce to a C-contiguous float64 (rows, cols) array or raise ValueError."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.shape != (rows, cols):
        raise ValueError(f"{what} has shape {arr.shape}, expected {(rows, cols)}")
    return arr


def _as_stamps(value: Any, what: str) -> FloatArray:
    """Coerce to a 1-D float64 stamp array or raise ValueError."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{what} must be 1-D, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class JointStateSeries:
    """Joint states over time; columns follow ``names``.

    stamp (T,) s from header stamps; position (T, n) rad; velocity (T, n)
    rad/s; effort (T, n) N·m. A field a message leaves empty reads as NaN.
    """

    stamp: FloatArray
    names: tuple[str, ...]
    position: FloatArray
    velocity: FloatArray
    effort: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "JointStateSeries.stamp")
        names = tuple(str(n) for n in self.names)
        if len(set(names)) != len(names):
            raise ValueError(f"JointStateSeries.names has duplicates: {names}")
        shape = (stamp.shape[0], len(names))
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "names", names)
        for key in ("position", "velocity", "effort"):
            arr = _as_matrix(getattr(self, key), *shape, f"JointStateSeries.{key}")
            object.__setattr__(self, key, arr)


@dataclass(frozen=True)
class CommandSeries:
    """Commanded joint torque: stamp (T,) s (bag log time), effort (T, n) N·m in run order."""

    stamp: FloatArray
    effort: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "CommandSeries.stamp")
        effort = np.ascontiguousarray(self.effort, dtype=np.float64)
        if effort.ndim != 2 or effort.shape[0] != stamp.shape[0]:
            raise ValueError(
                f"CommandSeries.effort has shape {effort.shape}, expected ({stamp.shape[0]}, n)"
            )
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "effort", effort)


@dataclass(frozen=True)
class WrenchSeries:
    """Wrench over time in ``frame_id``: stamp (T,) s, force (T, 3) N, torque (T, 3) N·m."""

    stamp: FloatArray
    frame_id: str
    force: FloatArray
    torque: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "WrenchSeries.stamp")
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "frame_id", str(self.frame_id))
        for key in ("force", "torque"):
            arr = _as_matrix(getattr(self, key), stamp.shape[0], 3, f"WrenchSeries.{key}")
            object.__setattr__(self, key, arr)


@dataclass(frozen=True)
class RecordedRun:
    """One recording: measured joint states, commands and optional ground truth.

    ``external_torque`` is the true external joint torque (effort field; its
    position/velocity may be zeros) in the same joint order as ``joint_states``.
    """

    joint_states: JointStateSeries
    commands: CommandSeries | None
    wrench: WrenchSeries | None = None
    external_torque: JointStateSeries | None = None

    def __post_init__(self) -> None:
        n = len(self.joint_states.names)
        if self.commands is not None and self.commands.effort.shape[1] != n:
            raise ValueError(
                f"commands have {self.commands.effort.shape[1]} joints, joint_states have {n}"
            )
        if self.external_torque is not None and self.external_torque.names != self.joint_names:
            raise ValueError(
                f"external_torque joints {self.external_torque.names} differ from "
                f"joint_states joints {self.joint_names}"
            )

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint order of every (T, n) array in the run."""
        return self.joint_states.names


# --------------------------------------------------------------------------- writing


def _stamp_ns(stamp: float) -> int:
    """Seconds → integer nanoseconds (nearest); rejects negative or non-finite stamps."""
    value = float(stamp)
    if not np.isfinite(value) or value < 0.0:
        raise ValueError(f"stamp must be finite and >= 0 s, got {stamp!r}")
    return round(value * 1e9)


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
        raise _error(
            path, f"unknown bag storage {storage!r}", f"use one of {sorted(_STORAGES)}"
        ) from None


class BagWriter:
    """Write a rosbag2 bag atomically; use as a context manager.

    Messages go into a temporary sibling directory that is renamed to ``path``
    only when the block exits without an exception, so a failed or interrupted
    write never leaves a partial bag at ``path``. Stamps are seconds; for
    messages with a header the header stamp is also the bag log time.
    """

    def __init__(self, path: PathLike, storage: str = "mcap", overwrite: bool = False) -> None:
        self.path = Path(path)
        self._plugin = _parse_storage(storage, self.path)
        self.overwrite = overwrite
        self._check_target()
        self._tmpdir: Path | None = None
        self._writer: Writer | None = None
        self._connections: dict[str, tuple[str, Any]] = {}

    # -- lifecycle

    def _check_target(self) -> None:
        if (self.path.exists() or self.path.is_symlink()) and not self.overwrite:
            raise _error(
                self.path, "output exists already", "pass overwrite=True or choose a new path"
            )

    def open(self) -> BagWriter:
        """Start writing into a temporary directory next to ``path``."""
        if self._writer is not None:
            raise RuntimeError("BagWriter is already open")
        self._check_target()
        parent = self.path.absolute().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=parent))
        except OSError as exc:
            raise _error(
                self.path,
                f"cannot create output ({exc.strerror})",
                "check the directory and permissions",
            ) from exc
        # The bag directory inside tmpdir has the final name, so the storage
        # file is '<name>.mcap' / '<name>.db3' as ros2 bag tools expect.
        writer = Writer(tmpdir / self.path.name, version=_BAG_VERSION, storage_plugin=self._plugin)
        try:
            writer.open()
        except BaseException:
            shutil.rmtree(tmpdir, ignore_errors=True)
            raise
        self._tmpdir, self._writer = tmpdir, writer
        return self

    def close(self) -> None:
        """Finish the bag and move it to ``path`` (replacing it if overwrite=True)."""
        writer, tmpdir = self._require_open(), self._tmpdir
        assert tmpdir is not None
        try:
            writer.close()
            self._commit(tmpdir / self.path.name)
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

    def _commit(self, built: Path) -> None:
        """Rename the finished bag onto ``path``; an old output is removed only after."""
        target = self.path
        if not (target.exists() or target.is_symlink()):
            os.rename(built, target)
            return
        if not self.overwrite:
            raise _error(
                target, "output appeared while writing", "pass overwrite=True or choose a new path"
            )
        if target.is_dir() and not target.is_symlink():
            trash = built.parent / ".replaced"
            os.rename(target, trash)
            try:
                os.rename(built, target)
            except BaseException:
                os.rename(trash, target)
                raise
            shutil.rmtree(trash, ignore_errors=True)
        else:  # a file or symlink where the bag directory should go
            target.unlink()
            os.rename(built, target)

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

    def _write(self, topic: str, msgtype: str, log_ns: int, msg: Any) -> None:
        writer = self._require_open()
        entry = self._connections.get(topic)
        if entry is None:
            conn = writer.add_connection(topic, msgtype, typestore=_typestore())
            entry = self._connections[topic] = (msgtype, conn)
        elif entry[0] != msgtype:
            raise ValueError(f"topic {topic} already carries {entry[0]}, cannot write {msgtype}")
        writer.write(entry[1], log_ns, _typestore().serialize_cdr(msg, msgtype))

    @staticmethod
    def _header(stamp_ns: int, frame_id: str = "") -> Any:
        types = _typestore().types
        time = types["builtin_interfaces/msg/Time"](sec=stamp_ns // _NS, nanosec=stamp_ns % _NS)
        return types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)

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
        ns = _stamp_ns(stamp)
        names = [str(n) for n in names]
        fields = {
            key: np.empty(0) if val is None else _float_vector(val, len(names), f"{topic} {key}")
            for key, val in (("position", position), ("velocity", velocity), ("effort", effort))
        }
        msg = _typestore().types[JOINT_STATE](header=self._header(ns), name=names, **fields)
        self._write(topic, JOINT_STATE, ns, msg)

    def wrench(self, topic: str, stamp: float, frame_id: str, force: Any, torque: Any) -> None:
        """Write a geometry_msgs/WrenchStamped: force (3,) N, torque (3,) N·m in frame_id."""
        ns = _stamp_ns(stamp)
        f = _float_vector(force, 3, f"{topic} force")
        t = _float_vector(torque, 3, f"{topic} torque")
        types = _typestore().types
        vec = types["geometry_msgs/msg/Vector3"]
        wrench = types["geometry_msgs/msg/Wrench"](
            force=vec(x=float(f[0]), y=float(f[1]), z=float(f[2])),
            torque=vec(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        )
        msg = types[WRENCH_STAMPED](header=self._header(ns, str(frame_id)), wrench=wrench)
        self._write(topic, WRENCH_STAMPED, ns, msg)

    def float64_array(
        self, topic: str, stamp: float, data: Any, names: Sequence[str] | None = None
    ) -> None:
        """Write a std_msgs/Float64MultiArray at log time ``stamp`` (it has no header).

        ``names`` (optional) labels the values: one layout dimension whose label is
        the comma-joined names, so readers can match joints by name.
        """
        ns = _stamp_ns(stamp)
        values = _float_vector(data, None if names is None else len(names), f"{topic} data")
        types = _typestore().types
        dims = []
        if names is not None:
            label = ",".join(str(n) for n in names)
            dims = [
                types["std_msgs/msg/MultiArrayDimension"](
                    label=label, size=len(values), stride=len(values)
                )
            ]
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
        self._write(topic, FLOAT64_ARRAY, ns, types[FLOAT64_ARRAY](layout=layout, data=values))

    def boolean(self, topic: str, stamp: float, value: bool) -> None:
        """Write a std_msgs/Bool at log time ``stamp`` (e.g. the contact flag)."""
        ns = _stamp_ns(stamp)
        self._write(topic, BOOL, ns, _typestore().types[BOOL](data=bool(value)))


def write_run(
    path: PathLike,
    run: RecordedRun,
    storage: str = "mcap",
    topics: TopicNames = TopicNames(),
    overwrite: bool = False,
) -> None:
    """Write ``run`` as a bag at ``path`` (atomic; see BagWriter).

    Messages are interleaved in log-time order like a live recording. Commands
    are a Float64MultiArray in the run's joint order, labelled with the joint
    names so the order survives a reader that asks for another one.
    """
    with BagWriter(path, storage=storage, overwrite=overwrite) as bag:
        write_run_messages(bag, run, topics)


def write_run_messages(bag: BagWriter, run: RecordedRun, topics: TopicNames = TopicNames()) -> None:
    """Write ``run``'s messages into an open ``bag``, interleaved in log-time order."""
    names = run.joint_names
    events: list[tuple[npt.NDArray[np.int64], int]] = []
    series: list[Any] = [run.joint_states, run.commands, run.wrench, run.external_torque]
    for kind, item in enumerate(series):
        if item is not None:
            events.append((_stamps_ns(item.stamp), kind))
    log_ns = np.concatenate([ns for ns, _ in events])
    kinds = np.concatenate([np.full(ns.shape, k) for ns, k in events])
    rows = np.concatenate([np.arange(ns.shape[0]) for ns, _ in events])
    order = np.lexsort((rows, kinds, log_ns))
    js, cmd, wr, ext = run.joint_states, run.commands, run.wrench, run.external_torque
    for i in order:
        kind, row = int(kinds[i]), int(rows[i])
        stamp = float(series[kind].stamp[row])
        if kind == 0:
            bag.joint_state(topics.joint_states, stamp, names, js.position[row], js.velocity[row], js.effort[row])
        elif kind == 1:
            assert cmd is not None
            bag.float64_array(topics.effort_commands, stamp, cmd.effort[row], names=names)
        elif kind == 2:
            assert wr is not None
            bag.wrench(topics.wrench, stamp, wr.frame_id, wr.force[row], wr.torque[row])
        else:
            assert ext is not None
            bag.joint_state(topics.external_torque, stamp, names, ext.position[row], ext.velocity[row],
                            ext.effort[row])


def _stamps_ns(stamp: FloatArray) -> npt.NDArray[np.int64]:
    """Seconds → integer nanoseconds, vectorised; rejects negative or non-finite stamps."""
    if stamp.size and (not np.all(np.isfinite(stamp)) or stamp.min() < 0.0):
        raise ValueError("stamps must be finite and >= 0 s")
    return np.rint(stamp * 1e9).astype(np.int64)


# --------------------------------------------------------------------------- reading


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
    """Maps a message's joint names onto the run's joint order, with a cache."""

    def __init__(self, path: Path, topic: str, wanted: tuple[str, ...]) -> None:
        self.path, self.topic, self.wanted = path, topic, wanted
        self._cache: dict[tuple[str, ...], npt.NDArray[np.intp] | None] = {}

    @property
    def seen(self) -> list[tuple[str, ...]]:
        """Distinct joint-name lists met so far."""
        return list(self._cache)

    def index(self, names: Sequence[str]) -> npt.NDArray[np.intp] | None:
        """Indices into the message's arrays; None for a message with none of the joints."""
        key = tuple(names)
        if key in self._cache:
            return self._cache[key]
        pos = {n: i for i, n in enumerate(key)}
        missing = [n for n in self.wanted if n not in pos]
        if len(missing) == len(self.wanted):
            idx = None  # another publisher on the topic (e.g. the gripper): skip
        elif missing:
            raise _error(
                self.path,
                f"joint {missing[0]!r} is missing from {self.topic}"
                + (f" (also {missing[1:]})" if len(missing) > 1 else "")
                + f", whose messages name {list(key)}",
                "fix joint_names (or the config) to name joints the bag has",
            )
        else:
            idx = np.fromiter((pos[n] for n in self.wanted), dtype=np.intp, count=len(self.wanted))
        self._cache[key] = idx
        return idx


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
    stamps that are all zero fall back to the bag log time.
    """
    wanted = None if joint_names is None else tuple(str(n) for n in joint_names)
    if wanted is not None and (not wanted or len(set(wanted)) != len(wanted)):
        raise _error(path, f"joint_names {list(wanted)} are empty or repeat", "fix the config")
    with _open_reader(path) as (given, reader):
        types = _topic_types(reader)
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
    )


def bag_info(path: PathLike) -> dict[str, Any]:
    """Summary of a bag for messages and the CLI.

    Returns {'path', 'storage' ('mcap'|'sqlite3'), 'start' s, 'end' s,
    'duration' s, 'message_count', 'topics': {topic: {'type', 'count'}}}.
    """
    with _open_reader(path) as (given, reader):
        target = _resolve(path)[1]
        files = [target] if target.is_file() else list(target.iterdir())
        suffixes = {f.suffix for f in files}
        storage = "mcap" if ".mcap" in suffixes else "sqlite3" if ".db3" in suffixes else "unknown"
        topic_info: dict[str, dict[str, Any]] = {}
        for conn in reader.connections:
            entry = topic_info.setdefault(conn.topic, {"type": conn.msgtype, "count": 0})
            if entry["type"] != conn.msgtype:
                entry["type"] = "|".join(sorted({*entry["type"].split("|"), conn.msgtype}))
            entry["count"] += conn.msgcount
        count = reader.message_count
        start = reader.start_time / 1e9 if count else 0.0
        end = (reader.end_time - 1) / 1e9 if count else 0.0
        return {
            "path": os.fspath(given),
            "storage": storage,
            "start": start,
            "end": end,
            "duration": end - start,
            "message_count": count,
            "topics": dict(sorted(topic_info.items())),
        }
