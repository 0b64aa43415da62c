"""``kvark import``: robot logs (UR RTDE CSV, libfranka text log, NPZ, MAT) to bags, and back, exactly.

The logs are made here from known trajectories (``ur_rtde_log``, ``franka_log``), so every test knows what
the bag must hold. The committed examples under ``examples/`` are physical logs from ``example_logs.py``;
``test_committed_examples_are_the_generated_ones_and_import_cleanly`` keeps them in step.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.io import savemat

from kvark_ros.cli import main
from example_logs import PANDA_JOINTS, UR_JOINTS, UR_TORQUE_CONSTANTS, write_examples
from example_logs import PANDA_MAPPING as FRANKA_MAPPING
from example_logs import UR_MAPPING
from kvark_ros.io import read_run

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def _trajectory(t: np.ndarray, joints: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth excitation q, its exact q̇ and a torque (T, joints) at the times ``t`` (s from the start)."""
    rng = np.random.default_rng(seed)
    amplitude, frequency = rng.uniform(0.2, 0.6, joints), rng.uniform(0.2, 0.8, joints)
    phase, offset = rng.uniform(0, 2 * np.pi, joints), rng.uniform(-1.5, 1.5, joints)
    arg = 2 * np.pi * frequency * t[:, None] + phase
    q = offset + amplitude * np.sin(arg)
    qd = amplitude * 2 * np.pi * frequency * np.cos(arg)
    torque = rng.uniform(-20, 20, joints) * np.cos(q) + 2.0 * qd
    return q, qd, torque


def ur_rtde_log(seconds: float = 2.0, seed: int = 1) -> tuple[str, dict[str, np.ndarray]]:
    """A UR RTDE CSV at 100 Hz (6 joints): jittered stamps, three rows with a NaN, one repeated stamp.

    Returns the text and what it holds: ``t`` (s), ``q``, ``qd``, ``current`` (A), ``moment`` (N·m) as
    written, and ``kept``, the rows an import keeps.
    """
    rng = np.random.default_rng(seed)
    rows = int(round(seconds * 100))
    elapsed = np.arange(rows) * 0.01 + rng.uniform(-8e-4, 8e-4, rows)
    t = np.round(4502.125 + elapsed, 6)
    t[101] = t[100]                                     # a repeated stamp: the second row is dropped
    q, qd, moment = (np.round(x, 6) for x in _trajectory(elapsed, 6, seed))
    current = np.round(moment / np.array(UR_TORQUE_CONSTANTS), 6)
    q[37, 2], qd[38, 0], current[120, 5] = np.nan, np.nan, np.nan
    header = ["timestamp"] + [f"{name}_{i}" for name in ("actual_q", "actual_qd", "actual_current", "target_moment")
                              for i in range(6)]
    lines = [",".join(header)]
    for k in range(rows):
        values = [f"{t[k]:.6f}"] + [f"{v:.6f}" for v in np.concatenate([q[k], qd[k], current[k], moment[k]])]
        lines.append(",".join(values))
    kept = np.setdiff1d(np.arange(rows), [37, 38, 101, 120])
    return "\n".join(lines) + "\n", {"t": t, "q": q, "qd": qd, "current": current, "moment": moment, "kept": kept}


def franka_log(seconds: float = 2.0, seed: int = 2) -> tuple[str, dict[str, np.ndarray]]:
    """A libfranka-style whitespace log at 1 kHz (7 joints): time in ms, three lost packets.

    Columns ``time q1..q7 dq1..dq7 tau_J1..tau_J7``, rounded as a compact log would be (q 0.1 mrad, q̇
    1 mrad/s, τ 0.1 N·m) to keep the example small.
    """
    rows = int(round(seconds * 1000))
    time_ms = 61_000 + np.arange(rows + 3)
    time_ms = np.delete(time_ms, [500, 1200, 1201])  # lost packets: the stamps jump by 2 and 3 ms
    q, qd, tau = _trajectory((time_ms - time_ms[0]) / 1000.0, 7, seed)
    q, qd, tau = np.round(q, 4), np.round(qd, 3), np.round(tau, 1)
    header = ["time"] + [f"{name}{i}" for name in ("q", "dq", "tau_J") for i in range(1, 8)]
    lines = [" ".join(header)]
    for k in range(rows):
        lines.append(" ".join([str(time_ms[k])] + [f"{v:.4f}" for v in q[k]] + [f"{v:.3f}" for v in qd[k]]
                              + [f"{v:.1f}" for v in tau[k]]))
    return "\n".join(lines) + "\n", {"t": time_ms / 1000.0, "q": q, "qd": qd, "tau": tau}



