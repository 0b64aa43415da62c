"""Real logs are messy: ``kvark import`` drops what breaks the physics with a report, every command that reads a bag
skips such samples naming bag, topic, time and joint, and a failed fit is one line, never a traceback.

The logs are the committed UR5 RTDE example (``examples/ur5_rtde_1.csv``, 100 Hz, UR5 URDF limits of
``config/ur5.yaml``: position ±2π (elbow ±π), velocity 3.15-3.2 rad/s, effort 150/28 N·m) with known corruptions,
so every test knows which line must go and why. The property tests corrupt them at random
(``test/corrupt_logs.py``): an import either keeps only rows within the physics or refuses in one line.
"""
from __future__ import annotations

import contextlib
import io
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.io import savemat

from corrupt_logs import ARRAY_KINDS, RUN_KINDS, TEXT_KINDS, corrupt_arrays, corrupt_run, corrupt_text
from example_logs import UR_JOINTS, UR_TORQUE_CONSTANTS
from kvark_ros.cli import main
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.sample_limits import POSITION, TORQUE, VELOCITY, SampleLimits
from kvark_ros.io import BagError, read_run, write_run
from kvark_ros.io.recorded_inputs import read_checked

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "ur5.yaml"
MAPPING = ROOT / "examples" / "ur_rtde_mapping.yaml"
ARRAY_FLAGS = ("--time", "t", "--position", "q:{i}", "--velocity", "qd:{i}", "--effort", "current:{i}",
               "--command", "moment:{i}", "--scale", "effort=" + ",".join(map(str, UR_TORQUE_CONSTANTS)),
               "--joints", ",".join(UR_JOINTS))
LIMITS = SampleLimits.from_robot(RobotModel(load_config(CONFIG).urdf, UR_JOINTS, "tool0"))


def _lines(rows: int) -> list[str]:
    """The header and the first ``rows`` rows of the UR5 example (line k of the file is item k − 1)."""
    return (ROOT / "examples" / "ur5_rtde_1.csv").read_text().splitlines()[:rows + 1]


def _write(path: Path, lines: list[str] | bytes) -> Path:
    path.write_bytes(lines if isinstance(lines, bytes) else ("\n".join(lines) + "\n").encode())
    return path


def _cell(line: str, column: int, value: str) -> str:
    cells = line.split(",")
    cells[column] = value
    return ",".join(cells)


def _import(capsys, log: Path, *args: str | Path) -> tuple[int, str, str]:
    """``kvark import LOG ARGS`` (UR RTDE mapping unless ARGS maps the columns): exit code, stdout, stderr."""
    capsys.readouterr()
    flags = args if "--time" in args else ("--mapping", MAPPING, *args)
    code = main(["import", str(log), *map(str, flags)])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err: str, *words: str) -> str:
    """The single stderr line ``kvark: error: ...``, holding every one of ``words``."""
    lines = err.rstrip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith("kvark: error: ") and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]}"
    return lines[0]


def _within_physics(bag: Path) -> bool:
    """Whether every joint state of ``bag`` is finite, within ``LIMITS`` and stamped after the one before."""
    states = read_run(bag, UR_JOINTS).joint_states
    return (all(np.isfinite(x).all() and not LIMITS.beyond(kind, x).any()
                for kind, x in ((POSITION, states.position), (VELOCITY, states.velocity), (TORQUE, states.effort)))
            and bool((np.diff(states.stamp) > 0).all()))


# --------------------------------------------------------------------------- kvark import

def test_a_truncated_last_line_is_dropped_with_a_warning(tmp_path, capsys):
    lines = _lines(150)
    lines[-1] = lines[-1][:40]                               # the logger stopped mid-line
    fields = len(lines[-1].split(","))
    log = _write(tmp_path / "log.csv", "\n".join(lines).encode())     # no newline after the cut
    code, out, err = _import(capsys, log, "--config", CONFIG, "--out", tmp_path / "bag")
    assert code == 0 and err == ""
    assert "149 of 150 kept; dropped: 1" in out
    assert f"truncated last line: 1 line (line 151; first: line 151 has {fields} fields, the header has 25)" in out
    assert (f"warning: the last line (line 151 has {fields} fields, the header has 25) is truncated: dropped (a "
            "logger stopped mid-line)") in out
    assert len(read_run(tmp_path / "bag").joint_states.stamp) == 149


