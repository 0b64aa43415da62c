"""Issue 27: ``kvark import`` of a spreadsheet's CSV export (European locale: ``;`` between columns). With ``.``
decimals it reads as the comma CSV does; with decimal commas it is one short error line naming the fix."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from kvark_ros.cli import main
from kvark_ros.io import read_run

ARGS = ("--time", "t", "--joints", "j", "--position", "q{i}", "--velocity", "v{i}", "--effort", "e{i}")
ROWS = [(0.0, 1.5, 0.25, -3.0), (0.1, 1.625, 0.5, -2.75), (0.2, 1.75, 0.75, -2.5)]


def _csv(tmp_path: Path, name: str, delimiter: str, decimal: str = ".", extra: str = "") -> Path:
    lines = [delimiter.join(("t", "q0", "v0", "e0"))]
    lines += [delimiter.join(str(value).replace(".", decimal) for value in row) + extra for row in ROWS]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_semicolon_separated_csv_reads_like_the_comma_one(tmp_path, capsys):
    for name, delimiter in (("comma.csv", ","), ("semicolon.csv", ";")):
        assert main(["import", str(_csv(tmp_path, name, delimiter)), *ARGS, "--out", str(tmp_path / name[:-4])]) == 0
    comma, semicolon = read_run(tmp_path / "comma"), read_run(tmp_path / "semicolon")
    np.testing.assert_array_equal(semicolon.joint_states.position, comma.joint_states.position)
    np.testing.assert_array_equal(semicolon.joint_states.effort[:, 0], [row[3] for row in ROWS])


def test_decimal_commas_are_one_short_line_naming_the_fix(tmp_path, capsys):
    log = _csv(tmp_path, "decimal_comma.csv", ";", decimal=",")
    assert main(["import", str(log), *ARGS, "--out", str(tmp_path / "bag")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and len(err.replace(str(log), "FILE")) < 200, err
    assert f"{log}: line 2, column 't': '0,0' has a decimal comma" in err
    assert "export the log with '.' as the decimal separator" in err and f"sed -i 's/,/./g' {log}" in err
    assert not (tmp_path / "bag").exists()


def test_a_bad_cell_is_shown_cut_not_the_whole_row(tmp_path, capsys):
    log = _csv(tmp_path, "bad.csv", "|", extra="|" + "|".join(["12.5"] * 60))   # '|' is no delimiter: one column
    assert main(["import", str(log), *ARGS, "--out", str(tmp_path / "bag")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and len(err.replace(str(log), "FILE")) < 200, err
    assert "is not a number); fix the cells or drop the rows" in err and "…" in err