def _write(tmp_path: Path, name: str, text: str | dict) -> Path:
    path = tmp_path / name
    path.write_text(text if isinstance(text, str) else yaml.safe_dump(text))
    return path


def _import(*args: str | Path) -> int:
    return main(["import", *map(str, args)])


def test_ur_rtde_csv_round_trip(tmp_path, capsys):
    text, truth = ur_rtde_log()
    log, mapping = _write(tmp_path, "ur.csv", text), _write(tmp_path, "ur.yaml", UR_MAPPING)
    bag = tmp_path / "bag"
    assert _import(log, "--mapping", mapping, "--joints", ",".join(UR_JOINTS), "--out", bag) == 0
    out = capsys.readouterr().out
    assert "196 of 200 kept; dropped: 4" in out
    assert "NaN or Inf in q, q̇ or τ: 3 rows (line 39 to line 122; first: elbow_joint q = nan)" in out
    assert "repeated stamp: 1 row (line 103; " in out
    assert "100.0 Hz median" in out and "/joint_states (196), /effort_commands (196)" in out
    run = read_run(bag, UR_JOINTS)
    kept = truth["kept"]
    np.testing.assert_allclose(run.joint_states.stamp, truth["t"][kept], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(run.joint_states.position, truth["q"][kept])
    np.testing.assert_array_equal(run.joint_states.velocity, truth["qd"][kept])
    np.testing.assert_array_equal(run.joint_states.effort, truth["current"][kept] * np.array(UR_TORQUE_CONSTANTS))
    np.testing.assert_array_equal(run.commands.effort, truth["moment"][kept])
    np.testing.assert_array_equal(run.commands.stamp, run.joint_states.stamp)
    assert run.wrench is None and run.external_torque is None


def test_franka_text_log_round_trip_with_ms_stamps_and_lost_packets(tmp_path, capsys):
    text, truth = franka_log()
    log, mapping = _write(tmp_path, "franka.txt", text), _write(tmp_path, "franka.yaml", FRANKA_MAPPING)
    bag = tmp_path / "bag"
    assert _import(log, "--mapping", mapping, "--out", bag) == 0
    out = capsys.readouterr().out
    assert "2000 of 2000 kept; dropped: none" in out
    assert "1000.0 Hz median" in out and "longest 3 ms" in out and "τ_m is the effort of /joint_states" in out
    run = read_run(bag)
    assert run.joint_names == PANDA_JOINTS and run.commands is None
    np.testing.assert_allclose(run.joint_states.stamp, truth["t"], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(run.joint_states.position, truth["q"])
    np.testing.assert_array_equal(run.joint_states.velocity, truth["qd"])
    np.testing.assert_array_equal(run.joint_states.effort, truth["tau"])


def test_npz_with_wrench_and_external_torque_from_flags(tmp_path, capsys):
    t = 10.0 + np.cumsum(np.full(50, 0.002))
    q, qd, tau = _trajectory(t, 3, seed=5)
    ext, ft = np.sin(t)[:, None] * [1.0, 2.0, 3.0], np.cos(t)[:, None] * np.arange(1.0, 7.0)
    ext[7] = np.nan                                 # one missing ground-truth sample: only that message is left out
    np.savez(tmp_path / "log.npz", t=t, q=q, qd=qd, tau=tau, ext=ext, ft=ft, names=np.array(["a", "b", "c"]))
    bag = tmp_path / "bag"
    assert _import(tmp_path / "log.npz", "--time", "t", "--joints", "a,b,c", "--position", "q:{i}", "--velocity",
                   "qd:{i}", "--command", "tau:{i}", "--external-torque", "ext:{i}", "--wrench",
                   ",".join(f"ft:{k}" for k in range(6)), "--wrench-frame", "tool0", "--scale", "command=2",
                   "--out", bag) == 0
    out = capsys.readouterr().out
    assert "/ground_truth/external_joint_torque: 1 of 50 rows left out (not finite or beyond the bounds)" in out
    assert "effort: not mapped, written as NaN" in out
    run = read_run(bag)
    np.testing.assert_array_equal(run.commands.effort, 2 * tau)
    assert np.isnan(run.joint_states.effort).all()
    np.testing.assert_array_equal(run.wrench.force, ft[:, :3])
    np.testing.assert_array_equal(run.wrench.torque, ft[:, 3:])
    assert run.wrench.frame_id == "tool0"
    np.testing.assert_array_equal(run.external_torque.effort, np.delete(ext, 7, axis=0))
    np.testing.assert_allclose(run.external_torque.stamp, np.delete(t, 7), rtol=0, atol=1e-9)


def test_imported_bag_names_its_log_and_is_not_taken_for_a_simulation(tmp_path):
    t = np.arange(1, 6) * 0.01
    np.savez(tmp_path / "log.npz", t=t, q=t, qd=t, tau=t, ext=t)
    assert _import(tmp_path / "log.npz", "--time", "t", "--joints", "a", "--position", "q", "--velocity", "qd",
                   "--effort", "tau", "--external-torque", "ext", "--out", tmp_path / "bag") == 0
    run = read_run(tmp_path / "bag")
    assert run.external_torque is not None                   # a true-torque topic, which simulated bags have
    assert run.source == "import: log.npz" and not run.simulated


def test_mat_in_matlab_orientation_with_differentiated_velocity_in_degrees(tmp_path, capsys):
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.004, 0.006, 80))                 # irregular 200 Hz stamps, kept as they are
    q, _, tau = _trajectory(t, 2, seed=7)
    savemat(tmp_path / "log.mat", {"t": t[None, :], "q_deg": np.degrees(q).T, "tau": tau.T})
    bag = tmp_path / "bag"
    assert _import(tmp_path / "log.mat", "--time", "t", "--joints", "j1,j2", "--position", "q_deg:{i}",
                   "--scale", f"position={math.pi / 180}", "--command", "tau:{i}", "--differentiate-velocity",
                   "--out", bag) == 0
    assert "central difference of the position" in capsys.readouterr().out
    run = read_run(bag)
    stamp = run.joint_states.stamp
    np.testing.assert_allclose(stamp, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.joint_states.position, q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(run.joint_states.velocity, np.gradient(run.joint_states.position, stamp, axis=0),
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(run.commands.effort, tau)


def test_out_of_order_rows_are_dropped_and_counted(tmp_path, capsys):
    """A stamp that goes back, one that repeats and one that spikes forward each cost their own row (the fewest rows
    whose removal leaves time strictly increasing; the spike, a step of 10^4 median steps, is far from the rest)."""
    stamps = ["0.0", "0.1", "0.2", "0.15", "0.3", "0.3", "1000", "0.4"]
    rows = "".join(f"{t},{k + 1},0,0\n" for k, t in enumerate(stamps))
    log = _write(tmp_path, "log.csv", "t,q0,v0,e0\n" + rows)
    bag = tmp_path / "bag"
    assert _import(log, "--time", "t", "--joints", "j", "--position", "q{i}", "--velocity", "v{i}", "--effort",
                   "e{i}", "--out", bag) == 0
    out = capsys.readouterr().out
    assert "5 of 8 kept; dropped: 3" in out
    assert "repeated stamp: 1 row (line 7; first: stamp 0.3 s" in out
    assert "stamp out of order: 1 row (line 5; first: stamp 0.15 s)" in out
    assert "stamp far from its neighbours (a step over 100 median steps): 1 row (line 8; first: stamp 1000 s" in out
    run = read_run(bag)
    np.testing.assert_array_equal(run.joint_states.position[:, 0], [1, 2, 3, 5, 8])


BASE = ("--time", "t", "--joints", "j", "--position", "q{i}", "--velocity", "v{i}", "--effort", "e{i}")


@pytest.mark.parametrize("content, args, message", [
    ("t,q0,v0\n0,1,2\n", BASE, "has no column 'e0'; its columns are t, q0, v0"),
    ("t,q0,v0,e0\n0,1,2,3\n0.1,1,abc,3\n", BASE, "too little left: 1 of 2 rows usable (a cell that is not a "
     "number: 1 line (line 3; first: line 3, column 'v0': 'abc' is not a number))"),
    ("t,q0,v0,e0\n0,1,2\n", BASE, "line 2 has 3 fields, the header has 4"),
    ("", BASE, "is empty (no header row)"),
    ("t,q0,v0,e0\n", BASE, "has a header but no data rows"),
    ("t,q0,v0,e0\nnan,1,2,3\n0,nan,2,3\n", BASE, "too little left: 0 of 2 rows usable (stamp not finite or out of "
     "range: 1 row (line 2; first: stamp nan s); NaN or Inf in q, q̇ or τ: 1 row (line 3; first: j q = nan))"),
    ("t,q0,v0,e0\n-1.5,1,2,3\n", BASE, "pass --time-offset 2"),
    ("t,q0,e0\n0,1,3\n", BASE[:6] + ("--effort", "e{i}"), "no velocity columns"),
    ("t,q0,v0\n0,1,2\n", BASE[:8], "no joint torque"),
    ("t,q0,v0,e0\n0,1,2,3\n", BASE[2:], "time needs a column"),
    ("t,q0,v0,e0\n0,1,2,3\n", ("--time", "t", *BASE[4:]), "no joint names"),
    ("t,q0,v0,e0\n0,1,2,3\n", BASE + ("--scale", "speed=2"), "--scale 'speed=2'"),
    ("t,q0,v0,e0\n0,1,2,3\n", BASE + ("--joints", "j,j"), "--joints 'j,j': expected distinct"),
])
def test_bad_input_is_one_error_line_and_no_bag(tmp_path, capsys, content, args, message):
    log, bag = _write(tmp_path, "log.csv", content), tmp_path / "bag"
    assert _import(log, *args, "--out", bag) == 1
    err = capsys.readouterr().err
    assert err.startswith("kvark: error: ") and err.count("\n") == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]       # no bag, no temporary directory


@pytest.mark.parametrize("mapping, message", [
    ({"time": "t", "positions": "q{i}"}, "unknown key 'positions'; allowed: format, time, first_index"),
    ({"time": {"column": "t", "unit": "min"}}, "time.unit 'min' is not one of s, ms, us, ns"),
    ({"time": "t", "first_index": 2}, "first_index must be 0 or 1"),
    ({"time": "t", "command": {"pattern": "e{i}", "scale": [1, 2]}}, "command.scale has 2 values, expected 1 or 1"),
    ({"time": "t", "wrench": "f{i}"}, "wrench needs the sensor's frame name"),
    ({"time": "t", "command": {"pattern": "e{i}", "columns": ["e0"]}}, "needs exactly one of 'columns' and 'pattern'"),
    ({"time": "t", "command": ["e0", "e1"]}, "command lists 2 columns, expected 1 (one per joint)"),
    ("[1, 2", "invalid YAML"),
    ("[1, 2]", "expected a YAML mapping of keys"),
])
def test_bad_mapping_is_one_error_line(tmp_path, capsys, mapping, message):
    log = _write(tmp_path, "log.csv", "t,q0,v0,e0\n0,1,2,3\n")
    path = _write(tmp_path, "map.yaml", mapping)
    assert _import(log, "--mapping", path, *BASE[2:], "--out", tmp_path / "bag") == 1
    err = capsys.readouterr().err
    assert err.startswith("kvark: error: ") and err.count("\n") == 1 and message in err, err


def test_unknown_format_and_missing_file(tmp_path, capsys):
    assert _import(_write(tmp_path, "log.xyz", "t\n0\n"), *BASE, "--out", tmp_path / "bag") == 1
    assert "unknown file format (suffix '.xyz'); pass --format csv|npz|mat" in capsys.readouterr().err
    assert _import(tmp_path / "nope.csv", *BASE, "--out", tmp_path / "bag") == 1
    assert "nope.csv: no such file" in capsys.readouterr().err
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    assert _import(tmp_path / "bad.npz", *BASE, "--out", tmp_path / "bag") == 1
    assert "is not a readable NPZ file" in capsys.readouterr().err


def test_existing_output_is_refused_unless_force(tmp_path, capsys):
    log = _write(tmp_path, "log.csv", "t,q0,v0,e0\n0,1,2,3\n0.1,1,2,3\n")
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "keep.txt").write_text("old")
    assert _import(log, *BASE, "--out", bag) == 1
    assert "exists and is not empty; pass --force" in capsys.readouterr().err
    assert (bag / "keep.txt").exists()
    assert _import(log, *BASE, "--out", bag, "--force") == 0
    assert not (bag / "keep.txt").exists() and len(read_run(bag).joint_states.stamp) == 2


