"""MCAP in bulk: every raw message of some channels at once, and a storage that writes many messages at once.

rosbags reads and writes MCAP one message record at a time in Python (reading alone costs about 2 µs a
message), which cost more than everything else a replay does but the estimator. Here whole chunks are
read and written as byte arrays:

- :func:`indexed_messages` finds a chunked, indexed file's messages through its message indexes (one
  (log time, offset) pair per message) and returns them as offsets into the mapped file. It returns None
  whenever it cannot vouch for giving exactly what rosbags' reader gives (compressed chunks, no index, an
  index that disagrees with the chunk's records): the caller then reads with rosbags.
- :class:`McapStorage` is a storage plugin for rosbags' ``Writer`` (its storage-writer protocol) whose
  :meth:`McapStorage.write_many` takes many messages at once. It writes what rosbags' MCAP storage
  writes: chunks closed after the record that takes them past 1 MiB, schema and channel records inside
  the chunk that is open when they are added, a message index per channel after each chunk, and the
  same summary, statistics and footer.

MCAP (https://mcap.dev/spec): records are an opcode byte, a uint64 length and a body, little endian; a
message record's body is channel id (uint16), sequence (uint32), log time and publish time (uint64 ns)
and the data.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.interfaces import Connection, MessageDefinitionFormat
from rosbags.rosbag2.enums import CompressionMode

from kvark_ros.io.cdr_arrays import WORD, scatter, windows

__all__ = ["McapStorage", "RawMessages", "indexed_messages"]

MAGIC = b"\x89MCAP0\r\n"
CHUNK_LIMIT = 1 << 20              # a chunk is closed after the record that takes it past this size
MESSAGE_HEAD = 31                  # opcode, length, channel, sequence, log time, publish time
LIBRARY = "kvark_ros"              # the header record's writer name
_HEAD = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                  ("log", "<u8"), ("publish", "<u8")])
_INDEX_HEAD = struct.Struct("<BQHI")     # message index: opcode, length, channel, byte length of its entries
_CHUNK_HEAD = struct.Struct("<BQQQQI")   # chunk: opcode, length, start, end, uncompressed size, crc

Int64s = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RawMessages:
    """Serialised messages in read order: message k is ``buffer[start[k]:start[k] + size[k]]``, logged at
    ``log_ns[k]`` on ``channel[k]``; ``buffer`` has at least ``WORD`` bytes after every message (for gathers
    in whole words)."""

    buffer: npt.NDArray[np.uint8]
    start: Int64s
    size: Int64s
    log_ns: Int64s
    channel: Int64s

    def message(self, k: int) -> bytes:
        """Message ``k``'s bytes."""
        return self.buffer[self.start[k]:self.start[k] + self.size[k]].tobytes()

    @classmethod
    def join(cls, parts: Sequence[bytes], start: Int64s, size: Int64s, log_ns: Int64s,
             channel: Int64s) -> RawMessages:
        """Concatenate ``parts`` (``start`` indexes the concatenation) and ``WORD`` zero bytes."""
        buffer = np.frombuffer(b"".join([*parts, bytes(WORD)]), np.uint8)
        return cls(buffer, start, size, log_ns, channel)


