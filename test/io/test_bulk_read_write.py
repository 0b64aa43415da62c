"""Bags read and written in bulk (issue 16) hold exactly what rosbags reads and writes message by message.

The reference for reading is the reader itself with bulk decoding switched off (``MAX_LAYOUTS = 0``: rosbags
decodes every message, one by one, in read order) and the MCAP index path off (rosbags' own reader). The
reference for writing is rosbags' own ``Writer`` fed one message at a time, serialised by rosbags.
"""
from __future__ import annotations

from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer

from kvark_ros.io import BagError, RecordedRun, read_run
from kvark_ros.io import mcap_bulk, reader
from kvark_ros.io.recorded_inputs import estimator_inputs
from kvark_ros.io.cdr_arrays import Layout, message_fields, windows
from kvark_ros.io.common import BOOL, FLOAT64_ARRAY, JOINT_STATE, WRENCH_STAMPED, typestore
from kvark_ros.io.mcap_bulk import indexed_messages
from kvark_ros.tools.replay import ObserverRun, write_estimates

ROOT = Path(__file__).resolve().parents[2]
BAGS = sorted((ROOT / "bags").glob("panda_*"))
ARM = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")
TYPES = typestore().types


# -- messages built and serialised by rosbags alone

def _header(ns: int, frame: str = "") -> Any:
    return TYPES["std_msgs/msg/Header"](stamp=TYPES["builtin_interfaces/msg/Time"](sec=ns // 10**9,
                                                                                  nanosec=ns % 10**9),
                                        frame_id=frame)


def joint_state(ns: int, names: list[str], position: Any, velocity: Any, effort: Any, frame: str = "") -> Any:
    def array(values: Any) -> np.ndarray:
        return np.empty(0) if values is None else np.asarray(values, dtype=np.float64)
    return TYPES[JOINT_STATE](header=_header(ns, frame), name=list(names), position=array(position),
                              velocity=array(velocity), effort=array(effort))


