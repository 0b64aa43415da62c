"""The column mapping of ``kvark import``: which columns of a log are time, q, q̇, τ and the rest.

A mapping is a small YAML file (``--mapping``), overridden key by key by the command's flags::

    format: csv                      # csv | npz | mat; default from the file suffix
    header: true                     # false: a text log without a header row; columns are named by position,
                                     # 1 for the first, and a list may hold ranges: position: 2-7
    time: {column: timestamp, unit: s, offset: 0.0}    # unit s | ms | us | ns; offset in s after scaling
    first_index: 0                   # what {i} counts from for the first joint: 0 or 1
    joints: [shoulder_pan_joint, ...]                   # or --joints, or --config's robot_model.joint_names
    position: actual_q_{i}           # a pattern with {i}, or a list (or comma-separated string) of columns
    velocity: {pattern: actual_qd_{i}, scale: 1.0}
    effort: {pattern: actual_current_{i}, scale: [k0, k1, k2, k3, k4, k5]}   # one factor, or one per joint
    command: target_moment_{i}
    wrench: {columns: [fx, fy, fz, tx, ty, tz], frame: tool0}                # force N, torque N·m
    external_torque: {pattern: "tau_ext:{i}", first_index: 0}
    differentiate_velocity: false
    topics: {joint_states: /joint_states, effort_commands: /effort_commands, wrench: /ft_sensor/wrench,
             external_torque: /ground_truth/external_joint_torque}

A headerless log (``header: false``, ``--no-header``) names its columns ``1`` … ``N``: ``time: 1``,
``position: 2-7`` (a range, one column per joint), ``effort: {columns: 14-19, scale: [...]}``.
Scale factors turn the log's units into SI (degrees → rad: 0.0174533; a motor current → joint torque:
the torque constant times the gear ratio, N·m/A). Every problem is one ``ConfigError`` naming the key.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, fields, replace
from typing import Any

from kvark_ros.core.config import ConfigError
from kvark_ros.io import TopicNames
from kvark_ros.io.tables import FORMATS

__all__ = ["FIELDS", "TIME_UNITS", "FieldSpec", "Mapping", "merge_flags", "parse_mapping"]

FIELDS = ("position", "velocity", "effort", "command", "wrench", "external_torque")
JOINT_FIELDS = ("position", "velocity", "effort", "command", "external_torque")
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
TOPIC_KEYS = tuple(f.name for f in fields(TopicNames))
_TOP_KEYS = ("format", "time", "first_index", "joints", *FIELDS, "differentiate_velocity", "topics", "header")
_FIELD_KEYS = ("columns", "pattern", "scale", "first_index", "frame")


@dataclass(frozen=True)
class FieldSpec:
    """One field's columns: an explicit list or a pattern with ``{i}``; ``scale`` has 1 or one-per-column values."""

    name: str
    columns: tuple[str, ...] | None
    pattern: str | None
    scale: tuple[float, ...]
    first_index: int | None
    frame: str | None

    def column_names(self, count: int, first_index: int) -> list[str]:
        """The ``count`` column names of this field (``{i}`` counts from this field's or the mapping's first_index)."""
        if self.pattern is not None:
            start = first_index if self.first_index is None else self.first_index
            return [self.pattern.replace("{i}", str(start + k)) for k in range(count)]
        assert self.columns is not None
        if len(self.columns) != count:
            raise ConfigError(f"mapping: {self.name} lists {len(self.columns)} columns, expected {count}"
                              f"{' (fx fy fz tx ty tz)' if self.name == 'wrench' else ' (one per joint)'}")
        return list(self.columns)

    def factors(self, count: int) -> list[float]:
        """One scale factor per column."""
        if len(self.scale) == 1:
            return list(self.scale) * count
        if len(self.scale) != count:
            raise ConfigError(f"mapping: {self.name}.scale has {len(self.scale)} values, expected 1 or {count}")
        return list(self.scale)


