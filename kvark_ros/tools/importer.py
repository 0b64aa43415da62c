"""``kvark import``: a robot's own log (CSV or text, NPZ, MAT) as a ROS 2 bag the other commands read.

The columns a mapping names (a --mapping YAML, see kvark_ros/tools/import_mapping.py, or the field
flags) become ``/joint_states`` (q, q̇, effort) and optionally ``/effort_commands`` (commanded torque,
Float64MultiArray labelled with the joint names), ``/ft_sensor/wrench`` (WrenchStamped) and
``/ground_truth/external_joint_torque`` (JointState effort). Stamps are kept as the log has them, never
resampled. Rows are dropped, and counted, when their time, position, velocity or effort is not finite,
or when their stamp (to the nanosecond a bag stores) repeats or goes back: a row whose stamp is not
after every earlier one is a logging glitch, and the estimator needs strictly increasing time. A
non-finite command, wrench or external torque leaves only that message out. The bag's metadata names
the log (``kvark_ros.source: import: <file>``), so its ground truth is not taken for a simulator's. The
bag is written atomically by ``kvark_ros.io.BagWriter``: a failed import leaves no partial bag, and an
existing output is replaced only with ``--force``.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kvark_ros.core.config import ConfigError, load_config
from kvark_ros.core.files import check_output, read_yaml
from kvark_ros.io import (BagError, CommandSeries, JointStateSeries, RecordedRun, TopicNames, WrenchSeries,
                          write_run)
from kvark_ros.io.common import FloatArray
from kvark_ros.io.tables import FORMATS, Table, read_table, table_format
from kvark_ros.tools.import_mapping import FIELDS, TIME_UNITS, Mapping, merge_flags, parse_mapping

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

_FLAG_TOPICS = {"joint_states_topic": "joint_states", "effort_commands_topic": "effort_commands",
                "wrench_topic": "wrench", "external_torque_topic": "external_torque"}


def _fail(path: str | os.PathLike[str], problem: str, fix: str) -> BagError:
    return BagError(f"{os.fspath(path)}: {problem}; {fix}")


@dataclass
class ImportReport:
    """What an import did: rows read, dropped (reason → rows), messages left out, kept stamps, notes."""

    rows: int
    dropped: dict[str, int]
    left_out: dict[str, int] = field(default_factory=dict)
    stamp: FloatArray = field(default_factory=lambda: np.empty(0))
    notes: list[str] = field(default_factory=list)


def _values(table: Table, mapping: Mapping, name: str, count: int, rows: int) -> FloatArray:
    """(rows, count) values of one field, scaled to SI."""
    spec = mapping.fields[name]
    names = spec.column_names(count, mapping.first_index)
    return np.column_stack([table.column(column, rows) * factor
                            for column, factor in zip(names, spec.factors(count))])


def _check_fields(mapping: Mapping) -> None:
    present = set(mapping.fields)
    if "position" not in present:
        raise ConfigError("mapping: position is required (a pattern such as q_{i}, or --position)")
    if "velocity" not in present and not mapping.differentiate_velocity:
        raise ConfigError("mapping: no velocity columns; map velocity (--velocity) or pass --differentiate-velocity "
                          "to take a central difference of the position on the stamps")
    if "velocity" in present and mapping.differentiate_velocity:
        raise ConfigError("mapping: velocity columns are mapped and --differentiate-velocity is set; choose one")
    if not present & {"effort", "command"}:
        raise ConfigError("mapping: no joint torque; map effort (measured, --effort) or command (commanded, "
                          "--command) or both")


def _kept_rows(stamp: FloatArray, finite: np.ndarray, report: ImportReport) -> np.ndarray:
    """Rows with finite joint-state values whose stamp (in ns) comes after every earlier row's."""
    rows = np.flatnonzero(finite)
    report.dropped["non-finite time, position, velocity or effort"] = int((~finite).sum())
    ns = np.rint(stamp[rows] * 1e9)
    before = np.concatenate(([-np.inf], np.maximum.accumulate(ns)[:-1])) if rows.size else ns
    report.dropped["repeated stamp"] = int((ns == before).sum())
    report.dropped["stamp before an earlier row's"] = int((ns < before).sum())
    return rows[ns > before]


