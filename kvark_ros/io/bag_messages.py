"""Some topics of a bag as their serialised messages, in log order: what ``kvark play`` publishes bit for bit.

Errors are the reader's (:class:`BagError`, one line naming the fix): a path that is not a bag, a corrupt or
truncated file, a topic the bag lacks (with the config key that names it and the bag's topics of that type), a
topic of a message type the caller cannot take.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from kvark_ros.io.common import PathLike
from kvark_ros.io.reader import open_reader
from kvark_ros.io.runs import bag_error
from kvark_ros.io.topic_hints import missing_topic

__all__ = ["TopicMessages", "read_messages"]


@dataclass(frozen=True)
class TopicMessages:
    """Messages of ``topics`` in log order: message k, of ``topics[topic[k]]`` (type ``msgtypes[topic[k]]``),
    logged at ``log_ns[k]``, is ``data[k]`` (its CDR bytes as stored)."""

    topics: tuple[str, ...]
    msgtypes: tuple[str, ...]
    log_ns: npt.NDArray[np.int64]
    topic: npt.NDArray[np.intp]
    data: list[bytes]

    def __len__(self) -> int:
        return len(self.data)

    def __iter__(self) -> Iterator[tuple[int, int, bytes]]:
        """(log time ns, topic index, CDR bytes) of each message, in log order."""
        return zip(self.log_ns.tolist(), self.topic.tolist(), self.data)

    @property
    def duration(self) -> float:
        """Log time from the first message to the last, s."""
        return float(self.log_ns[-1] - self.log_ns[0]) / 1e9 if len(self.data) else 0.0


def read_messages(path: PathLike, topics: Mapping[str, tuple[str, set[str]]]) -> TopicMessages:
    """The messages of ``topics`` (topic → (the config key that names it, the message types taken)) in ``path``
    (a bag directory or its .mcap/.db3 file), in log order."""
    with open_reader(path) as (given, reader):
        types: dict[str, set[str]] = {}
        for connection in reader.connections:
            types.setdefault(connection.topic, set()).add(connection.msgtype)
        msgtypes = []
        for topic, (key, allowed) in topics.items():
            if topic not in types:
                raise missing_topic(given, f"topic {topic} ({key}) is absent", topic, key, types, allowed,
                                    exclude=tuple(topics))
            if len(types[topic]) != 1 or not types[topic] <= allowed:
                raise bag_error(given, f"topic {topic} ({key}) has type {'|'.join(sorted(types[topic]))}, expected "
                                       f"{' or '.join(sorted(allowed))}", f"set {key} to a topic of that type")
            msgtypes.append(next(iter(types[topic])))
        order = {topic: k for k, topic in enumerate(topics)}
        connections = [connection for connection in reader.connections if connection.topic in order]
        log_ns, which, data = [], [], []
        try:
            for connection, stamp, raw in reader.messages(connections=connections):
                log_ns.append(stamp)
                which.append(order[connection.topic])
                data.append(bytes(raw))
        except Exception as exc:  # rosbags raises ReaderError, sqlite3 and decompression errors
            raise bag_error(given, f"cannot read bag, it is corrupt or truncated ({exc or type(exc).__name__})",
                            "re-record it") from exc
    return TopicMessages(tuple(topics), tuple(msgtypes), np.array(log_ns, dtype=np.int64),
                         np.array(which, dtype=np.intp), data)