@dataclass(frozen=True)
class Mapping:
    """A parsed mapping (module docstring)."""

    time: str
    time_unit: str
    time_offset: float
    first_index: int
    joints: tuple[str, ...] | None
    fields: dict[str, FieldSpec]
    differentiate_velocity: bool
    format: str | None
    topics: TopicNames
    header: bool = True


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"mapping: {what} must be a finite number, got {value!r}")
    return float(value)


def _position(x: Any) -> bool:
    """A column number as YAML writes it (a headerless log's column)."""
    return isinstance(x, int) and not isinstance(x, bool) and x >= 1


def _names(value: Any, what: str) -> tuple[str, ...]:
    """A list of strings (or column numbers), or one comma-separated string."""
    items = value.split(",") if isinstance(value, str) else [value] if _position(value) else value
    if not isinstance(items, list) or not items or not all(
            (isinstance(x, str) and x.strip()) or _position(x) for x in items):
        raise ConfigError(f"mapping: {what} must be a non-empty list of names, got {value!r}")
    return tuple(str(x).strip() for x in items)


def column_range(name: str) -> list[str]:
    """``A-B`` (column numbers of a headerless log, A ≤ B) as the names A … B; any other name as itself."""
    first, dash, last = name.partition("-")
    if not dash or not first.isdigit() or not last.isdigit():
        return [name]
    if int(first) < 1 or int(last) < int(first):
        raise ConfigError(f"mapping: column range {name!r} must count up from 1 or more (e.g. 2-7)")
    return [str(k) for k in range(int(first), int(last) + 1)]


def _first_index(value: Any, what: str) -> int:
    if value not in (0, 1) or isinstance(value, bool):
        raise ConfigError(f"mapping: {what} must be 0 or 1 (what {{i}} counts from), got {value!r}")
    return int(value)


def _field_form(name: str, value: Any) -> dict[str, Any]:
    """A field's mapping form ({columns|pattern, scale, first_index, frame}) from a pattern, a list or a mapping."""
    if isinstance(value, (str, list)):
        return {"pattern" if isinstance(value, str) and "{i}" in value else "columns": value}
    if not isinstance(value, dict):
        raise ConfigError(f"mapping: {name} must be a pattern with {{i}}, a list of columns or a mapping, "
                          f"got {value!r}")
    return dict(value)


def _field(name: str, value: Any) -> FieldSpec:
    """One field from its YAML form (``_field_form``), checked."""
    value = _field_form(name, value)
    unknown = sorted(set(value) - set(_FIELD_KEYS))
    if unknown:
        raise ConfigError(f"mapping: unknown key '{name}.{unknown[0]}'; allowed: {', '.join(_FIELD_KEYS)}")
    if ("columns" in value) == ("pattern" in value):
        raise ConfigError(f"mapping: {name} needs exactly one of 'columns' and 'pattern'")
    pattern = value.get("pattern")
    if pattern is not None and (not isinstance(pattern, str) or "{i}" not in pattern):
        raise ConfigError(f"mapping: {name}.pattern must contain {{i}} (the joint index), got {pattern!r}")
    scale = value.get("scale", 1.0)
    scales = tuple(_number(x, f"{name}.scale") for x in (scale if isinstance(scale, list) else [scale]))
    frame = value.get("frame")
    if frame is not None and (name != "wrench" or not isinstance(frame, str) or not frame):
        raise ConfigError(f"mapping: {name}.frame is only for wrench, as the sensor's frame name")
    return FieldSpec(name, _names(value["columns"], f"{name}.columns") if "columns" in value else None, pattern,
                     scales, None if "first_index" not in value else _first_index(value["first_index"],
                                                                                  f"{name}.first_index"), frame)


def _time(value: Any) -> tuple[str, str, float]:
    if isinstance(value, str) or _position(value):
        value = {"column": value}
    if isinstance(value, dict) and _position(value.get("column")):
        value = {**value, "column": str(value["column"])}
    if not isinstance(value, dict) or not isinstance(value.get("column"), str) or not value["column"]:
        raise ConfigError("mapping: time needs a column (time: NAME or time: {column: NAME, unit: s}); "
                          "or pass --time NAME")
    unknown = sorted(set(value) - {"column", "unit", "offset"})
    if unknown:
        raise ConfigError(f"mapping: unknown key 'time.{unknown[0]}'; allowed: column, unit, offset")
    unit = value.get("unit", "s")
    if unit not in TIME_UNITS:
        raise ConfigError(f"mapping: time.unit {unit!r} is not one of {', '.join(TIME_UNITS)}")
    return value["column"], unit, _number(value.get("offset", 0.0), "time.offset")