def indexed_messages(path: Path, chunks: Sequence[Any], channels: Collection[int]) -> RawMessages | None:
    """The messages of ``channels`` in the MCAP file ``path`` in rosbags' read order (log time, then file
    position), or None (module docstring). ``chunks``: the file's chunk index entries as rosbags parses them
    (start and end time, chunk and message index offsets). A chunk is used only when its indexed message
    records and other records tile it exactly, so rosbags, which walks every record, finds the same messages.
    The buffer is the file itself, mapped: message offsets are file offsets."""
    wanted = set(channels)
    try:
        data = np.memmap(path, dtype=np.uint8, mode="r")
    except (OSError, ValueError):  # a file system without memory maps: rosbags reads it
        return None
    entries: list[tuple[Int64s, Int64s, Int64s]] = []      # (log time, file offset, channel) per index
    for chunk in chunks:
        if wanted.isdisjoint(chunk.message_index_offsets):
            continue
        head = _chunk_head(data, chunk.chunk_start_offset)
        if head is None:
            return None
        start, size, crc = head
        records = data[start:start + size]
        if crc and zlib.crc32(records) != crc:
            return None
        indexes = {cid: _message_index(data, offset, cid) for cid, offset in chunk.message_index_offsets.items()}
        if not _tiled(records, indexes):
            return None
        for cid in wanted.intersection(indexes):
            index = indexes[cid]
            assert index is not None
            index = index[(index[:, 0] >= chunk.message_start_time) & (index[:, 0] <= chunk.message_end_time)]
            entries.append((index[:, 0].astype(np.int64), start + index[:, 1].astype(np.int64),
                            np.full(len(index), cid, np.int64)))
    empty = np.zeros(0, np.int64)
    log_ns, offset, channel = (np.concatenate(column) for column in zip(*entries)) if entries else (empty,) * 3
    order = np.lexsort((offset, log_ns))
    offset = offset[order]
    length = windows(data, offset + 1, WORD).view("<u8")[:, 0].astype(np.int64)
    return RawMessages(data, offset + MESSAGE_HEAD, length - (MESSAGE_HEAD - 9), log_ns[order], channel[order])


def _chunk_head(data: npt.NDArray[np.uint8], start: int) -> tuple[int, int, int] | None:
    """(file offset, size, CRC) of the records of the uncompressed chunk at file offset ``start``, or None
    (not a chunk, a compressed one (rosbags decompresses it), or one that ends the file)."""
    end = start + _CHUNK_HEAD.size + 12
    if end > len(data):
        return None
    op, _, _, _, size, crc = _CHUNK_HEAD.unpack_from(data, start)
    compression, stored = struct.unpack_from("<IQ", data, start + _CHUNK_HEAD.size)
    if op != 0x06 or compression or stored != size or end + size + WORD > len(data):
        return None
    return end, size, crc


