"""Numeric tables from robot logs (CSV or whitespace text, NPZ, MAT), read without ROS.

A table is named numeric columns. A CSV or text log has one header row naming its columns (lines
before it that start with ``#`` are comments); the delimiter is a semicolon when the header has more
of them than commas (a spreadsheet's export where the decimal separator is a comma), else a comma
when the header has one, else whitespace; an empty CSV cell reads as NaN. A line that holds no row (too
few or too many fields: a logger killed mid-line, two lines run together; a cell that is not a number: a
message or a repeated header in the log) is left out and named in ``Table.unreadable`` with its line number,
the rest is read; a log whose every line is unreadable is an error, and so is a decimal comma (an export
setting, the whole file's). A log without a header row (``header=False``) has its columns named by position,
``1`` for the first (as a MATLAB or awk script counts them); the first data row decides the delimiter and the
field count most of its lines have the number of columns.
NPZ and MAT files hold arrays by name: a vector is the column ``name``, a 2-D array a block whose column
k is ``name:k``. Samples run along a 2-D array's longer axis, so MATLAB's (1, T) vectors and (k, T)
matrices read like (T,) and (T, k) ones.
Every failure a user can cause is one :class:`BagError` naming the file, the problem and the fix.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kvark_ros.core.hints import did_you_mean, shorten
from kvark_ros.io.common import FloatArray, PathLike
from kvark_ros.io.runs import bag_error

__all__ = ["FORMATS", "TRUNCATED_END", "Table", "Unreadable", "read_table", "table_format"]

FORMATS = ("csv", "npz", "mat")
_SUFFIXES = {".csv": "csv", ".txt": "csv", ".log": "csv", ".tsv": "csv", ".dat": "csv", ".npz": "npz",
             ".mat": "mat"}
_SHOWN_NAMES = 40  # columns listed in a "missing column" error
WIDTH = "too few or too many fields"
NOT_A_NUMBER = "a cell that is not a number"
TRUNCATED_END = "truncated last line"


@dataclass(frozen=True)
class Unreadable:
    """Lines of a text log left out for one reason: their numbers (1 for the file's first line) and what the
    first one shows."""

    reason: str
    lines: list[int]
    detail: str


@dataclass(frozen=True)
class Table:
    """Named numeric columns of one file; ``skipped`` names arrays that are not numeric vectors or matrices.

    ``lines``: the file line of each row (text logs; None for NPZ/MAT, whose rows are counted from 1);
    ``unreadable``: the text lines left out, per reason (module docstring).
    """

    path: Path
    columns: dict[str, FloatArray]
    skipped: dict[str, str] = field(default_factory=dict)
    lines: np.ndarray | None = None
    unreadable: tuple[Unreadable, ...] = ()

    def where(self, row: int) -> str:
        """Row ``row`` (0 for the first) as a user finds it: ``line 12`` of a text log, ``row 13`` of an array."""
        return f"line {int(self.lines[row])}" if self.lines is not None else f"row {row + 1}"

    def describe(self) -> str:
        """The column names, shortened for an error message."""
        names = list(self.columns)
        shown = ", ".join(shorten(name) for name in names[:_SHOWN_NAMES])
        more = f" and {len(names) - _SHOWN_NAMES} more" if len(names) > _SHOWN_NAMES else ""
        return f"{shown}{more}" if names else "no numeric columns"

    def column(self, name: str, rows: int | None = None) -> FloatArray:
        """The column ``name`` (``name:k`` for column k of a 2-D array), of ``rows`` samples if given; a
        BagError naming what the file has."""
        if name in self.columns:
            found = self.columns[name]
            if rows is not None and found.shape[0] != rows:
                raise bag_error(self.path, f"column {name!r} has {found.shape[0]} samples, the time column {rows}",
                                "map the columns of one recording")
            return found
        why = f" ({name} is {self.skipped[name]})" if name in self.skipped else ""
        hint = did_you_mean(name, self.columns)
        raise bag_error(self.path, f"has no column {name!r}{why}{hint}; its columns are {self.describe()}",
                        "fix the column names in the mapping (--mapping or the field flags)")


def table_format(path: PathLike, fmt: str | None = None) -> str:
    """``fmt`` if given, else the format the file's suffix says (``csv`` for .csv/.txt/.log/.tsv/.dat)."""
    if fmt is not None:
        if fmt not in FORMATS:
            raise bag_error(path, f"unknown format {fmt!r}", f"use one of {', '.join(FORMATS)}")
        return fmt
    suffix = Path(path).suffix.lower()
    if suffix not in _SUFFIXES:
        raise bag_error(path, f"unknown file format (suffix {suffix or 'none'!r})",
                        f"pass --format {'|'.join(FORMATS)} (suffixes: {', '.join(_SUFFIXES)})")
    return _SUFFIXES[suffix]


def read_table(path: PathLike, fmt: str | None = None, header: bool = True) -> Table:
    """Read a CSV/text, NPZ or MAT file into a :class:`Table` (module docstring); ``header=False``: a text log
    without a header row, its columns named ``1`` … ``N``."""
    given = Path(path)
    kind = table_format(given, fmt)
    if not given.is_file():
        raise bag_error(given, "no such file" if not given.exists() else "is not a file", "check the input path")
    if kind == "csv":
        return _read_text(given, header)
    if not header:
        raise bag_error(given, f"is a {kind.upper()} file, whose arrays have names", "drop --no-header (header: false)")
    return _from_arrays(given, _load_npz(given) if kind == "npz" else _load_mat(given))


def _decoded(path: Path) -> str:
    """The file's text; bytes that are not UTF-8 read as U+FFFD (their lines then hold no number), unless the
    first line has them: then it is no text file."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise bag_error(path, f"cannot read it ({exc.strerror})", "check the file permissions") from exc
    try:
        return data.decode()
    except UnicodeDecodeError:
        text = data.decode(errors="replace")
    first = next((line for line in text.splitlines() if line.strip()), "")
    if "\ufffd" in first or "\x00" in first:
        raise bag_error(path, "is not a text file", "pass --format npz or mat for binary files")
    return text


def _read_text(path: Path, header: bool) -> Table:
    """A delimited text file with a header row, or without one (module docstring)."""
    lines = _decoded(path).split("\n")       # not splitlines: garbage may hold the other line breaks it knows
    numbered = [(k + 1, line) for k, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise bag_error(path, "is empty (no header row)" if header else "is empty",
                        "export the log with a header row naming the columns" if header else "export the log's data")
    header_line, first = numbered[0]
    delimiter = ";" if first.count(";") > first.count(",") else "," if "," in first else None
    if not header:
        counts = np.bincount([len(line.split(delimiter)) for _, line in numbered])
        names = [str(k + 1) for k in range(int(np.argmax(counts)))]
        return _table(path, numbered, names, delimiter, "most lines")
    names = [name.strip().strip('"').strip("'") for name in first.split(delimiter)]
    if len(names) > 1 and all(_is_number(name) for name in names):
        raise bag_error(path, f"line {header_line}: the first row is numbers, not column names",
                        "pass --no-header (mapping header: false) and name columns by position: --time 1")
    if not all(names):
        raise bag_error(path, f"line {header_line}: the header has an empty column name", "name every column")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise bag_error(path, f"line {header_line}: the header names {shorten(repeated[0])!r} twice",
                        "name every column once")
    body = numbered[1:]
    if not body:
        raise bag_error(path, "has a header but no data rows", "export the log with its data")
    return _table(path, body, names, delimiter, "the header")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _table(path: Path, body: list[tuple[int, str]], names: list[str], delimiter: str | None, first: str) -> Table:
    """The data rows as one contiguous array per named column (``first``: what set the column count); lines that
    hold no row are left out (``_parse_cells``)."""
    try:
        data = np.loadtxt(io.StringIO("\n".join(line for _, line in body)), delimiter=delimiter, ndmin=2)
        if data.shape[1] != len(names):
            raise ValueError("column count")
        lines, unreadable = np.array([line_no for line_no, _ in body]), ()
    except ValueError:
        data, lines, unreadable = _parse_cells(path, body, names, delimiter, first)
    return Table(path, {name: np.ascontiguousarray(data[:, k]) for k, name in enumerate(names)}, lines=lines,
                 unreadable=unreadable)


def _parse_cells(path: Path, body: list[tuple[int, str]], names: list[str], delimiter: str | None,
                 first: str) -> tuple[FloatArray, np.ndarray, tuple[Unreadable, ...]]:
    """Cell by cell, for the rows the fast reader refused: an empty cell is NaN, anything else must be a number.
    Returns the rows, their line numbers and the lines left out per reason; a decimal comma, or no readable line
    at all, is a BagError."""
    data = np.empty((len(body), len(names)))
    kept: list[int] = []
    bad: dict[str, tuple[list[int], str]] = {}
    for line_no, line in body:
        cells = line.split(delimiter)
        reason, detail = None, ""
        if len(cells) != len(names):
            count = "have" if first == "most lines" else "has"
            reason, detail = WIDTH, f"line {line_no} has {len(cells)} fields, {first} {count} {len(names)}"
        else:
            for k, cell in enumerate(cells):
                text = cell.strip()
                try:
                    data[len(kept), k] = float(text) if text else np.nan
                except ValueError:
                    _decimal_comma(path, line_no, names[k], text)
                    reason = NOT_A_NUMBER
                    detail = f"line {line_no}, column {shorten(names[k])!r}: {shorten(text)!r} is not a number"
                    break
        if reason is None:
            kept.append(line_no)
            continue
        if line_no == body[-1][0] and len(cells) < len(names):
            reason = TRUNCATED_END          # a logger stopped mid-line
        bad.setdefault(reason, ([], detail))[0].append(line_no)
    if not kept:
        lines, detail = next(iter(bad.values()))
        fix = "fix the cells or drop the rows" if NOT_A_NUMBER in bad else f"fix the rows or {first}"
        raise bag_error(path, f"no line holds a row of numbers ({detail})", fix)
    unreadable = tuple(Unreadable(reason, lines, detail) for reason, (lines, detail) in bad.items())
    return data[:len(kept)], np.array(kept), unreadable


def _decimal_comma(path: Path, line_no: int, name: str, text: str) -> None:
    """The error of a cell written with a decimal comma (``1,5``): an export setting, so the fix is the whole
    file's."""
    try:
        float(text.replace(",", ".", 1))
    except ValueError:
        return
    raise bag_error(path, f"line {line_no}, column {shorten(name)!r}: {shorten(text)!r} has a decimal comma",
                    "export the log with '.' as the decimal separator, or "
                    f"replace the commas: sed -i 's/,/./g' {path}")


def _load_npz(path: Path) -> dict[str, object]:
    try:     # our own file object: numpy leaves its own open when the archive is not a zip
        with open(path, "rb") as stream, np.load(stream, allow_pickle=False) as archive:
            arrays: dict[str, object] = {}
            for name in archive.files:
                try:
                    arrays[name] = archive[name]
                except ValueError:   # an object array, which needs pickle: not numeric data
                    arrays[name] = None
            return arrays
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise bag_error(path, f"is not a readable NPZ file ({exc})", "save it with numpy.savez") from exc


def _load_mat(path: Path) -> dict[str, object]:
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    try:
        found = loadmat(path)
    except NotImplementedError as exc:   # MATLAB -v7.3 files are HDF5
        raise bag_error(path, "is a MATLAB v7.3 (HDF5) file", "save it with save(..., '-v7') or as CSV") from exc
    except (MatReadError, OSError, ValueError, TypeError) as exc:
        raise bag_error(path, f"is not a readable MAT file ({exc})",
                        "save it with MATLAB's save or scipy.io.savemat") from exc
    return {name: value for name, value in found.items() if not name.startswith("__")}


def _from_arrays(path: Path, arrays: dict[str, object]) -> Table:
    """Columns of named arrays: vectors as ``name``, 2-D arrays as ``name:k`` (samples on the longer axis)."""
    columns: dict[str, FloatArray] = {}
    skipped: dict[str, str] = {}
    for name, value in arrays.items():
        array = np.asarray(value) if value is not None else None
        if array is None or array.dtype.kind not in "biuf":
            skipped[name] = "not numeric"
            continue
        if array.ndim == 2 and 1 in array.shape:
            array = array.reshape(-1)
        if array.ndim == 1:
            columns[name] = array.astype(np.float64)
        elif array.ndim == 2:
            block = array if array.shape[0] >= array.shape[1] else array.T
            columns.update({f"{name}:{k}": block[:, k].astype(np.float64) for k in range(block.shape[1])})
        else:
            skipped[name] = f"{array.ndim}-D with shape {array.shape}"
    if not columns:
        raise bag_error(path, "holds no numeric vectors or matrices", "save the signals as numeric arrays")
    return Table(path, columns, skipped)
