"""Robot logs and bags corrupted the ways real ones are, for the messy-log tests and the fuzz.

A logger killed mid-line, a packet parsed as numbers, a sensor glitch, a disk that lost a block: each
``corrupt_*`` function takes a clean log (the text of a CSV, the arrays of an NPZ/MAT file, a recorded run,
the bytes of a bag's MCAP file) and a random generator, and returns the corrupted one and the names of what
it did (one to three corruptions, drawn from the ``*_KINDS`` tuples), so a failing case says what it was.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from kvark_ros.io import CommandSeries, JointStateSeries, RecordedRun

TEXT_KINDS = ("truncated_last", "truncated_line", "garbage_row", "binary_row", "header_again", "nan_cell",
              "inf_cell", "huge_cell", "empty_cell", "swapped_columns", "swapped_header", "repeated_stamp",
              "backward_stamp", "stamp_spike", "negative_stamps", "duplicate_rows", "extra_field",
              "missing_field", "decimal_comma", "empty_file", "header_only", "all_garbage", "zero_rows")
ARRAY_KINDS = ("nan", "inf", "huge", "short_array", "swapped_arrays", "repeated_stamp", "backward_stamp",
               "stamp_spike", "empty_array", "text_array", "cube_array", "missing_array", "zero_rows")
RUN_KINDS = ("nan", "inf", "huge", "swapped_joints", "swapped_fields", "repeated_stamp", "backward_stamp",
             "zero_stamps", "far_stamp", "no_commands", "one_sample", "zero_rows", "scaled_torque")
BYTE_KINDS = ("truncated", "flipped_bytes", "garbage_block", "inserted_bytes", "empty", "no_metadata")
HUGE = (1e300, -1e305, 1e154, 2.7e154, 1e308)


def _rows_of(text: str) -> tuple[str, list[str]]:
    """(header, data lines) of a CSV text."""
    lines = text.rstrip("\n").split("\n")
    return lines[0], lines[1:]


def _cell(line: str, k: int, value: str) -> str:
    cells = line.split(",")
    cells[k % len(cells)] = value
    return ",".join(cells)


def _text_once(header: str, rows: list[str], kind: str, rng: np.random.Generator) -> tuple[str, list[str]]:
    """One corruption of a CSV's header and rows (``TEXT_KINDS``)."""
    rows = list(rows)
    width = len(header.split(","))
    k = int(rng.integers(0, len(rows))) if rows else 0
    if not rows and kind not in ("empty_file", "header_only"):
        return header, rows
    if kind == "truncated_last":
        rows[-1] = rows[-1][:int(rng.integers(1, max(2, len(rows[-1]))))]
    elif kind == "truncated_line":
        rows[k] = rows[k][:int(rng.integers(0, max(1, len(rows[k]))))]
    elif kind == "garbage_row":
        rows.insert(k, str(rng.choice(["ERROR: RTDE connection lost", "###", "nan nan", "0x7f3a", "-", ",,,,",
                                       "timestamp", "\t"])))
    elif kind == "binary_row":
        rows.insert(k, bytes(rng.integers(1, 256, int(rng.integers(1, 40)), dtype=np.uint8)).decode("latin-1"))
    elif kind == "header_again":
        rows.insert(k, header)
    elif kind in ("nan_cell", "inf_cell", "huge_cell", "empty_cell"):
        value = {"nan_cell": "nan", "inf_cell": str(rng.choice(["inf", "-inf"])), "empty_cell": "",
                 "huge_cell": f"{rng.choice(HUGE):.6g}"}[kind]
        for _ in range(int(rng.integers(1, 4))):
            j = int(rng.integers(0, len(rows)))
            rows[j] = _cell(rows[j], int(rng.integers(0, width)), value)
    elif kind == "swapped_columns":
        a, b = rng.choice(width, 2, replace=False)
        swapped = []
        for line in rows:
            cells = line.split(",")
            if len(cells) == width:
                cells[a], cells[b] = cells[b], cells[a]
            swapped.append(",".join(cells))
        rows = swapped
    elif kind == "swapped_header":
        names = header.split(",")
        a, b = rng.choice(width, 2, replace=False)
        names[a], names[b] = names[b], names[a]
        header = ",".join(names)
    elif kind in ("repeated_stamp", "backward_stamp", "stamp_spike") and len(rows) > 1:
        k = max(k, 1)
        before = rows[k - 1].split(",")[0]
        value = {"repeated_stamp": before, "backward_stamp": f"{_number(before) - rng.uniform(0.001, 5):.6f}",
                 "stamp_spike": f"{rng.choice([2.7e154, 1e9, _number(before) + 1000.0]):.9g}"}[kind]
        rows[k] = _cell(rows[k], 0, value)
    elif kind == "negative_stamps":
        rows = [_cell(line, 0, f"{-_number(line.split(',')[0]):.6f}") for line in rows]
    elif kind == "duplicate_rows":
        rows[k:k] = [rows[k]] * int(rng.integers(1, 4))
    elif kind == "extra_field":
        rows[k] += ",1.0"
    elif kind == "missing_field":
        rows[k] = ",".join(rows[k].split(",")[:-1])
    elif kind == "decimal_comma":
        rows[k] = rows[k].replace(".", ",", 1)
    elif kind == "empty_file":
        return "", []
    elif kind == "header_only":
        rows = []
    elif kind == "all_garbage":
        rows = ["garbage " * int(rng.integers(1, 5)) for _ in rows]
    elif kind == "zero_rows":
        rows[k] = ",".join([rows[k].split(",")[0]] + ["0"] * (width - 1))
    return header, rows


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return 0.0


