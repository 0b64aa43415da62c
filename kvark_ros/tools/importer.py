"""``kvark import``: a robot's own log (CSV or text, NPZ, MAT) as a ROS 2 bag the other commands read.

The columns a mapping names (a --mapping YAML, see kvark_ros/tools/import_mapping.py, or the field
flags) become ``/joint_states`` (q, q̇, effort) and optionally ``/effort_commands`` (commanded torque,
Float64MultiArray labelled with the joint names), ``/ft_sensor/wrench`` (WrenchStamped) and
``/ground_truth/external_joint_torque`` (JointState effort). Stamps are kept as the log has them, never
resampled. Real logs are messy: every row is checked and a row that fails is dropped, counted per reason
with where it is (first and last line), and the rest is imported. A line that holds no row (too few or too
many fields, a cell that is not a number) is dropped; a truncated last line (a logger stopped mid-line) with
a warning. A row is dropped when its time, position, velocity or effort is not finite or outside what the
arm can do: the URDF's limits with margins (with --config; generic bounds without), time strictly
increasing (a repeated stamp, to the nanosecond a bag stores, or one out of order costs its row), no stamp
far from the others, no position jump faster than the joint can move (the rule and its margins:
kvark_ros/core/estimation/sample_limits.py). A command, wrench or external torque that is not finite or
beyond those bounds leaves only that message out. ``--strict`` refuses the file at the first such row
instead; a file with too little left (fewer than two rows, or under half of them) is refused with one line
naming the main reason and its fix. The bag's metadata names the log (``kvark_ros.source: import: <file>``),
so its ground truth is not taken for a simulator's. The bag is written atomically by
``kvark_ros.io.BagWriter``: a failed import leaves no partial bag, and an existing output is replaced only
with ``--force``.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from kvark_ros.core.config import ConfigError, EstimatorConfig, load_config
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.sample_limits import (GENERIC_TORQUE, POSITION_MARGIN, TORQUE_FACTOR,
                                                     VELOCITY_FACTOR, RowCheck, SampleLimits, check_rows, counted,
                                                     drop_lines, span)
from kvark_ros.core.files import check_output, read_yaml
from kvark_ros.io import (BagError, CommandSeries, JointStateSeries, RecordedRun, TopicNames, WrenchSeries,
                          write_run)
from kvark_ros.io.common import FloatArray
from kvark_ros.io.tables import FORMATS, TRUNCATED_END, Table, read_table, table_format
from kvark_ros.tools.import_mapping import FIELDS, TIME_UNITS, Mapping, merge_flags, parse_mapping

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

_FLAG_TOPICS = {"joint_states_topic": "joint_states", "effort_commands_topic": "effort_commands",
                "wrench_topic": "wrench", "external_torque_topic": "external_torque"}
MAX_STAMP = 2.0 ** 31    # s: a bag stores stamps in [0, 2**31) s (int32 seconds of a ROS time)
MIN_ROWS = 2             # rows a bag needs at least: one time step
MIN_KEPT_SHARE = 0.5     # under half the rows usable is a wrong mapping or URDF, not glitches: refused
# The fix each reason of a dropped row points to, when it is why a file is refused.
FIXES = {
    "time": "check the time column and its unit (time.unit)",
    "non-finite": "check the mapping's position, velocity and effort columns",
    "position": "check the mapping's position columns, their scale (rad) and joint order, or the URDF's limits",
    "velocity": "check the mapping's velocity columns, their scale (rad/s) and joint order, or the URDF's limits",
    "torque": "check the mapping's effort columns and their scale (N·m; a current needs its torque constant), or "
              "the URDF's effort limits",
    "repeated": "check the time column and its unit (time.unit): stamps repeat",
    "order": "check the time column: its stamps do not increase",
    "far": "check the time column and its unit (time.unit)",
    "jump": "check the mapping's position columns and joint order",
}


def _fail(path: str | os.PathLike[str], problem: str, fix: str) -> BagError:
    return BagError(" ".join(f"{os.fspath(path)}: {problem}; {fix}".split()))


@dataclass
class ImportReport:
    """What an import did: rows read (lines of a text log that hold data), rows kept, one line per reason rows
    were dropped for, messages left out per topic, kept stamps, notes and warnings."""

    rows: int
    kept: int = 0
    dropped: list[str] = field(default_factory=list)
    left_out: dict[str, int] = field(default_factory=dict)
    stamp: FloatArray = field(default_factory=lambda: np.empty(0))
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _values(table: Table, mapping: Mapping, name: str, count: int, rows: int) -> FloatArray:
    """(rows, count) values of one field, scaled to SI (a value the scale takes past the float range is inf)."""
    spec = mapping.fields[name]
    names = spec.column_names(count, mapping.first_index)
    with np.errstate(over="ignore", invalid="ignore"):
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


def _stamps(table: Table, mapping: Mapping) -> FloatArray:
    """Stamps in s (unit and offset applied), rounded to the nanosecond a bag stores where a bag can store them."""
    with np.errstate(over="ignore", invalid="ignore"):
        stamp = table.column(mapping.time) * TIME_UNITS[mapping.time_unit] + mapping.time_offset
        storable = np.isfinite(stamp) & (stamp >= 0.0) & (stamp < MAX_STAMP)
        return np.where(storable, np.rint(stamp * 1e9) / 1e9, stamp)


def _refusal(table: Table, check: RowCheck, stamp: FloatArray, report: ImportReport) -> BagError:
    """The one line of a file with too little left: counts, the reasons, and the fix of the main reason."""
    main = max(check.drops, key=lambda drop: len(drop.rows)).reason if check.drops else ""
    fix = FIXES.get(main, "fix the rows the report names")
    negative = stamp[np.isfinite(stamp) & (stamp < 0.0)]
    if main == "time" and negative.size:
        fix = f"pass --time-offset {-np.floor(negative.min()):.0f} (s added to every stamp; bags need stamps >= 0)"
    if not check.drops and table.unreadable:
        fix = "fix the lines the report names, or the mapping's format (delimiter, header)"
    return _fail(table.path, f"too little left: {report.kept} of {report.rows} rows usable "
                             f"({'; '.join(report.dropped)})", fix)


def _strict(table: Table, check: RowCheck) -> None:
    """--strict: the first dropped row (or unreadable line) is an error."""
    found = [(lines.lines[0], f"{lines.reason} ({lines.detail})") for lines in table.unreadable]
    found += [(int(table.lines[drop.rows[0]]) if table.lines is not None else int(drop.rows[0]) + 1,
               f"{drop.text}: {drop.detail}") for drop in check.drops]
    if found:
        where, what = min(found)
        noun = "line" if table.lines is not None else "row"
        raise _fail(table.path, f"{noun} {where}: {what}",
                    "fix it, or import without --strict to drop such rows with a report")


def _left_out(data: FloatArray, bound: float | FloatArray) -> np.ndarray:
    """(T,) rows of an optional field (T, k) that are written: finite and within ``bound``."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(data).all(axis=1) & (np.abs(data) <= bound).all(axis=1)


