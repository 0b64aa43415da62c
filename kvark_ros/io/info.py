"""Summarise a bag (storage, time span, topics) for messages and the CLI."""

from __future__ import annotations

import os
from typing import Any

from kvark_ros.io.common import PathLike
from kvark_ros.io.reader import open_reader, resolve_bag

__all__ = ["bag_info", "topic_types"]


def bag_info(path: PathLike) -> dict[str, Any]:
    """Summary of a bag for messages and the CLI.

    Returns {'path', 'storage' ('mcap'|'sqlite3'), 'start' s, 'end' s,
    'duration' s, 'message_count', 'topics': {topic: {'type', 'count'}}}.
    """
    with open_reader(path) as (given, reader):
        target = resolve_bag(path)[1]
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


def topic_types(path: PathLike) -> dict[str, set[str]]:
    """topic → the message types recorded on it (``bag_info``'s topics)."""
    return {topic: set(entry["type"].split("|")) for topic, entry in bag_info(path)["topics"].items()}