def _kinds(rng: np.random.Generator, choices: tuple[str, ...], kinds: list[str] | None) -> list[str]:
    """``kinds``, else one to three of ``choices`` drawn by ``rng``."""
    return list(kinds) if kinds is not None else [str(k) for k in rng.choice(choices, int(rng.integers(1, 4)))]


def corrupt_text(text: str, rng: np.random.Generator, kinds: list[str] | None = None) -> tuple[bytes, list[str]]:
    """A CSV log (header row, comma-delimited, as ``examples/ur5_rtde_*.csv``) with the corruptions ``kinds`` (default:
    one to three drawn), as the bytes of the file."""
    header, rows = _rows_of(text)
    kinds = _kinds(rng, TEXT_KINDS, kinds)
    for kind in kinds:
        header, rows = _text_once(header, rows, str(kind), rng)
    if not header and not rows:
        return b"", [str(k) for k in kinds]
    body = "\n".join([header, *rows])
    return (body + ("" if "truncated_last" in kinds else "\n")).encode("latin-1"), [str(k) for k in kinds]


def corrupt_arrays(arrays: dict[str, np.ndarray], rng: np.random.Generator, kinds: list[str] | None = None
                   ) -> tuple[dict[str, np.ndarray], list[str]]:
    """The arrays of an NPZ/MAT log (``t`` (T,) and (T, n) blocks) with the corruptions ``kinds`` (``ARRAY_KINDS``;
    default: one to three drawn)."""
    arrays = {name: np.array(value, copy=True) for name, value in arrays.items()}
    kinds = _kinds(rng, ARRAY_KINDS, kinds)
    for kind in kinds:
        names = [name for name in arrays if arrays[name].dtype.kind == "f" and arrays[name].size]
        if not names:
            break
        name = str(rng.choice(names))
        value = arrays[name]
        flat = value.reshape(-1)
        k = int(rng.integers(0, flat.size))
        if kind in ("nan", "inf", "huge"):
            flat[k] = {"nan": np.nan, "inf": -np.inf, "huge": float(rng.choice(HUGE))}[kind]
        elif kind == "short_array":
            arrays[name] = value[:int(rng.integers(0, len(value)))]
        elif kind == "swapped_arrays":
            other = str(rng.choice(names))
            if arrays[other].shape == value.shape:
                arrays[name], arrays[other] = arrays[other], value
        elif kind in ("repeated_stamp", "backward_stamp", "stamp_spike") and "t" in names and arrays["t"].size > 1:
            t = arrays["t"].reshape(-1)
            j = int(rng.integers(1, t.size))
            t[j] = {"repeated_stamp": t[j - 1], "backward_stamp": t[j - 1] - 1.0, "stamp_spike": 2.7e154}[kind]
        elif kind == "empty_array":
            arrays[name] = value[:0]
        elif kind == "text_array":
            arrays[name] = np.array(["a"] * len(value))
        elif kind == "cube_array":
            arrays[name] = np.repeat(value.reshape(len(value), -1)[:, :, None], 2, axis=2)
        elif kind == "missing_array":
            del arrays[name]
        elif kind == "zero_rows" and value.ndim == 2:
            value[int(rng.integers(0, len(value)))] = 0.0
    return arrays, kinds