def test_garbage_text_rows_are_dropped_with_their_lines_and_the_rest_imported(tmp_path, capsys):
    clean = _lines(150)
    lines = list(clean)
    lines.insert(51, "ERROR: RTDE connection lost")            # file line 52
    lines.insert(81, clean[0])                                 # the header again (the logger restarted): line 82
    lines.insert(101, "\ufffd\ufffd" + "\x00" * 3)             # bytes that are no text: line 102
    lines[120] = lines[120][:60]                               # a truncated line in the middle: line 121
    code, out, err = _import(capsys, _write(tmp_path / "log.csv", lines), "--config", CONFIG, "--out",
                             tmp_path / "bag")
    assert code == 0 and err == ""
    assert "149 of 153 kept; dropped: 4" in out
    assert "too few or too many fields: 3 lines (line 52 to line 121; first: line 52 has 1 fields, the header has 25)" \
        in out
    assert ("a cell that is not a number: 1 line (line 82; first: line 82, column 'timestamp': 'timestamp' is not a "
            "number)") in out
    kept = [line for k, line in enumerate(clean[1:]) if k != 116]               # the row cut short at line 121
    expected = np.array([[float(x) for x in line.split(",")[1:7]] for line in kept])
    np.testing.assert_array_equal(read_run(tmp_path / "bag", UR_JOINTS).joint_states.position, expected)


def _absurd(lines: list[str]) -> list[str]:
    """Four rows no UR5 produces: q 1e300 (line 22), q̇ 12 rad/s (line 32, the limit is 3.15), a current of 30 A
    (line 42: 405 N·m, the effort limit is 150) and a stamp of 2.7e154 s (line 52)."""
    lines = list(lines)
    lines[21] = _cell(lines[21], 3, "1e300")
    lines[31] = _cell(lines[31], 7, "12.0")
    lines[41] = _cell(lines[41], 14, "30.0")
    lines[51] = _cell(lines[51], 0, "2.7e154")
    return lines


def test_absurd_values_are_dropped_against_the_urdfs_limits(tmp_path, capsys):
    code, out, _ = _import(capsys, _write(tmp_path / "log.csv", _absurd(_lines(150))), "--config", CONFIG,
                           "--out", tmp_path / "bag")
    assert code == 0 and "146 of 150 kept; dropped: 4" in out
    for line in ("stamp not finite or out of range: 1 row (line 52; first: stamp 2.7e+154 s)",
                 "position beyond the joint limits (+0.1 rad): 1 row (line 22; first: elbow_joint q = 1e+300 rad, "
                 "bounds [-3.242, 3.242])",
                 "velocity beyond 2× the velocity limit: 1 row (line 32; first: shoulder_pan_joint q̇ = 12 rad/s, "
                 "bounds [-6.3, 6.3])",
                 "torque beyond 2× the effort limit: 1 row (line 42; first: shoulder_lift_joint τ = 405 N·m, bounds "
                 "[-300, 300])",
                 "limits: the URDF example-robot-data:ur5 (position +0.1 rad, velocity ×2, effort ×2"):
        assert line in out, line
    assert _within_physics(tmp_path / "bag")


def test_without_a_urdf_only_absurd_values_are_dropped(tmp_path, capsys):
    code, out, _ = _import(capsys, _write(tmp_path / "log.csv", _absurd(_lines(150))), "--joints",
                           ",".join(UR_JOINTS), "--out", tmp_path / "bag")
    assert code == 0 and "148 of 150 kept; dropped: 2" in out
    assert "limits: generic bounds only" in out and "pass --config to check rows against the URDF's limits" in out


def test_strict_refuses_at_the_first_row_it_would_drop(tmp_path, capsys):
    lines = _lines(150)
    lines[39] = _cell(lines[39], 1, "nan")
    lines[-1] = lines[-1][:30]
    log = _write(tmp_path / "log.csv", lines)
    code, _, err = _import(capsys, log, "--config", CONFIG, "--strict", "--out", tmp_path / "bag")
    assert code == 1 and not (tmp_path / "bag").exists()
    _one_line(err, f"{log}: line 40: NaN or Inf in q, q̇ or τ: shoulder_pan_joint q = nan; fix it, or import without "
                   "--strict")


def _in_microseconds(lines: list[str]) -> list[str]:
    """The log with its stamps in µs (a logger's choice; the mapping still says s: 4.5e9 s, past what a bag stores)."""
    return [lines[0]] + [_cell(line, 0, f"{1e6 * float(line.split(',')[0]):.0f}") for line in lines[1:]]