def float64_array(values: Any, labels: list[str] | None = None) -> Any:
    values = np.asarray(values, dtype=np.float64)
    dims = [] if labels is None else [TYPES["std_msgs/msg/MultiArrayDimension"](
        label=",".join(labels), size=len(values), stride=len(values))]
    return TYPES[FLOAT64_ARRAY](layout=TYPES["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0), data=values)


def wrench(ns: int, frame: str, values: Any) -> Any:
    vec = TYPES["geometry_msgs/msg/Vector3"]
    f = [float(v) for v in values]
    return TYPES[WRENCH_STAMPED](header=_header(ns, frame), wrench=TYPES["geometry_msgs/msg/Wrench"](
        force=vec(x=f[0], y=f[1], z=f[2]), torque=vec(x=f[3], y=f[4], z=f[5])))


def boolean(value: bool) -> Any:
    return TYPES[BOOL](data=bool(value))


class RosbagsBag:
    """A bag written by rosbags' own Writer, one message at a time (any type on any topic, any byte order)."""

    def __init__(self, path: Path, storage: str = "mcap") -> None:
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        self.writer = Writer(path, version=9, storage_plugin=plugin)
        if storage == "mcap-zstd":
            self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.writer.open()
        self.conns: dict[tuple[str, str], Any] = {}

    def raw(self, topic: str, msgtype: str, ns: int, data: bytes) -> None:
        key = (topic, msgtype)
        if key not in self.conns:
            self.conns[key] = self.writer.add_connection(topic, msgtype, typestore=typestore())
        self.writer.write(self.conns[key], ns, data)

    def add(self, topic: str, msgtype: str, ns: int, msg: Any, little_endian: bool = True) -> None:
        self.raw(topic, msgtype, ns, bytes(typestore().serialize_cdr(msg, msgtype, little_endian=little_endian)))

    def close(self) -> None:
        self.writer.close()


# -- reading: bulk against one by one

def _attempt(path: Path, **kwargs: Any) -> RecordedRun | str:
    try:
        return read_run(path, **kwargs)
    except BagError as exc:
        return str(exc)


def read_both(path: Path, monkeypatch: pytest.MonkeyPatch, **kwargs: Any) -> tuple[Any, Any]:
    """(bulk read, message-by-message read) of ``path``: a RecordedRun, or the BagError's text."""
    bulk = _attempt(path, **kwargs)
    with monkeypatch.context() as patch:
        patch.setattr(reader, "MAX_LAYOUTS", 0)
        patch.setattr(reader, "_indexed", lambda *args: None)
        single = _attempt(path, **kwargs)
    return bulk, single


def assert_same_run(bulk: Any, single: Any) -> None:
    """Equal errors, or runs equal to the bit (NaN payloads, -0.0 and all)."""
    assert type(bulk) is type(single)
    if isinstance(single, str):
        assert bulk == single
        return
    assert bulk.source == single.source
    for name in ("joint_states", "commands", "wrench", "external_torque"):
        a, b = getattr(bulk, name), getattr(single, name)
        assert (a is None) == (b is None), name
        if b is None:
            continue
        for key, value in vars(b).items():
            got = getattr(a, key)
            if isinstance(value, np.ndarray):
                assert got.dtype == value.dtype and got.shape == value.shape, (name, key)
                assert got.tobytes() == value.tobytes(), (name, key)
            else:
                assert got == value, (name, key)


@pytest.mark.parametrize("bag", BAGS, ids=lambda path: path.name)
def test_committed_bags_read_the_same_in_bulk(bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for joint_names in (None, ARM):
        bulk, single = read_both(bag, monkeypatch, joint_names=joint_names)
        assert isinstance(single, RecordedRun)
        assert_same_run(bulk, single)


@pytest.mark.parametrize("bag", BAGS, ids=lambda path: path.name)
def test_indexed_messages_are_rosbags_messages(bag: Path) -> None:
    """The MCAP index path gives rosbags' read order, log times and bytes (several chunks per bag)."""
    (mcap,) = bag.glob("*.mcap")
    with Reader(mcap) as bag_reader:
        storage = bag_reader.storage
        assert len(storage.chunks) > 1
        raw = indexed_messages(mcap, storage.chunks, [conn.id for conn in bag_reader.connections])
        expected = [(conn.id, stamp, bytes(data)) for conn, stamp, data in bag_reader.messages()]
    assert raw is not None
    assert [(int(raw.channel[k]), int(raw.log_ns[k]), raw.message(k)) for k in range(len(raw.start))] == expected


ORDERS = [list(ARM), list(ARM[::-1]), [*FINGERS, *ARM], [*ARM[:3], FINGERS[0], *ARM[3:]]]


def write_adversarial(path: Path, storage: str, seed: int, frame: str) -> None:
    """Joint orders that change (runs and alternations, more than MAX_LAYOUTS of them), extra and foreign
    joints, NaN/±inf/-0.0, empty fields, header frames of every length mod 8, repeated and backward stamps,
    big-endian messages, labelled and unlabelled commands next to JointState commands on the same topic."""
    rng = np.random.default_rng(seed)
    orders = ORDERS + [list(rng.permutation(ARM)) for _ in range(reader.MAX_LAYOUTS + 4)]
    bag = RosbagsBag(path, storage)
    for k in range(300):
        ns = 1_000_000_000 + 2_000_000 * k - (4_000_000 if k % 17 == 5 else 0)
        names = orders[0] if k % 40 < 25 else orders[int(rng.integers(len(orders)))]
        values = rng.normal(size=(3, len(names)))
        values[rng.random(values.shape) < 0.05] = rng.choice([np.nan, np.inf, -np.inf, -0.0])
        msg = joint_state(ns, names, values[0], None if k % 13 == 7 else values[1], values[2],
                          frame="x" * int(rng.integers(0, 9)))
        bag.add("/joint_states", JOINT_STATE, ns, msg, little_endian=k % 19 != 4)
        if k % 31 == 3:       # another publisher on the topic
            bag.add("/joint_states", JOINT_STATE, ns + 1000,
                    joint_state(ns + 1000, list(FINGERS), [0, 0], [0, 0], None))
        labels = orders[(k // 3) % len(orders)]
        order = [labels.index(name) for name in ARM if name in labels]
        command = rng.normal(size=len(labels))
        if k % 11 == 0:
            bag.add("/effort_commands", FLOAT64_ARRAY, ns + 500_000, float64_array(command[order]))
        elif k % 11 == 1:
            bag.add("/effort_commands", JOINT_STATE, ns + 500_000, joint_state(0, labels, None, None, command))
        else:
            bag.add("/effort_commands", FLOAT64_ARRAY, ns + 500_000, float64_array(command, labels),
                    little_endian=k % 23 != 2)
        bag.add("/ft_sensor/wrench", WRENCH_STAMPED, ns, wrench(ns, frame, rng.normal(size=6)),
                little_endian=k % 29 != 8)
        bag.add("/ground_truth/external_joint_torque", JOINT_STATE, ns,
                joint_state(ns, list(rng.permutation(ARM)), None, None, rng.normal(size=7)))
    bag.close()


@pytest.mark.parametrize("storage", ["mcap", "mcap-zstd", "sqlite3"])
@pytest.mark.parametrize("frame", ["", "a", "abc", "abcd", "abcdefg", "panda_hand_tcp"])
def test_adversarial_bags_read_the_same_in_bulk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, storage: str,
                                                frame: str) -> None:
    write_adversarial(tmp_path / "bag", storage, seed=len(frame), frame=frame)
    bulk, single = read_both(tmp_path / "bag", monkeypatch, joint_names=ARM)
    assert isinstance(single, RecordedRun) and single.wrench is not None and single.wrench.frame_id == frame
    assert_same_run(bulk, single)
    # the first joint state names the joints: later messages without its fingers are an error, the same one
    bulk, single = read_both(tmp_path / "bag", monkeypatch, joint_names=None)
    assert_same_run(bulk, single)


def _faulty(path: Path, first: str, second: str) -> None:
    """A bag whose messages go wrong in two ways, ``first`` at 60 ms, ``second`` at 100 ms."""
    bag = RosbagsBag(path)
    for k in range(80):
        ns = 2_000_000 * k
        fault = first if k == 30 else second if k == 50 else ""
        names = list(ARM[:-1]) if fault == "missing joint" else list(ARM)
        velocity = np.zeros(3) if fault == "malformed" else np.zeros(7)
        bag.add("/joint_states", JOINT_STATE, ns, joint_state(ns, names, np.zeros(len(names)), velocity[:len(names)]
                                                               if fault != "malformed" else velocity, None))
        command = float64_array(np.zeros(5)) if fault == "short command" else float64_array(np.zeros(7), list(ARM))
        if fault == "garbage":
            bag.raw("/effort_commands", FLOAT64_ARRAY, ns + 1000, b"\x00\x01\x00\x00\xff\xff\xff\x7f")
        else:
            bag.add("/effort_commands", FLOAT64_ARRAY, ns + 1000, command)
        bag.add("/ft_sensor/wrench", WRENCH_STAMPED, ns,
                wrench(ns, "tool" if fault == "frame" else "flange", np.ones(6)))
    bag.close()


FAULTS = ["missing joint", "malformed", "short command", "garbage", "frame"]


@pytest.mark.parametrize("second", FAULTS)
@pytest.mark.parametrize("first", FAULTS)
def test_the_first_fault_in_read_order_is_the_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, first: str,
                                                    second: str) -> None:
    _faulty(tmp_path / "bag", first, second)
    bulk, single = read_both(tmp_path / "bag", monkeypatch, joint_names=ARM)
    assert isinstance(single, str)
    assert_same_run(bulk, single)


# -- layouts

def _messages(rng: np.random.Generator) -> list[tuple[str, Any]]:
    names = ["a", "bé", "joint_with_a_long_name", "", "x" * 9][: int(rng.integers(1, 6))]
    n = len(names)
    frame = "f" * int(rng.integers(0, 12))
    return [(JOINT_STATE, joint_state(int(rng.integers(0, 2**62)) % (2**31 * 10**9), names, rng.normal(size=n),
                                      None if rng.random() < 0.3 else rng.normal(size=n), rng.normal(size=n), frame)),
            (FLOAT64_ARRAY, float64_array(rng.normal(size=n), None if rng.random() < 0.3 else names)),
            (WRENCH_STAMPED, wrench(int(rng.integers(0, 2**31)) * 10**9, frame, rng.normal(size=6))),
            (BOOL, boolean(rng.random() < 0.5))]


def _bitwise(fields: dict[str, np.ndarray]) -> dict[str, bytes]:
    """Numbers as bytes: floats as float64 (NaN payloads count), integers and flags as int64."""
    return {name: value.astype(np.float64 if value.dtype.kind == "f" else np.int64).tobytes()
            for name, value in fields.items()}


@pytest.mark.parametrize("little_endian", [True, False])
def test_layout_decodes_and_encodes_like_rosbags(little_endian: bool) -> None:
    """A layout read off one message decodes every message of its layout as rosbags does, also with other
    bytes in the alignment padding, and refuses a message whose names differ; encoding gives rosbags' bytes."""
    rng = np.random.default_rng(7)
    store = typestore()
    for _ in range(25):
        for (msgtype, msg), (_, other) in zip(_messages(rng), _messages(rng)):
            raw = bytes(store.serialize_cdr(msg, msgtype, little_endian=little_endian))
            layout = Layout.read(raw, msgtype, msg)
            assert layout is not None
            buffer = np.frombuffer(raw + bytes(8), np.uint8)
            block = windows(buffer, np.array([0]), layout.width)
            assert layout.matches(block).all()
            assert _bitwise(layout.decode(block)) == _bitwise(message_fields(msg, msgtype))
            assert layout.encode(message_fields(msg, msgtype), 1).tobytes() == raw
            noisy = bytearray(raw)                # other padding bytes: rosbags ignores them, so must we
            for position in _ignored(raw, msgtype):
                noisy[position] ^= 0x01
            noisy_block = windows(np.frombuffer(bytes(noisy) + bytes(8), np.uint8), np.array([0]), layout.width)
            assert layout.matches(noisy_block).all()
            decoded = store.deserialize_cdr(bytes(noisy), msgtype)
            assert _bitwise(layout.decode(noisy_block)) == _bitwise(message_fields(decoded, msgtype))
            other_raw = bytes(store.serialize_cdr(other, msgtype, little_endian=little_endian))
            if len(other_raw) == len(raw) and msgtype == JOINT_STATE and other.name != msg.name:
                other_block = windows(np.frombuffer(other_raw + bytes(8), np.uint8), np.array([0]), layout.width)
                assert not layout.matches(other_block).any()


def _ignored(raw: bytes, msgtype: str) -> list[int]:
    """Bytes of ``raw`` that rosbags ignores (alignment padding): changing one leaves the message it decodes."""
    store = typestore()
    reference = bytes(store.serialize_cdr(store.deserialize_cdr(raw, msgtype), msgtype, little_endian=bool(raw[1])))
    ignored = []
    for position in range(4, len(raw)):
        changed = bytearray(raw)
        changed[position] ^= 0x01                   # the low bit: a flag byte of 0x5B would still read True
        try:
            decoded = store.deserialize_cdr(bytes(changed), msgtype)
        except Exception:  # a length, count or terminator
            continue
        if bytes(store.serialize_cdr(decoded, msgtype, little_endian=bool(raw[1]))) == reference:
            ignored.append(position)
    return ignored


# -- writing: bulk against rosbags message by message

def _reference_estimates(path: Path, run: RecordedRun, inputs: Any, results: list[ObserverRun], frame: str) -> None:
    """What replay wrote before issue 16: rosbags' Writer, one message at a time, serialised by rosbags."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns: dict[str, Any] = {}

    def put(topic: str, msgtype: str, stamp: float, msg: Any) -> None:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore())
        writer.write(conns[topic], round(stamp * 1e9), bytes(typestore().serialize_cdr(msg, msgtype)))

    names = list(run.joint_names)
    js, cmd, wr, ext = run.joint_states, run.commands, run.wrench, run.external_torque
    assert cmd is not None and wr is not None and ext is not None
    series = [js, cmd, wr, ext]
    events = sorted((round(float(item.stamp[row]) * 1e9), kind, row)
                    for kind, item in enumerate(series) for row in range(len(item.stamp)))
    for _, kind, row in events:
        stamp = float(series[kind].stamp[row])
        ns = round(stamp * 1e9)
        if kind in (0, 3):
            item = js if kind == 0 else ext
            put("/joint_states" if kind == 0 else "/ground_truth/external_joint_torque", JOINT_STATE, stamp,
                joint_state(ns, names, item.position[row], item.velocity[row], item.effort[row]))
        elif kind == 1:
            put("/effort_commands", FLOAT64_ARRAY, stamp, float64_array(cmd.effort[row], names))
        else:
            put("/ft_sensor/wrench", WRENCH_STAMPED, stamp,
                wrench(ns, wr.frame_id, np.r_[wr.force[row], wr.torque[row]]))
    for result in results:
        prefix = f"/kvark/{result.name}"
        for k in np.flatnonzero(result.valid):
            stamp = float(inputs.stamp[k])
            ns = round(stamp * 1e9)
            put(f"{prefix}/external_joint_torque", JOINT_STATE, stamp,
                joint_state(ns, names, None, None, result.tau_ext[k]))
            put(f"{prefix}/external_wrench", WRENCH_STAMPED, stamp, wrench(ns, frame, result.wrench[k]))
            if result.tau_std is not None:
                put(f"{prefix}/external_joint_torque_stddev", FLOAT64_ARRAY, stamp,
                    float64_array(result.tau_std[k], names))
            put(f"{prefix}/contact", BOOL, stamp, boolean(result.contact[k]))
            put(f"{prefix}/collision", BOOL, stamp, boolean(result.collision[k]))
    writer.close()


def _observer_run(name: str, count: int, rng: np.random.Generator, covariance: bool) -> ObserverRun:
    tau = rng.normal(size=(count, 7))
    tau[rng.random(tau.shape) < 0.01] = np.nan
    valid = rng.random(count) < 0.97
    return ObserverRun(name, tau, np.abs(rng.normal(size=(count, 7))) if covariance else None,
                       rng.normal(size=(count, 6)), None, valid, 1.0, {}, rng.random(count) < 0.3,
                       rng.random(count) < 0.1)


def test_replay_output_bag_is_what_rosbags_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  panda_config: Any) -> None:
    """On a committed bag (several 1 MiB chunks) with two observers, the estimates bag equals, byte for byte,
    the one rosbags' own Writer writes message by message (the header's writer name aside)."""
    run = read_run(ROOT / "bags" / "panda_contact", panda_config.joint_names)
    inputs = estimator_inputs(run)
    rng = np.random.default_rng(3)
    results = [_observer_run("kvark", len(inputs), rng, True), _observer_run("gmo", len(inputs), rng, False)]
    frame = "base" if panda_config.wrench.frame == "base" else panda_config.ee_frame
    _reference_estimates(tmp_path / "reference" / "estimates", run, inputs, results, frame)
    monkeypatch.setattr(mcap_bulk, "LIBRARY", f"rosbags-{version('rosbags')}")
    write_estimates(tmp_path / "bulk" / "estimates", run, inputs, results, panda_config)
    for name in ("estimates.mcap", "metadata.yaml"):
        reference = (tmp_path / "reference" / "estimates" / name).read_bytes()
        assert (tmp_path / "bulk" / "estimates" / name).read_bytes() == reference, name