def build_run(table: Table, mapping: Mapping, joints: tuple[str, ...], limits: SampleLimits | None = None,
              strict: bool = False) -> tuple[RecordedRun, ImportReport]:
    """The run a table holds under ``mapping`` (module docstring), and what was dropped on the way; ``limits``:
    the bounds rows are checked against (None: the generic ones); ``strict``: refuse instead of dropping."""
    _check_fields(mapping)
    limits = limits or SampleLimits.generic(joints)
    stamp = _stamps(table, mapping)
    rows, n = stamp.shape[0], len(joints)
    values = {name: _values(table, mapping, name, 6 if name == "wrench" else n, rows) for name in mapping.fields}
    check = check_rows(stamp, values["position"], values.get("velocity"), values.get("effort"), limits,
                       (0.0, MAX_STAMP))
    unread = sum(len(lines.lines) for lines in table.unreadable)
    report = ImportReport(rows + unread, int(check.kept.sum()))
    report.dropped = [f"{lines.reason}: {counted(len(lines.lines), 'line')} "
                      f"({span(f'line {lines.lines[0]}', f'line {lines.lines[-1]}')}; first: {lines.detail})"
                      for lines in table.unreadable] + drop_lines(check, table.where)
    report.warnings += [f"the last line ({lines.detail}) is truncated: dropped (a logger stopped mid-line)"
                        for lines in table.unreadable if lines.reason == TRUNCATED_END]
    if strict:
        _strict(table, check)
    if report.kept < MIN_ROWS or report.kept < MIN_KEPT_SHARE * report.rows:
        raise _refusal(table, check, stamp, report)
    kept = np.flatnonzero(check.kept)
    t = stamp[kept]
    report.stamp = t
    q = values["position"][kept]
    if mapping.differentiate_velocity:
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
    bounds = {"command": limits.tau_max, "external_torque": limits.tau_max, "wrench": GENERIC_TORQUE}

    def optional(name: str, topic: str) -> tuple[FloatArray, FloatArray] | None:
        if name not in values:
            return None
        data = values[name][kept]
        good = _left_out(data, bounds[name])
        if not good.all():
            report.left_out[topic] = int((~good).sum())
        return (t[good], data[good]) if good.any() else None

    command = optional("command", topics.effort_commands)
    wrench = optional("wrench", topics.wrench)
    external = optional("external_torque", topics.external_torque)
    if strict and report.left_out:
        topic, count = next(iter(report.left_out.items()))
        raise _fail(table.path, f"{count} rows of {topic} are not finite or beyond the bounds",
                    "fix them, or import without --strict to leave those messages out")
    run = RecordedRun(
        joint_states=JointStateSeries(t, joints, q, qd, effort),
        commands=None if command is None else CommandSeries(*command),
        wrench=None if wrench is None else WrenchSeries(wrench[0], mapping.fields["wrench"].frame or "",
                                                        wrench[1][:, :3], wrench[1][:, 3:]),
        external_torque=None if external is None else JointStateSeries(
            external[0], joints, np.zeros_like(external[1]), np.zeros_like(external[1]), external[1]),
        source=f"import: {table.path.name}")
    return run, report