def corrupt_run(run: RecordedRun, rng: np.random.Generator, kinds: list[str] | None = None
                ) -> tuple[RecordedRun, list[str]]:
    """A recorded run with the corruptions ``kinds`` (``RUN_KINDS``; default: one to three drawn), still one a bag can
    store (stamps finite, in [0, 2**31) s)."""
    js, cmd = run.joint_states, run.commands
    stamp, q, qd, effort = (np.array(x, copy=True) for x in (js.stamp, js.position, js.velocity, js.effort))
    command = None if cmd is None else (np.array(cmd.stamp, copy=True), np.array(cmd.effort, copy=True))
    kinds = _kinds(rng, RUN_KINDS, kinds)
    for kind in kinds:
        rows = len(stamp)
        if rows == 0:
            break
        k = int(rng.integers(0, rows))
        target = [q, qd, effort] + ([command[1]] if command is not None else [])
        field = target[int(rng.integers(0, len(target)))]
        if kind in ("nan", "inf", "huge"):
            field[k % len(field), int(rng.integers(0, field.shape[1]))] = {
                "nan": np.nan, "inf": np.inf, "huge": float(rng.choice(HUGE))}[kind]
        elif kind == "swapped_joints":
            a, b = rng.choice(q.shape[1], 2, replace=False)
            field[:, [a, b]] = field[:, [b, a]]
        elif kind == "swapped_fields":
            q, qd = qd, q
        elif kind in ("repeated_stamp", "backward_stamp") and rows > 1:
            k = max(k, 1)
            stamp[k] = stamp[k - 1] if kind == "repeated_stamp" else max(stamp[k - 1] - rng.uniform(0.001, 1.0), 0.0)
        elif kind == "zero_stamps":
            stamp[:] = 0.0
        elif kind == "far_stamp":
            stamp[k] = min(float(rng.choice([2.0 ** 31 - 1.0, stamp[k] + 1000.0])), 2.0 ** 31 - 1.0)
        elif kind == "no_commands":
            command = None
        elif kind == "one_sample":
            keep = slice(k, k + 1)
            stamp, q, qd, effort = stamp[keep], q[keep], qd[keep], effort[keep]
            if command is not None:
                command = (command[0][keep], command[1][keep])
        elif kind == "zero_rows":
            q[k], qd[k] = 0.0, 0.0
        elif kind == "scaled_torque":                       # a current logged where N·m was expected, or the reverse
            with np.errstate(over="ignore"):              # a 1e308 already there becomes inf: so be it
                field *= float(rng.choice([1e-3, 100.0, 1e6]))
    states = JointStateSeries(stamp, js.names, q, qd, effort)
    commands = None if command is None else CommandSeries(*command)
    return replace(run, joint_states=states, commands=commands), kinds


def corrupt_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes | None, list[str]]:
    """A bag's MCAP file damaged on disk (``BYTE_KINDS``); None: its ``metadata.yaml`` is lost instead."""
    kind = str(rng.choice(BYTE_KINDS))
    block = bytearray(data)
    if kind == "truncated":
        return bytes(block[:int(rng.integers(0, len(block)))]), [kind]
    if kind == "flipped_bytes":
        for _ in range(int(rng.integers(1, 30))):
            block[int(rng.integers(0, len(block)))] = int(rng.integers(0, 256))
        return bytes(block), [kind]
    if kind == "garbage_block":
        start = int(rng.integers(0, len(block) - 64))
        block[start:start + 64] = rng.bytes(64)
        return bytes(block), [kind]
    if kind == "inserted_bytes":
        at = int(rng.integers(0, len(block)))
        return bytes(block[:at]) + rng.bytes(int(rng.integers(1, 200))) + bytes(block[at:]), [kind]
    if kind == "empty":
        return b"", [kind]
    return None, [kind]