def build_run(table: Table, mapping: Mapping, joints: tuple[str, ...]) -> tuple[RecordedRun, ImportReport]:
    """The run a table holds under ``mapping`` (module docstring), and what was dropped on the way."""
    _check_fields(mapping)
    raw_time = table.column(mapping.time)
    rows, n = raw_time.shape[0], len(joints)
    stamp = raw_time * TIME_UNITS[mapping.time_unit] + mapping.time_offset
    values = {name: _values(table, mapping, name, 6 if name == "wrench" else n, rows) for name in mapping.fields}
    report = ImportReport(rows, {})
    state = [values[name] for name in ("position", "velocity", "effort") if name in values]
    finite = np.isfinite(stamp) & np.all([np.isfinite(v).all(axis=1) for v in state], axis=0)
    kept = _kept_rows(stamp, finite, report)
    if kept.size == 0:
        raise _fail(table.path, f"no usable rows among {rows} ({_dropped_text(report)})",
                    "check the time and joint columns of the mapping")
    t = np.rint(stamp[kept] * 1e9) / 1e9
    if t[0] < 0.0:
        raise _fail(table.path, f"stamps start at {t[0]:.9g} s, a bag needs them >= 0",
                    f"pass --time-offset {-np.floor(t[0]):.0f} (s added to every stamp)")
    report.stamp = t
    q = values["position"][kept]
    if mapping.differentiate_velocity:
        if kept.size < 2:
            raise _fail(table.path, "one usable row: no velocity can be differentiated", "import a longer log")
        qd = np.gradient(q, t, axis=0)
        report.notes.append("velocity: central difference of the position on the kept stamps (one-sided at the "
                            "ends), --differentiate-velocity")
    else:
        qd = values["velocity"][kept]
    effort = values["effort"][kept] if "effort" in values else np.full_like(q, np.nan)
    if "effort" not in values:
        report.notes.append("effort: not mapped, written as NaN (τ_m comes from the commands)")
    elif "command" not in values:
        report.notes.append("τ_m is the effort of /joint_states (offline the commands' fallback; for the live "
                            "node set input.torque_source: joint_states_effort)")
    topics = mapping.topics

    def optional(name: str, topic: str) -> tuple[FloatArray, FloatArray] | None:
        if name not in values:
            return None
        data = values[name][kept]
        good = np.isfinite(data).all(axis=1)
        if not good.all():
            report.left_out[topic] = int((~good).sum())
        return (t[good], data[good]) if good.any() else None

    command = optional("command", topics.effort_commands)
    wrench = optional("wrench", topics.wrench)
    external = optional("external_torque", topics.external_torque)
    run = RecordedRun(
        joint_states=JointStateSeries(t, joints, q, qd, effort),
        commands=None if command is None else CommandSeries(*command),
        wrench=None if wrench is None else WrenchSeries(wrench[0], mapping.fields["wrench"].frame or "",
                                                        wrench[1][:, :3], wrench[1][:, 3:]),
        external_torque=None if external is None else JointStateSeries(
            external[0], joints, np.zeros_like(external[1]), np.zeros_like(external[1]), external[1]),
        source=f"import: {table.path.name}")
    return run, report


def _dropped_text(report: ImportReport) -> str:
    parts = [f"{count} {reason}" for reason, count in report.dropped.items() if count]
    return ", ".join(parts) if parts else "none"