def rate_text(stamp: FloatArray) -> str:
    """Median rate and the spread of the time steps: ``100.0 Hz median (step 10 ms; 5-95 %: 9.1-10.9 ms; ...)``."""
    if stamp.size < 2:
        return "one sample, no rate"
    step = np.diff(stamp) * 1e3
    low, median, high = np.percentile(step, [5, 50, 95])
    return (f"{1e3 / median:.1f} Hz median (step {median:.3g} ms; 5-95 %: {low:.3g}-{high:.3g} ms; "
            f"longest {step.max():.3g} ms), {stamp[-1] - stamp[0]:.3f} s from {stamp[0]:.6f} s")


def _joints(args: argparse.Namespace, mapping: Mapping, config: EstimatorConfig | None) -> tuple[str, ...]:
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
    if config is not None:
        return tuple(config.joint_names)
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
    parser.add_argument("--strict", action="store_true",
                        help="refuse the log at the first row that would be dropped (default: drop it and report)")
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
                                                        "joints and whose URDF's limits every row is checked against "
                                                        "(without it: generic bounds only)")
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


def _limits(config: EstimatorConfig | None, joints: tuple[str, ...]) -> SampleLimits:
    """The limits of ``joints`` in the URDF of ``config`` (--config), else the generic bounds."""
    if config is None:
        return SampleLimits.generic(joints)
    return SampleLimits.from_robot(RobotModel(config.urdf, joints, config.ee_frame))


def limits_text(limits: SampleLimits) -> str:
    """Where the bounds rows were checked against come from, and their margins."""
    if limits.source.startswith("the generic"):
        return ("limits: generic bounds only (|q| ≤ 100 rad, |q̇| ≤ 100 rad/s, |τ| ≤ 1e5 N·m); pass --config to check "
                "rows against the URDF's limits")
    return (f"limits: {limits.source} (position +{POSITION_MARGIN:g} rad, velocity ×{VELOCITY_FACTOR:g}, effort "
            f"×{TORQUE_FACTOR:g}; kvark_ros/core/estimation/sample_limits.py)")


def run(args: argparse.Namespace, out_line: Callable[[str], None] = print) -> int:
    """``kvark import`` (module docstring); ``out_line`` prints the report's lines."""
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
    config = load_config(args.config) if args.config else None
    joints = _joints(args, mapping, config)
    limits = _limits(config, joints)
    recorded, report = build_run(table, mapping, joints, limits, args.strict)
    write_run(out, recorded, storage=args.storage, topics=mapping.topics, force=args.force)
    out_line(f"kvark import: {args.input} ({fmt}, {report.rows} rows, {len(table.columns)} columns) -> {out} "
             f"({args.storage})")
    dropped = report.rows - report.kept
    out_line(f"  rows: {report.kept} of {report.rows} kept; dropped: {dropped if dropped else 'none'}")
    for line in report.dropped:
        out_line(f"    {line}")
    out_line(f"  {limits_text(limits)}")
    out_line(f"  rate: {rate_text(report.stamp)}")
    for note in report.notes:
        out_line(f"  {note}")
    for topic, count in report.left_out.items():
        out_line(f"  {topic}: {count} of {report.kept} rows left out (not finite or beyond the bounds)")
    for warning in report.warnings:
        out_line(f"  warning: {warning}")
    series = {mapping.topics.joint_states: recorded.joint_states, mapping.topics.effort_commands: recorded.commands,
              mapping.topics.wrench: recorded.wrench, mapping.topics.external_torque: recorded.external_torque}
    written = [f"{topic} ({item.stamp.size})" for topic, item in series.items() if item is not None]
    out_line(f"  wrote {', '.join(written)} for joints {', '.join(recorded.joint_names)}")
    return 0