@pytest.mark.parametrize("edit, flags, words", [
    (None, ("--position", "target_moment_{i}", "--command", "actual_q_{i}"),      # torque columns taken for q
     ("too little left: 0 of 150 rows usable (position beyond the joint limits", "check the mapping's position "
      "columns, their scale (rad) and joint order, or the URDF's limits")),
    (None, ("--scale", "position=57.29578"),                                       # degrees taken for radians
     ("too little left: ", "check the mapping's position columns, their scale (rad)")),
    (_in_microseconds, (), ("too little left: 0 of 150 rows usable (stamp not finite or out of range: 150 rows",
                            "check the time column and its unit (time.unit)")),
])
def test_a_file_with_too_little_left_is_refused_with_the_fix(tmp_path, capsys, edit, flags, words):
    lines = _lines(150) if edit is None else edit(_lines(150))
    log = _write(tmp_path / "log.csv", lines)
    code, _, err = _import(capsys, log, "--config", CONFIG, *flags, "--out", tmp_path / "bag")
    assert code == 1 and not (tmp_path / "bag").exists()
    _one_line(err, str(log), *words)


def _arrays(rows: int) -> dict[str, np.ndarray]:
    data = np.loadtxt(io.StringIO("\n".join(_lines(rows)[1:])), delimiter=",", ndmin=2)
    return {"t": data[:, 0], "q": data[:, 1:7], "qd": data[:, 7:13], "current": data[:, 13:19],
            "moment": data[:, 19:25]}


def test_npz_rows_are_dropped_by_row_number(tmp_path, capsys):
    arrays = _arrays(150)
    arrays["t"][60] = arrays["t"][59]
    arrays["q"][70, 1] = np.nan
    arrays["current"][80, 2] = 1e300
    arrays["t"][90] = arrays["t"][89] - 1.0
    np.savez(tmp_path / "log.npz", **arrays)
    code, out, _ = _import(capsys, tmp_path / "log.npz", *ARRAY_FLAGS, "--config", CONFIG, "--out", tmp_path / "bag")
    assert code == 0 and "146 of 150 kept; dropped: 4" in out
    for line in ("NaN or Inf in q, q̇ or τ: 1 row (row 71; first: shoulder_lift_joint q = nan)",
                 "torque beyond 2× the effort limit: 1 row (row 81; first: elbow_joint τ = 1.35e+301 N·m",
                 "repeated stamp: 1 row (row 61;", "stamp out of order: 1 row (row 91;"):
        assert line in out, line


@pytest.mark.parametrize("name, data, words", [
    ("empty.csv", b"", ("is empty (no header row)",)),
    ("header.csv", b"t,q0,v0,e0\n", ("has a header but no data rows",)),
    ("garbage.csv", b"t,q0,v0,e0\nabc\ndef\n", ("no line holds a row of numbers",)),
    ("binary.csv", b"\xff\xfe\x00\x01\x02", ("is not a text file",)),
    ("empty.mat", b"", ("is not a readable MAT file",)),
    ("empty.npz", b"", ("is not a readable NPZ file",)),
])
def test_an_unreadable_file_is_one_line(tmp_path, capsys, name, data, words):
    log = _write(tmp_path / name, data)
    code, _, err = _import(capsys, log, *ARRAY_FLAGS[:2], *ARRAY_FLAGS[2:], "--out", tmp_path / "bag")
    assert code == 1
    _one_line(err, str(log), *words)