def parse_mapping(document: Any) -> Mapping:
    """Validate a mapping document (the YAML with the flags merged in, see ``merge_flags``)."""
    if not isinstance(document, dict):
        raise ConfigError("mapping: expected a YAML mapping of keys such as time, position, velocity")
    unknown = sorted(set(document) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(f"mapping: unknown key '{unknown[0]}'; allowed: {', '.join(_TOP_KEYS)}")
    fmt = document.get("format")
    if fmt is not None and fmt not in FORMATS:
        raise ConfigError(f"mapping: format {fmt!r} is not one of {', '.join(FORMATS)}")
    topics = document.get("topics", {})
    if not isinstance(topics, dict) or set(topics) - set(TOPIC_KEYS) or not all(
            isinstance(v, str) and v for v in topics.values()):
        raise ConfigError(f"mapping: topics must map some of {', '.join(TOPIC_KEYS)} to topic names")
    joints = document.get("joints")
    specs = {name: _field(name, document[name]) for name in FIELDS if document.get(name) is not None}
    if "wrench" in specs and specs["wrench"].frame is None:
        raise ConfigError("mapping: wrench needs the sensor's frame name (wrench: {frame: F, ...} or --wrench-frame F)")
    header = document.get("header", True)
    if not isinstance(header, bool):
        raise ConfigError(f"mapping: header must be true or false (a log without a header row), got {header!r}")
    if not header:
        specs = {name: replace(spec, columns=tuple(c for column in spec.columns for c in column_range(column)))
                 if spec.columns is not None else spec for name, spec in specs.items()}
    differentiate = document.get("differentiate_velocity", False)
    if not isinstance(differentiate, bool):
        raise ConfigError(f"mapping: differentiate_velocity must be true or false, got {differentiate!r}")
    return Mapping(*_time(document.get("time")), _first_index(document.get("first_index", 0), "first_index"),
                   None if joints is None else _names(joints, "joints"), specs, differentiate, fmt,
                   TopicNames(**topics), header)


def merge_flags(document: dict[str, Any], flags: dict[str, Any]) -> dict[str, Any]:
    """The mapping document with the command's flags on top (a copy).

    ``flags`` holds the flag values that were given: ``time``, ``time_unit``, ``time_offset``, ``first_index``,
    ``format``, ``differentiate_velocity``, ``header``, ``wrench_frame``, a field name → pattern or comma-separated
    columns, ``scale`` → {field: [factors]} and ``topics`` → {key: topic}.
    """
    merged = copy.deepcopy(document)
    time = merged.get("time")
    time = dict(time) if isinstance(time, dict) else ({"column": time} if time is not None else {})
    for flag, key in (("time", "column"), ("time_unit", "unit"), ("time_offset", "offset")):
        if flag in flags:
            time[key] = flags[flag]
    if time:
        merged["time"] = time
    for key in ("first_index", "format", "differentiate_velocity", "header"):
        if key in flags:
            merged[key] = flags[key]
    for name in FIELDS:
        spec = {} if merged.get(name) is None else _field_form(name, merged[name])
        if name in flags:
            spec = {k: v for k, v in spec.items() if k not in ("columns", "pattern")}
            spec["pattern" if "{i}" in flags[name] else "columns"] = flags[name]
        if name in flags.get("scale", {}):
            spec["scale"] = flags["scale"][name]
        if name == "wrench" and "wrench_frame" in flags:
            spec["frame"] = flags["wrench_frame"]
        if spec:
            merged[name] = spec
    if flags.get("topics"):
        merged["topics"] = {**(merged.get("topics") or {}), **flags["topics"]}
    return merged