def rate_text(stamp: FloatArray) -> str:
    """Median rate and the spread of the time steps: ``100.0 Hz median (step 10 ms; 5-95 %: 9.1-10.9 ms; ...)``."""
    if stamp.size < 2:
        return "one sample, no rate"
    step = np.diff(stamp) * 1e3
    low, median, high = np.percentile(step, [5, 50, 95])
    return (f"{1e3 / median:.1f} Hz median (step {median:.3g} ms; 5-95 %: {low:.3g}-{high:.3g} ms; "
            f"longest {step.max():.3g} ms), {stamp[-1] - stamp[0]:.3f} s from {stamp[0]:.6f} s")


def _joints(args: argparse.Namespace, mapping: Mapping) -> tuple[str, ...]:
    """--joints, else the mapping's joints, else the config's robot_model.joint_names."""
    if args.joints is not None:
        names = tuple(name.strip() for name in args.joints.split(","))
        if not all(names) or len(set(names)) != len(names):
            raise ConfigError(f"--joints {args.joints!r}: expected distinct, non-empty names separated by commas")
        return names
    if mapping.joints is not None:
        if len(set(mapping.joints)) != len(mapping.joints):
            raise ConfigError(f"mapping: joints {list(mapping.joints)} name a joint twice")
        return mapping.joints
    if args.config:
        return tuple(load_config(args.config).joint_names)
    raise ConfigError("no joint names: pass --joints a,b,c, or --config FILE (its robot_model.joint_names), "
                      "or write joints: [...] in the mapping")