def test_committed_examples_are_the_generated_ones_and_import_cleanly(tmp_path, capsys):
    """examples/ holds what test/example_logs.py writes (numbers equal to their last printed digit: the RNEA may
    round differently on another machine), and each log imports with its mapping."""
    generated = tmp_path / "examples"
    write_examples(generated)
    for path in generated.iterdir():
        committed = (EXAMPLES / path.name).read_text().splitlines()
        fresh = path.read_text().splitlines()
        assert committed[0] == fresh[0] and len(committed) == len(fresh), "regenerate: python test/example_logs.py"
        if path.suffix in (".csv", ".txt"):
            separator = "," if path.suffix == ".csv" else None
            a, b = (np.array([line.split(separator) for line in lines[1:]], dtype=float)
                    for lines in (committed, fresh))
            np.testing.assert_allclose(a, b, rtol=0, atol=0.011)     # 0.01 N·m: the coarsest digit written
    for name in ("ur5_rtde_1.csv", "ur5_rtde_2.csv"):
        assert _import(EXAMPLES / name, "--mapping", EXAMPLES / "ur_rtde_mapping.yaml",
                       "--config", ROOT / "config" / "ur5.yaml", "--out", tmp_path / name) == 0
        assert read_run(tmp_path / name).joint_names == UR_JOINTS
    assert _import(EXAMPLES / "panda_log_2.txt", "--mapping", EXAMPLES / "franka_log_mapping.yaml",
                   "--out", tmp_path / "panda") == 0
    assert len(read_run(tmp_path / "panda").joint_states.stamp) == 4000