def _message_index(data: npt.NDArray[np.uint8], offset: int, channel: int) -> npt.NDArray[np.uint64] | None:
    """A chunk's message index for ``channel`` at file ``offset``: (k, 2) log time and record offset, or None."""
    if offset + _INDEX_HEAD.size > len(data):
        return None
    op, _, cid, length = _INDEX_HEAD.unpack_from(data, offset)
    if op != 0x07 or cid != channel or length % 16 or offset + _INDEX_HEAD.size + length > len(data):
        return None
    return np.frombuffer(data, "<u8", count=length // 8, offset=offset + _INDEX_HEAD.size).reshape(-1, 2)


def _tiled(records: npt.NDArray[np.uint8], indexes: Mapping[int, npt.NDArray[np.uint64] | None]) -> bool:
    """Whether every index entry points at a message record of its channel logged at its time, and these
    records with the other, non-message records between them cover the chunk exactly, without overlap."""
    if any(index is None for index in indexes.values()):
        return False
    found = [(index, cid) for cid, index in indexes.items() if index is not None and len(index)]
    if not found:
        return _walk_others(records, 0, len(records))
    index = np.concatenate([index for index, _ in found])
    channel = np.concatenate([np.full(len(index), cid) for index, cid in found])
    offsets = index[:, 1].astype(np.int64)
    if offsets.max() + MESSAGE_HEAD > len(records):
        return False
    order = np.argsort(offsets)
    heads = windows(records, offsets[order], MESSAGE_HEAD).view(_HEAD)[:, 0]
    starts, ends = offsets[order], offsets[order] + 9 + heads["length"].astype(np.int64)
    if not (np.all(heads["op"] == 0x05) and np.all(heads["channel"] == channel[order])
            and np.all(heads["log"] == index[order, 0]) and np.all(heads["length"] >= MESSAGE_HEAD - 9)
            and ends[-1] <= len(records) and np.all(starts[1:] >= ends[:-1])):
        return False
    gaps = np.flatnonzero(np.r_[starts[0] > 0, starts[1:] > ends[:-1], ends[-1] < len(records)])
    bounds = np.r_[0, ends], np.r_[starts, len(records)]
    return all(_walk_others(records, int(bounds[0][k]), int(bounds[1][k])) for k in gaps)


def _walk_others(records: npt.NDArray[np.uint8], start: int, end: int) -> bool:
    """Whether ``records[start:end]`` is a run of whole records none of which is a message."""
    while start < end:
        if start + 9 > end or records[start] == 0x05:
            return False
        start += 9 + int.from_bytes(records[start + 1:start + 9].tobytes(), "little")
    return start == end


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _record(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


class McapStorage:
    """MCAP storage for rosbags' ``Writer`` (module docstring); rosbags' MCAP storage without compression."""

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        if compression != CompressionMode.NONE:
            raise ValueError("McapStorage writes uncompressed chunks only")
        self.path = path / f"{path.name}.mcap"
        self.bio = self.path.open("xb")
        self.bio.write(MAGIC + _record(0x01, _string("ros2") + _string(LIBRARY)))
        self.schemas: list[bytes] = []
        self.schema_ids: dict[str, int] = {}
        self.channels: list[bytes] = []
        self.chunk_indexes: list[bytes] = []
        self.counts: dict[int, int] = {}
        self.start, self.end = 2**63 - 1, 0
        self._new_chunk()

    def _new_chunk(self) -> None:
        self.parts: list[bytes | memoryview] = []
        self.size = 0
        self.index: list[tuple[Int64s, Int64s, Int64s]] = []   # (channel, log time, offset) of its messages

    def _add(self, data: bytes | memoryview) -> None:
        self.parts.append(data)
        self.size += len(data)

    def add_msgtype(self, connection: Connection) -> None:
        """Register ``connection``'s message type (a schema record)."""
        self.schema_ids[connection.msgtype] = len(self.schemas) + 1
        encoding = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        self.schemas.append(_record(0x03, struct.pack("<H", len(self.schemas) + 1) + _string(connection.msgtype)
                                    + _string(encoding) + _string(connection.msgdef.data)))
        self._add(self.schemas[-1])

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        """Register ``connection`` (a channel record)."""
        metadata = _string("offered_qos_profiles") + _string(offered_qos_profiles)
        self.channels.append(_record(0x04, struct.pack("<HH", connection.id, self.schema_ids[connection.msgtype])
                                     + _string(connection.topic) + _string(connection.ext.serialization_format)
                                     + struct.pack("<I", len(metadata)) + metadata))
        self.counts[connection.id] = 0
        self._add(self.channels[-1])

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        """Write one message."""
        payload = np.frombuffer(data, np.uint8)[None, :]
        self.write_many(np.array([connection.id]), np.array([timestamp], np.int64), [payload],
                         np.zeros(1, np.intp), np.zeros(1, np.intp))

    def write_many(self, channel: npt.NDArray[Any], log_ns: Int64s, payloads: Sequence[npt.NDArray[np.uint8]],
                    block: npt.NDArray[np.intp], row: npt.NDArray[np.intp]) -> None:
        """Write messages in order: message k is on ``channel[k]`` at ``log_ns[k]`` with the data
        ``payloads[block[k]][row[k]]`` (each payload block (m, size) bytes)."""
        if not len(log_ns):
            return
        sizes = np.array([p.shape[1] for p in payloads], np.int64)[block] + MESSAGE_HEAD
        ends = np.cumsum(sizes)
        records = np.empty(int(ends[-1]), np.uint8)
        starts = ends - sizes
        heads = np.zeros(len(log_ns), _HEAD)
        heads["op"], heads["length"], heads["channel"] = 0x05, sizes - 9, channel
        heads["log"] = heads["publish"] = log_ns
        scatter(records, starts, heads.view(np.uint8).reshape(-1, MESSAGE_HEAD))
        for k, payload in enumerate(payloads):
            mine = np.flatnonzero(block == k)
            rows = row[mine]
            in_order = len(rows) == len(payload) and np.array_equal(rows, np.arange(len(rows)))
            scatter(records, starts[mine] + MESSAGE_HEAD, payload if in_order else payload[rows])
        channel = np.asarray(channel, np.int64)
        for cid, count in enumerate(np.bincount(channel)):
            if count:
                self.counts[cid] += int(count)
        first = 0
        while first < len(sizes):
            # rosbags closes a chunk after the record that takes it past the limit
            last = min(int(np.searchsorted(ends, CHUNK_LIMIT - self.size + starts[first], "right")), len(sizes) - 1)
            self.index.append((channel[first:last + 1], log_ns[first:last + 1],
                               starts[first:last + 1] - starts[first] + self.size))
            self._add(memoryview(records)[starts[first]:ends[last]])
            if self.size > CHUNK_LIMIT:
                self._close_chunk()
            first = last + 1
        self.start, self.end = min(self.start, int(log_ns.min())), max(self.end, int(log_ns.max()))

    def _close_chunk(self) -> None:
        channel, log_ns, offset = (np.concatenate(column) for column in zip(*self.index)) if self.index else \
            (np.zeros(0, np.int64),) * 3
        start = int(log_ns.min()) if len(log_ns) else 2**63 - 1
        end = int(log_ns.max()) if len(log_ns) else 0
        chunk_start = self.bio.tell()
        # body: start and end time, uncompressed size, CRC (0: none), compression "", compressed size, records
        self.bio.write(struct.pack("<BQQQQI", 0x06, 40 + self.size, start, end, self.size, 0)
                       + _string("") + struct.pack("<Q", self.size))
        for part in self.parts:
            self.bio.write(part)
        chunk_end = self.bio.tell()
        ids, first = np.unique(channel, return_index=True)
        offsets = []
        for cid in ids[np.argsort(first)]:                     # channels in the order they first appear
            mine = channel == cid
            entries = np.column_stack((log_ns[mine], offset[mine])).astype("<u8").tobytes()
            offsets.append(struct.pack("<HQ", cid, self.bio.tell()))
            self.bio.write(_record(0x07, struct.pack("<HI", cid, len(entries)) + entries))
        self.chunk_indexes.append(_record(0x08, struct.pack("<QQQQ", start, end, chunk_start, chunk_end - chunk_start)
                                          + struct.pack("<I", 10 * len(offsets)) + b"".join(offsets)
                                          + struct.pack("<Q", self.bio.tell() - chunk_end) + _string("")
                                          + struct.pack("<QQ", self.size, self.size)))
        self._new_chunk()

    def close(self, version: int, metadata: str) -> None:
        """Finish the file: the open chunk, the rosbag2 metadata record, the summary and the footer."""
        del version
        if self.size:
            self._close_chunk()
        bio = self.bio
        metadata_start = bio.tell()
        entry = _string("serialized_metadata") + _string(metadata)
        bio.write(_record(0x0C, _string("rosbag2") + struct.pack("<I", len(entry)) + entry))
        metadata_end = bio.tell()
        bio.write(_record(0x0F, struct.pack("<I", 0)))
        groups = []
        for op, records in ((0x03, self.schemas), (0x04, self.channels), (0x08, self.chunk_indexes)):
            groups.append((op, bio.tell()))
            bio.write(b"".join(records))
        summary_start = groups[0][1]
        groups.append((0x0D, bio.tell()))
        bio.write(_record(0x0D, struct.pack("<QQ", metadata_start, metadata_end - metadata_start)
                          + _string("rosbag2")))
        groups.append((0x0B, bio.tell()))
        counts = b"".join(struct.pack("<HQ", cid, count) for cid, count in sorted(self.counts.items()))
        bio.write(_record(0x0B, struct.pack("<QHIIIIQQI", sum(self.counts.values()), len(self.schemas),
                                            len(self.channels), 0, 1, len(self.chunk_indexes), self.start,
                                            self.end, len(counts)) + counts))
        offsets_start = bio.tell()
        ends = [start for _, start in groups[1:]] + [offsets_start]
        for (op, start), end in zip(groups, ends):
            if end != start:
                bio.write(_record(0x0E, struct.pack("<BQQ", op, start, end - start)))
        bio.write(_record(0x02, struct.pack("<QQI", summary_start, offsets_start, 0)) + MAGIC)
        bio.close()

    def abort(self) -> None:
        """Close the file unfinished (the caller removes it)."""
        self.bio.close()