def _flags(args: argparse.Namespace) -> dict[str, object]:
    """The mapping keys the flags set (``import_mapping.merge_flags``)."""
    flags: dict[str, object] = {key: getattr(args, key) for key in (
        "time", "time_unit", "time_offset", "first_index", "format", "wrench_frame", *FIELDS)
        if getattr(args, key) is not None}
    if args.differentiate_velocity:
        flags["differentiate_velocity"] = True
    if args.no_header:
        flags["header"] = False
    scale: dict[str, list[float]] = {}
    for item in args.scale:
        name, _, text = item.partition("=")
        if name not in FIELDS or not text:
            raise ConfigError(f"--scale {item!r}: expected FIELD=X or FIELD=X1,...,Xn with FIELD one of "
                              f"{', '.join(FIELDS)}")
        try:
            factors = [float(x) for x in text.split(",")]
        except ValueError:
            raise ConfigError(f"--scale {item!r}: the factors must be numbers") from None
        scale[name] = factors
    flags["scale"] = scale
    flags["topics"] = {key: getattr(args, flag) for flag, key in _FLAG_TOPICS.items() if getattr(args, flag)}
    return flags


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "import", help="convert a robot log (CSV/text, NPZ, MAT) into a ROS 2 bag",
        description=__doc__.split("\n\n")[1].replace("``", ""), formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="A field SPEC is a pattern with {i}, the joint index (actual_q_{i}, q{i}; q:{i} is column i of an\n"
               "NPZ/MAT array q), or comma-separated column names in joint order (wrench: fx,fy,fz,tx,ty,tz).\n"
               "Flags override the --mapping file key by key (see examples/ur_rtde_mapping.yaml).")
    parser.add_argument("input", help="the log: .csv/.txt/.log/.tsv/.dat (header row, or see --no-header; comma, "
                                      "semicolon or whitespace delimited), .npz or .mat")
    parser.add_argument("--out", required=True, metavar="BAG",
                        help="bag directory to write (new or empty; see --force)")
    parser.add_argument("--mapping", metavar="FILE", help="YAML column mapping (examples/*_mapping.yaml)")
    parser.add_argument("--format", choices=FORMATS, help="input format (default: from the file suffix)")
    parser.add_argument("--force", action="store_true", help="replace an existing --out (only once the new bag is "
                                                             "complete)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="bag storage (default mcap)")
    parser.add_argument("--no-header", action="store_true",
                        help="the text log has no header row: its columns are named by position, 1 for the first, "
                             "and a field may name a range (--time 1 --position 2-7)")
    names = parser.add_argument_group("time and joints")
    names.add_argument("--time", metavar="COLUMN", help="time column")
    names.add_argument("--time-unit", choices=tuple(TIME_UNITS), help="unit of the time column (default s)")
    names.add_argument("--time-offset", type=float, metavar="S", help="seconds added to every stamp after the unit "
                                                                      "(bags need stamps >= 0; default 0)")
    names.add_argument("--joints", metavar="A,B,C", help="joint names in column order (default: the mapping's "
                                                         "joints, else --config's robot_model.joint_names)")
    names.add_argument("--config", metavar="FILE", help="estimator config whose robot_model.joint_names name the "
                                                        "joints")
    names.add_argument("--first-index", type=int, choices=(0, 1), help="what {i} counts from for the first joint "
                                                                       "(default 0)")
    fields_group = parser.add_argument_group("fields (SPEC: pattern with {i} or comma-separated columns)")
    for name, meaning in (("position", "joint position q, rad (or m)"),
                          ("velocity", "joint velocity q̇, rad/s (or m/s)"),
                          ("effort", "measured joint torque τ_m, N·m (or a current, with --scale)"),
                          ("command", "commanded joint torque, N·m (written to /effort_commands)"),
                          ("wrench", "wrist F/T: fx fy fz (N) tx ty tz (N·m), needs --wrench-frame"),
                          ("external_torque", "true external joint torque, N·m (ground truth)")):
        fields_group.add_argument(f"--{name.replace('_', '-')}", dest=name, metavar="SPEC", help=meaning)
    fields_group.add_argument("--scale", action="append", default=[], metavar="FIELD=X[,X...]",
                              help="factor(s) turning a field into SI, one or one per column, e.g. "
                                   "position=0.0174533 (degrees) or effort=k1,...,kn (N·m/A); repeatable")
    fields_group.add_argument("--wrench-frame", metavar="FRAME", help="URDF frame the F/T sensor measures in")
    fields_group.add_argument("--differentiate-velocity", action="store_true",
                              help="no velocity columns: q̇ by central difference of q on the kept stamps")
    topics = parser.add_argument_group("topics (defaults: the names every kvark command reads)")
    for flag, key in _FLAG_TOPICS.items():
        topics.add_argument(f"--{flag.replace('_', '-')}", dest=flag, metavar="TOPIC",
                            help=f"default {getattr(TopicNames(), key)}")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    check_output(out, args.force, (args.input, args.mapping))
    document = read_yaml(args.mapping, ConfigError, "mapping file", "pass an existing mapping YAML",
                         "pass a YAML mapping file") if args.mapping else {}
    if not isinstance(document, dict):
        raise ConfigError(f"{args.mapping}: expected a YAML mapping of keys such as time, position, velocity "
                          "(see examples/ur_rtde_mapping.yaml)")
    mapping = parse_mapping(merge_flags(document, _flags(args)))
    fmt = table_format(args.input, mapping.format)
    table = read_table(args.input, fmt, mapping.header)
    recorded, report = build_run(table, mapping, _joints(args, mapping))
    write_run(out, recorded, storage=args.storage, topics=mapping.topics, force=args.force)
    kept = report.stamp.size
    print(f"kvark import: {args.input} ({fmt}, {report.rows} rows, {len(table.columns)} columns) -> {out} "
          f"({args.storage})")
    print(f"  rows: {kept} of {report.rows} kept; dropped: {_dropped_text(report)}")
    print(f"  rate: {rate_text(report.stamp)}")
    for note in report.notes:
        print(f"  {note}")
    for topic, count in report.left_out.items():
        print(f"  {topic}: {count} of {kept} rows left out (non-finite values)")
    series = {mapping.topics.joint_states: recorded.joint_states, mapping.topics.effort_commands: recorded.commands,
              mapping.topics.wrench: recorded.wrench, mapping.topics.external_torque: recorded.external_torque}
    written = [f"{topic} ({item.stamp.size})" for topic, item in series.items() if item is not None]
    print(f"  wrote {', '.join(written)} for joints {', '.join(recorded.joint_names)}")
    return 0