def test_a_truncated_mat_file_is_one_line(tmp_path, capsys):
    savemat(tmp_path / "log.mat", _arrays(150))
    data = (tmp_path / "log.mat").read_bytes()
    log = _write(tmp_path / "log.mat", data[:len(data) // 2])
    code, _, err = _import(capsys, log, *ARRAY_FLAGS, "--out", tmp_path / "bag")
    assert code == 1
    _one_line(err, str(log), "is not a readable MAT file")


# --------------------------------------------------------------------------- commands that read bags

@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A 4 s UR5 bag (the example imported) with a sample of q 50 rad on the elbow at row 100 and a commanded torque
    of 1e6 N·m at row 200; a copy whose commanded torque is in the wrong unit (×100); and ``kvark train``'s exit code
    and output on the corrupted bag."""
    root = tmp_path_factory.mktemp("messy_bags")
    _write(root / "log.csv", _lines(400))
    assert main(["import", str(root / "log.csv"), "--mapping", str(MAPPING), "--config", str(CONFIG), "--out",
                 str(root / "clean")]) == 0
    run = read_run(root / "clean", UR_JOINTS)
    run.joint_states.position[100, 2] = 50.0
    run.commands.effort[200, 0] = 1e6
    write_run(root / "messy", run)
    run.commands.effort[:] *= 100.0
    write_run(root / "wrong_unit", run)
    with tempfile.TemporaryFile("w+") as stream:
        with contextlib.redirect_stdout(stream):
            code = main(["train", "--config", str(CONFIG), "--bags", str(root / "messy"), "--out", str(root / "model"),
                         "--no-baselines", "--no-plots", "--jobs", "1", "--residual-inputs", "qd"])
        stream.seek(0)
        trained = stream.read()
    elapsed = run.joint_states.stamp - run.joint_states.stamp[0]
    return {"root": root, "train": (code, trained), "t100": float(elapsed[100]), "t200": float(elapsed[200])}


def _skipped(bags: dict, tag: str) -> tuple[str, str]:
    bag = bags["root"] / "messy"
    return (f"[{tag}] warning: {bag}: skipped 1 sample of /joint_states, position beyond the joint limits (+0.1 rad), "
            f"at {bags['t100']:.3f} s (first: elbow_joint q = 50 rad, bounds [-3.242, 3.242])",
            f"[{tag}] warning: {bag}: skipped 1 sample of /effort_commands, torque beyond 2× the effort limit, at "
            f"{bags['t200']:.3f} s (first: shoulder_pan_joint τ = 1e+06 N·m, bounds [-300, 300])")


def test_train_skips_samples_beyond_the_physics_naming_bag_topic_time_and_joint(bags):
    code, out = bags["train"]
    assert code == 0, out
    for line in _skipped(bags, "train"):
        assert line in out, line


def test_replay_skips_them_and_counts_them_in_its_metrics(bags, tmp_path, capsys):
    code = main(["replay", "--config", str(CONFIG), "--model", str(bags["root"] / "model"), "--bag",
                 str(bags["root"] / "messy"), "--out", str(tmp_path / "out"), "--no-plots", "--no-bag",
                 "--ground-truth", "zero"])
    out = capsys.readouterr().out
    assert code == 0
    for line in _skipped(bags, "replay"):
        assert line in out, line
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["skipped_samples"] == {"position": 1, "torque": 1} and metrics["samples"] == 398


def test_diagnose_skips_them(bags, tmp_path, capsys):
    assert main(["diagnose", "--config", str(CONFIG), "--bags", str(bags["root"] / "messy"), "--out",
                 str(tmp_path / "out"), "--no-plots", "--effects", "coulomb_friction"]) == 0
    out = capsys.readouterr().out
    for line in _skipped(bags, "diagnose"):
        assert line in out, line


@pytest.mark.parametrize("command", ["train", "diagnose"])
def test_a_bag_whose_samples_mostly_break_the_physics_is_refused_in_one_line(bags, tmp_path, capsys, command):
    bag = bags["root"] / "wrong_unit"
    code = main([command, "--config", str(CONFIG), "--bags", str(bag), "--out", str(tmp_path / "out"), "--no-plots"])
    assert code == 1 and not (tmp_path / "out").exists()
    _one_line(capsys.readouterr().err, f"{bag}: 0 of 400 samples within the physics of the URDF example-robot-data:ur5",
              "of /effort_commands, torque beyond 2× the effort limit", "check input.torque_source and that the "
              "torque is in N·m")


# --------------------------------------------------------------------------- a failed fit is one line

def _fails(*args, **kwargs):
    raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")


def test_a_failed_diagnosis_fit_is_one_line_naming_the_bag_and_the_effect(bags, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("kvark_ros.gap.fitting.lsq_linear", _fails)
    bag = bags["root"] / "clean"
    code = main(["diagnose", "--config", str(CONFIG), "--bags", str(bag), "--out", str(tmp_path / "out"),
                 "--no-plots", "--effects", "coulomb_friction"])
    assert code == 1 and not (tmp_path / "out").exists()
    _one_line(capsys.readouterr().err, f"{bag}: the diagnosis failed (LinAlgError: the least-squares fit of "
              "coulomb_friction on joint(s) 1", "SVD did not converge in Linear Least Squares); check the bags' "
              "skipped-sample lines above")


def test_a_failed_training_fit_is_one_line_and_keeps_the_previous_model(bags, tmp_path, capsys, monkeypatch):
    model = tmp_path / "model"
    model.mkdir()
    (model / "model.yaml").write_text("previous: model\n")
    monkeypatch.setattr("kvark_ros.core.learning.training.fit_residual", _fails)
    bag = bags["root"] / "clean"
    code = main(["train", "--config", str(CONFIG), "--bags", str(bag), "--out", str(model), "--force",
                 "--no-baselines", "--no-plots", "--jobs", "1", "--residual-inputs", "qd"])
    assert code == 1 and (model / "model.yaml").read_text() == "previous: model\n"
    _one_line(capsys.readouterr().err, f"{bag}: training failed (LinAlgError: SVD did not converge",
              "train on more motion")


def test_a_failed_replay_computation_is_one_line_naming_the_bag(bags, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("kvark_ros.tools.replay.condition_numbers", _fails)
    bag = bags["root"] / "clean"
    code = main(["replay", "--config", str(CONFIG), "--model", str(bags["root"] / "model"), "--bag", str(bag),
                 "--out", str(tmp_path / "out"), "--no-plots", "--no-bag"])
    assert code == 1 and not (tmp_path / "out").exists()
    _one_line(capsys.readouterr().err, f"{bag}: the replay failed (LinAlgError: SVD did not converge")


# --------------------------------------------------------------------------- properties

PROPERTY = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@PROPERTY
@given(kinds=st.lists(st.sampled_from(TEXT_KINDS), min_size=1, max_size=3), seed=st.integers(0, 2 ** 32 - 1))
def test_a_corrupted_csv_imports_within_the_physics_or_is_refused_in_one_line(capsys, kinds, seed):
    with tempfile.TemporaryDirectory() as folder:
        data, _ = corrupt_text("\n".join(_lines(80)) + "\n", np.random.default_rng(seed), kinds)
        log = _write(Path(folder) / "log.csv", data)
        code, _, err = _import(capsys, log, "--config", CONFIG, "--out", Path(folder) / "bag")
        if code == 0:
            assert err == "" and _within_physics(Path(folder) / "bag")
        else:
            _one_line(err, str(log))


@PROPERTY
@given(kinds=st.lists(st.sampled_from(ARRAY_KINDS), min_size=1, max_size=3), seed=st.integers(0, 2 ** 32 - 1),
       suffix=st.sampled_from(["npz", "mat"]))
def test_a_corrupted_npz_or_mat_log_imports_within_the_physics_or_is_refused_in_one_line(capsys, kinds, seed, suffix):
    with tempfile.TemporaryDirectory() as folder:
        arrays, _ = corrupt_arrays(_arrays(80), np.random.default_rng(seed), kinds)
        log = Path(folder) / f"log.{suffix}"
        np.savez(log, **arrays) if suffix == "npz" else savemat(log, arrays)
        code, _, err = _import(capsys, log, *ARRAY_FLAGS, "--config", CONFIG, "--out", Path(folder) / "bag")
        if code == 0:
            assert err == "" and _within_physics(Path(folder) / "bag")
        else:
            _one_line(err, str(log))


@PROPERTY
@given(kinds=st.lists(st.sampled_from(RUN_KINDS), min_size=1, max_size=3), seed=st.integers(0, 2 ** 32 - 1))
def test_a_corrupted_bag_reads_within_the_physics_or_is_refused_in_one_line(bags, kinds, seed):
    config = load_config(CONFIG)
    with tempfile.TemporaryDirectory() as folder:
        run, _ = corrupt_run(read_run(bags["root"] / "clean", UR_JOINTS), np.random.default_rng(seed), kinds)
        write_run(Path(folder) / "bag", run)
        try:
            _, inputs, _, lines = read_checked(Path(folder) / "bag", config, LIMITS)
        except BagError as exc:
            assert "\n" not in str(exc) and str(Path(folder) / "bag") in str(exc)
            return
        assert all(np.isfinite(x).all() and not LIMITS.beyond(kind, x).any()
                   for kind, x in ((POSITION, inputs.q), (VELOCITY, inputs.qd), (TORQUE, inputs.tau_m)))
        assert (np.diff(inputs.stamp) > 0).all() and all("\n" not in line for line in lines)
