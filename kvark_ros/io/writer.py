"""Write runs and estimator outputs as ROS 2 bags (MCAP or sqlite3), atomically.

Stamps are stored in a bag as integer nanoseconds, so a stamp ``t`` survives a
write/read round trip bit for bit when ``t == round(t * 1e9) / 1e9`` (stamps
built as ``ns / 1e9``); others are rounded to the nearest nanosecond.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from rosbags.rosbag2 import StoragePlugin, Writer

from kvark_ros.io.common import (
    BOOL,
    FLOAT64_ARRAY,
    JOINT_STATE,
    WRENCH_STAMPED,
    _NS,
    FloatArray,
    PathLike,
    _typestore,
)
from kvark_ros.io.runs import SOURCE_KEY, RecordedRun, TopicNames, _error

__all__ = ["BagWriter", "write_run", "write_run_messages"]

_STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_BAG_VERSION: Literal[9] = 9  # rosbag2 metadata version written by Jazzy


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

    def __init__(self, path: PathLike, storage: str = "mcap", overwrite: bool = False, source: str = "") -> None:
        self.path = Path(path)
        self.source = source          # metadata custom_data kvark_ros.source ("" = none): what wrote the bag
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
    """Write ``run`` as a bag at ``path`` (atomic; see BagWriter); ``run.source`` goes into its metadata.

    Messages are interleaved in log-time order like a live recording. Commands
    are a Float64MultiArray in the run's joint order, labelled with the joint
    names so the order survives a reader that asks for another one.
    """
    with BagWriter(path, storage=storage, overwrite=overwrite, source=run.source) as bag:
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