def test_headerless_log_with_columns_by_position_and_ranges(tmp_path, capsys):
    """The UR log without its header row (as the UR10e logs of Mamedov et al. 2020 are written): ``--no-header``
    names the columns 1 … 25, ``--position 2-7`` is a range; the bag equals the one the header row gives."""
    text, truth = ur_rtde_log()
    headerless = _write(tmp_path, "ur.csv", text.split("\n", 1)[1])
    bag = tmp_path / "bag"
    scale = "effort=" + ",".join(str(k) for k in UR_TORQUE_CONSTANTS)
    assert _import(headerless, "--no-header", "--time", "1", "--position", "2-7", "--velocity", "8,9,10,11,12,13",
                   "--effort", "14-19", "--scale", scale, "--command", "20-25", "--joints", ",".join(UR_JOINTS),
                   "--out", bag) == 0
    assert "196 of 200 kept" in capsys.readouterr().out
    run = read_run(bag, UR_JOINTS)
    kept = truth["kept"]
    np.testing.assert_array_equal(run.joint_states.position, truth["q"][kept])
    np.testing.assert_array_equal(run.joint_states.velocity, truth["qd"][kept])
    np.testing.assert_array_equal(run.joint_states.effort, truth["current"][kept] * np.array(UR_TORQUE_CONSTANTS))
    np.testing.assert_array_equal(run.commands.effort, truth["moment"][kept])


