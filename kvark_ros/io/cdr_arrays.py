"""Decode and encode many CDR messages of one layout at once, with numpy.

rosbags (de)serialises one message per call (about 7 µs for a JointState), which dominated reading and
writing bags. The messages of one topic nearly always share their *layout*: the same joint names, frame
and array lengths, so only the numbers differ. A :class:`Layout` is read off one message: where its
numbers lie, and which bytes every message of that layout repeats (everything else but the alignment
padding). Messages of the same size whose repeated bytes are equal then decode as slices of one
(m, size) byte block, and encoding writes the numbers into copies of a message rosbags serialised.

CDR as rosbags reads and writes it: a 4-byte encapsulation header (byte 1: 1 little, 0 big endian),
then every field aligned to its size relative to the end of that header; a string is a uint32 length
(counting its NUL) and its bytes, a sequence a uint32 count and its items (float64 items 8-byte aligned
when there are any). A layout is only used after the numbers it locates in its own message were found
equal, bit for bit, to what rosbags decoded from it, so a message the walk misreads is left to rosbags.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from kvark_ros.io.common import BOOL, FLOAT64_ARRAY, JOINT_STATE, TWIST_WITH_COVARIANCE_STAMPED, WRENCH_STAMPED

__all__ = ["Layout", "WORD", "message_fields", "scatter", "windows"]

Bytes = npt.NDArray[np.uint8]
WORD = 8          # blocks are gathered in whole 8-byte words, so a buffer needs this many bytes of tail padding


class _Walk:
    """Steps through one CDR message, noting its numbers' places and its padding."""

    def __init__(self, raw: bytes) -> None:
        self.raw, self.pos = raw, 4
        self.order = "<" if raw[1] else ">"
        self.padding: list[tuple[int, int]] = []
        self.fields: dict[str, tuple[int, np.dtype[Any], int]] = {}

    def align(self, size: int) -> None:
        aligned = 4 + ((self.pos - 4 + size - 1) & -size)
        self.padding.append((self.pos, aligned))
        self.pos = aligned

    def count(self) -> int:
        """A uint32 that is part of the layout (a length, count, size or stride)."""
        self.align(4)
        if self.pos + 4 > len(self.raw):
            raise IndexError("message ends inside a count")
        value = int.from_bytes(self.raw[self.pos:self.pos + 4], "little" if self.order == "<" else "big")
        self.pos += 4
        return value

    def string(self) -> None:
        length = self.count()                  # before the += reads pos: count() moves it
        self.pos += length

    def number(self, name: str, code: str, count: int = 1) -> None:
        dtype = np.dtype(self.order + code)
        if count:
            self.align(dtype.itemsize)
        self.fields[name] = (self.pos, dtype, count)
        self.pos += dtype.itemsize * count

    def floats(self, name: str) -> None:
        self.number(name, "f8", self.count())

    def header(self) -> None:
        self.number("sec", "i4")
        self.number("nanosec", "u4")
        self.string()                      # frame_id


def _joint_state(walk: _Walk) -> None:
    walk.header()
    for _ in range(walk.count()):
        walk.string()
    for name in ("position", "velocity", "effort"):
        walk.floats(name)


def _float64_array(walk: _Walk) -> None:
    for _ in range(walk.count()):          # layout.dim: label, size, stride
        walk.string()
        walk.count()
        walk.count()
    walk.count()                           # layout.data_offset
    walk.floats("data")


def _wrench_stamped(walk: _Walk) -> None:
    walk.header()
    walk.number("wrench", "f8", 6)         # force x, y, z then torque x, y, z


def _twist_with_covariance_stamped(walk: _Walk) -> None:
    walk.header()
    walk.number("wrench", "f8", 6)         # twist linear x, y, z then angular x, y, z
    walk.number("covariance", "f8", 36)


def _bool(walk: _Walk) -> None:
    walk.number("data", "u1")


_WALKS: dict[str, Callable[[_Walk], None]] = {
    JOINT_STATE: _joint_state, FLOAT64_ARRAY: _float64_array, WRENCH_STAMPED: _wrench_stamped, BOOL: _bool,
    TWIST_WITH_COVARIANCE_STAMPED: _twist_with_covariance_stamped,
}


def message_fields(msg: Any, msgtype: str) -> dict[str, npt.NDArray[Any]]:
    """The numbers of one decoded message, each as a (1, count) array, named as in :class:`Layout`."""
    if msgtype == JOINT_STATE:
        stamp = msg.header.stamp
        values = {"sec": [stamp.sec], "nanosec": [stamp.nanosec], "position": msg.position,
                  "velocity": msg.velocity, "effort": msg.effort}
    elif msgtype == FLOAT64_ARRAY:
        values = {"data": msg.data}
    elif msgtype == WRENCH_STAMPED:
        stamp, force, torque = msg.header.stamp, msg.wrench.force, msg.wrench.torque
        values = {"sec": [stamp.sec], "nanosec": [stamp.nanosec],
                  "wrench": [force.x, force.y, force.z, torque.x, torque.y, torque.z]}
    elif msgtype == TWIST_WITH_COVARIANCE_STAMPED:
        stamp, linear, angular = msg.header.stamp, msg.twist.twist.linear, msg.twist.twist.angular
        values = {"sec": [stamp.sec], "nanosec": [stamp.nanosec],
                  "wrench": [linear.x, linear.y, linear.z, angular.x, angular.y, angular.z],
                  "covariance": msg.twist.covariance}
    else:
        values = {"data": [msg.data]}
    return {name: np.asarray(value).reshape(1, -1) for name, value in values.items()}