def test_headerless_mapping_file_and_its_errors(tmp_path, capsys):
    text, _ = ur_rtde_log()
    headerless = _write(tmp_path, "ur.csv", text.split("\n", 1)[1])
    mapping = _write(tmp_path, "m.yaml", {"header": False, "time": 1, "position": "2-7", "velocity": [8, 9, 10, 11,
                                                                                                       12, 13],
                                          "effort": {"columns": "14-19", "scale": list(UR_TORQUE_CONSTANTS)}})
    assert _import(headerless, "--mapping", mapping, "--joints", ",".join(UR_JOINTS), "--out", tmp_path / "a") == 0
    capsys.readouterr()
    # without --no-header the first data row would be taken for column names: one line naming the flag
    assert _import(headerless, "--time", "1", "--position", "2-7", "--velocity", "8-13", "--effort", "14-19",
                   "--joints", ",".join(UR_JOINTS), "--out", tmp_path / "b") != 0
    assert "pass --no-header" in capsys.readouterr().err
    # a range past the last column names the missing column and what the log has
    assert _import(headerless, "--no-header", "--time", "1", "--position", "2-7", "--velocity", "8-13", "--effort",
                   "21-26", "--joints", ",".join(UR_JOINTS), "--out", tmp_path / "c") != 0
    assert "has no column '26'" in capsys.readouterr().err
    assert _import(headerless, "--no-header", "--time", "1", "--position", "7-2", "--velocity", "8-13", "--effort",
                   "14-19", "--joints", ",".join(UR_JOINTS), "--out", tmp_path / "d") != 0
    assert "column range '7-2'" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in "bcd")