@dataclass(frozen=True)
class Layout:
    """Where a message's numbers lie and which bytes every message of its layout repeats.

    ``template``: the message's bytes, zero-padded to whole words; ``fixed``: a word mask of the bytes
    that must be equal (not the numbers, the alignment padding or the up to 3 trailing bytes);
    ``fields``: name → (byte offset, dtype with byte order, count).
    """

    msgtype: str
    size: int
    template: npt.NDArray[np.uint64]
    fixed: npt.NDArray[np.uint64]
    fields: dict[str, tuple[int, np.dtype[Any], int]]

    @classmethod
    def read(cls, raw: bytes, msgtype: str, msg: Any) -> Layout | None:
        """The layout of ``raw`` (one CDR message of ``msgtype`` that rosbags decoded to ``msg``), or
        None when the walk does not find exactly the numbers rosbags found (the message is left to rosbags)."""
        walk = _Walk(raw)
        try:
            _WALKS[msgtype](walk)
        except IndexError:
            return None
        if walk.pos > len(raw):
            return None
        decoded = message_fields(msg, msgtype)
        for name, (offset, dtype, count) in walk.fields.items():
            if raw[offset:offset + dtype.itemsize * count] != decoded[name].astype(dtype).tobytes():
                return None
        width = -(-len(raw) // WORD) * WORD
        template = np.zeros(width, np.uint8)
        template[:len(raw)] = np.frombuffer(raw, np.uint8)
        fixed = np.zeros(width, np.uint8)
        fixed[:walk.pos] = 0xFF
        for start, end in walk.padding:
            fixed[start:end] = 0
        for offset, dtype, count in walk.fields.values():
            fixed[offset:offset + dtype.itemsize * count] = 0
        return cls(msgtype, len(raw), template.view(np.uint64), fixed.view(np.uint64), walk.fields)

    @property
    def width(self) -> int:
        """Bytes gathered per message: its size rounded up to whole words."""
        return int(self.template.nbytes)

    def matches(self, block: Bytes) -> npt.NDArray[np.bool_]:
        """Which rows of ``block`` ((m, width) bytes of messages of this size) repeat the fixed bytes."""
        words = block.view(np.uint64)
        same = np.ones(len(words), dtype=bool)
        edges = np.flatnonzero(np.diff(np.r_[0, self.fixed != 0, 0]))
        for start, end in zip(edges[::2], edges[1::2]):          # runs of words with fixed bytes
            differ = words[:, start:end] ^ self.template[start:end]
            differ &= self.fixed[start:end]
            same &= differ.max(axis=1) == 0
        return same

    def decode(self, block: Bytes) -> dict[str, npt.NDArray[Any]]:
        """The numbers of every row of ``block``: name → (m, count) in native byte order."""
        out = {}
        for name, (offset, dtype, count) in self.fields.items():
            raw = np.ascontiguousarray(block[:, offset:offset + dtype.itemsize * count])
            out[name] = raw.view(dtype).astype(dtype.newbyteorder("="), copy=False)
        return out

    def encode(self, values: dict[str, npt.ArrayLike], rows: int) -> Bytes:
        """(rows, size) bytes: this layout's message with every field set to its row of ``values``."""
        block = np.tile(self.template.view(np.uint8)[:self.size], (rows, 1))
        for name, (offset, dtype, count) in self.fields.items():
            column = np.ascontiguousarray(np.broadcast_to(values[name], (rows, count)), dtype=dtype)
            block[:, offset:offset + dtype.itemsize * count] = column.view(np.uint8).reshape(rows, -1)
        return block


def _items(buffer: Bytes, width: int) -> npt.NDArray[np.void]:
    """Every ``width``-byte run of ``buffer`` (one per start byte) as one item, so that fancy indexing copies
    whole runs (several times faster than rows of a byte-wise sliding window)."""
    return np.ndarray((len(buffer) - width + 1,), dtype=np.dtype((np.void, width)), buffer=buffer, strides=(1,))


def windows(buffer: Bytes, starts: npt.NDArray[np.int64], width: int) -> Bytes:
    """(m, width) copies of ``buffer[start:start + width]``."""
    return _items(buffer, width)[starts].view(np.uint8).reshape(len(starts), width)


def scatter(buffer: Bytes, starts: npt.NDArray[np.int64], rows: Bytes) -> None:
    """``buffer[start:start + width] = row`` for every start and (m, width) row."""
    width = rows.shape[1]
    if width and len(starts):
        _items(buffer, width)[starts] = np.ascontiguousarray(rows).view(np.dtype((np.void, width)))[:, 0]
