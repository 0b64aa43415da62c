"""Fuzz: corrupted robot logs and bags through ``kvark import``, ``train``, ``diagnose`` and ``replay``, no traceback.

Every case runs the real command in-process (``kvark_ros.cli.main``) on a tiny corrupted input made from the
committed UR5 RTDE example (``examples/ur5_rtde_1.csv``, 100 Hz) by ``corrupt_logs``: a CSV, NPZ or MAT log for
``kvark import``, or a bag (its data corrupted, or its MCAP file damaged on disk) for the other three. A case
passes when nothing escapes ``main`` (what a user would see as a traceback), no warning is raised, a failure is
exactly one stderr line ``kvark: error: ...`` naming the input, and an imported bag holds nothing that breaks the
physics of the UR5's URDF (finite, within the limits, strictly increasing stamps). Replay reuses one model,
trained once per session by ``kvark train`` on a bag imported from a corrupted log, so a case costs milliseconds.

The seed is fixed; ``KVARK_FUZZ_CASES`` sets the number of cases (default 1000; the figures of a 10 000-case run
are in the command's report). A failing case is reported with its index and corruptions, and reproduces alone.
"""
from __future__ import annotations

import contextlib
import io
import os
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat

from corrupt_logs import corrupt_arrays, corrupt_bytes, corrupt_run, corrupt_text
from example_logs import UR_JOINTS, UR_TORQUE_CONSTANTS
from kvark_ros.cli import main
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.sample_limits import POSITION, TORQUE, VELOCITY, SampleLimits
from kvark_ros.io import read_run, write_run

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "ur5.yaml"
MAPPING = ROOT / "examples" / "ur_rtde_mapping.yaml"
CASES = int(os.environ.get("KVARK_FUZZ_CASES", "1000"))
SEED = 20240601
ROWS = 120                   # rows of a fuzzed log: 1.2 s at 100 Hz, enough for diagnose's filter and held-out part
# Shares of the cases: (what, share). Imports are the cheapest; a replay, diagnose or train case runs its fits.
# A train case's bag is as short as the others: training refuses it (one line, too few samples for its mixture
# models) after reading and checking it; the shared model is trained on a corrupted log, test_messy_logs.py trains
# on a bag with samples skipped.
PLAN = (("csv", 0.45), ("npz", 0.11), ("mat", 0.11), ("replay", 0.22), ("diagnose", 0.06), ("train", 0.05))
ARRAY_FLAGS = ("--time", "t", "--position", "q:{i}", "--velocity", "qd:{i}", "--effort", "current:{i}",
               "--command", "moment:{i}", "--scale", "effort=" + ",".join(map(str, UR_TORQUE_CONSTANTS)),
               "--joints", ",".join(UR_JOINTS))


def _log_text(rows: int) -> str:
    """The first ``rows`` rows of the committed UR5 RTDE example, with its header."""
    lines = (ROOT / "examples" / "ur5_rtde_1.csv").read_text().splitlines()
    return "\n".join(lines[:rows + 1]) + "\n"


def _arrays(text: str) -> dict[str, np.ndarray]:
    """The log's columns as NPZ/MAT arrays: t (T,), q, qd, current, moment (T, 6)."""
    data = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, ndmin=2)
    return {"t": data[:, 0], "q": data[:, 1:7], "qd": data[:, 7:13], "current": data[:, 13:19],
            "moment": data[:, 19:25]}


@pytest.fixture(scope="session")
def fuzz_base(tmp_path_factory):
    """The clean inputs every case corrupts, and one model: ``kvark train`` on a bag imported from a corrupted 6 s
    log (garbage rows, a row of 1e300, a truncated last line, all dropped by the import)."""
    root = tmp_path_factory.mktemp("fuzz_base")
    text = _log_text(ROWS)
    bag = root / "clean_bag"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["import", str(_write(root / "clean.csv", text.encode())), "--mapping", str(MAPPING), "--config",
                     str(CONFIG), "--out", str(bag)]) == 0
        lines = _log_text(600).splitlines()
        lines[200:200] = ["ERROR: RTDE connection lost", lines[0]]
        lines[300] = ",".join(lines[300].split(",")[:7] + ["1e300"] * 18)
        lines[-1] = lines[-1][:40]
        assert main(["import", str(_write(root / "messy.csv", "\n".join(lines).encode())), "--mapping", str(MAPPING),
                     "--config", str(CONFIG), "--out", str(root / "messy_bag")]) == 0
        assert main(["train", "--config", str(CONFIG), "--bags", str(root / "messy_bag"), "--out",
                     str(root / "model"), "--no-baselines", "--no-plots", "--jobs", "1", "--residual-inputs",
                     "qd"]) == 0
    config = load_config(CONFIG)
    (mcap,) = bag.glob("*.mcap")
    return {"root": root, "text": text, "arrays": _arrays(text), "run": read_run(bag, UR_JOINTS),
            "mcap": mcap.read_bytes(), "model": load_model(root / "model", config.joint_names),
            "limits": SampleLimits.from_robot(RobotModel(config.urdf, config.joint_names, config.ee_frame))}


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _run(argv: list[str]) -> tuple[int | None, str, str | None]:
    """``kvark ARGV`` in-process: (exit code, stderr, what escaped main or the warning raised, if anything)."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = main(argv)
        except SystemExit as exc:                      # argparse: a usage line, no traceback
            code = exc.code if isinstance(exc.code, int) else 1
        except Exception as exc:                       # noqa: BLE001 - what a user would see as a traceback
            return None, err.getvalue(), f"{type(exc).__name__}: {exc}"
    if caught:
        return code, err.getvalue(), f"warning {caught[0].category.__name__}: {caught[0].message}"
    return code, err.getvalue(), None


def _physics(bag: Path, limits: SampleLimits) -> str | None:
    """What an imported bag holds that breaks the physics, or None."""
    states = read_run(next(bag.glob("*.mcap")), UR_JOINTS).joint_states      # the file: no metadata.yaml to parse
    problems = [name for name, bad in (
        ("non-finite", not all(np.isfinite(x).all() for x in (states.position, states.velocity, states.effort))),
        ("position", limits.beyond(POSITION, states.position).any()),
        ("velocity", limits.beyond(VELOCITY, states.velocity).any()),
        ("torque", limits.beyond(TORQUE, states.effort).any()), ("stamps", not (np.diff(states.stamp) > 0).all()))
        if bad]
    return ", ".join(problems) or None


def _case(index: int, what: str, base: dict, folder: Path) -> tuple[list[str], Path, list[str]]:
    """The corrupted input of case ``index`` in ``folder``: (its corruptions, the path an error must name, argv)."""
    rng = np.random.default_rng([SEED, index])
    out = folder / "out"
    if what == "csv":
        data, kinds = corrupt_text(base["text"], rng)
        log = _write(folder / "log.csv", data)
        return kinds, log, ["import", str(log), "--mapping", str(MAPPING), "--config", str(CONFIG), "--out", str(out),
                            "--force"]
    if what in ("npz", "mat"):
        arrays, kinds = corrupt_arrays(base["arrays"], rng)
        log = folder / f"log.{what}"
        if what == "npz":
            np.savez(log, **arrays)
        else:
            savemat(log, arrays)
        if rng.random() < 0.1:                         # the file itself damaged
            data = log.read_bytes()
            log.write_bytes(data[:int(rng.integers(0, len(data)))])
            kinds.append("truncated_file")
        return kinds, log, ["import", str(log), *ARRAY_FLAGS, "--config", str(CONFIG), "--out", str(out), "--force"]
    bag = folder / "bag"
    if rng.random() < 0.2:                             # a bag damaged on disk
        data, kinds = corrupt_bytes(base["mcap"], rng)
        write_run(bag, base["run"], force=True)
        if data is None:
            (bag / "metadata.yaml").unlink()
        else:
            next(bag.glob("*.mcap")).write_bytes(data)
    else:
        run, kinds = corrupt_run(base["run"], rng)
        write_run(bag, run, force=True)
    command = {"replay": ["replay", "--model", str(base["root"] / "model"), "--bag", str(bag), "--no-plots",
                          "--no-bag", "--ground-truth", "zero"],
               "diagnose": ["diagnose", "--bags", str(bag), "--no-plots", "--effects",
                            "coulomb_friction,torque_offset"],
               "train": ["train", "--bags", str(bag), "--no-baselines", "--no-plots", "--jobs", "1",
                         "--residual-inputs", "qd"]}[what]
    return kinds, bag, [*command, "--config", str(CONFIG), "--out", str(out), "--force"]


def test_corrupted_logs_and_bags_never_give_a_traceback(fuzz_base, tmp_path, monkeypatch):
    monkeypatch.setattr("kvark_ros.tools.replay.load_model", lambda *args, **kwargs: fuzz_base["model"])
    shares = np.cumsum([share for _, share in PLAN])
    failures, outcomes, seconds = [], {what: {"ok": 0, "refused": 0} for what, _ in PLAN}, {}
    for index in range(CASES):
        what = PLAN[int(np.searchsorted(shares, (index + 0.5) / CASES))][0]
        folder = tmp_path / "case"        # every case overwrites the last one's files (--force): no cleaning up
        folder.mkdir(exist_ok=True)
        kinds, given, argv = _case(index, what, fuzz_base, folder)
        started = time.perf_counter()
        code, err, escaped = _run(argv)
        seconds[what] = seconds.get(what, 0.0) + time.perf_counter() - started
        lines = err.rstrip("\n").split("\n")
        problem = escaped
        if problem is None and code == 0 and what in ("csv", "npz", "mat"):
            problem = _physics(folder / "out", fuzz_base["limits"])
        elif problem is None and code != 0 and not (
                len(lines) == 1 and lines[0].startswith("kvark: error: ") and str(given) in lines[0]):
            problem = f"exit {code}, stderr not one line naming {given.name}: {err!r}"
        if problem is not None:
            failures.append(f"case {index} ({what}: {', '.join(kinds)}): {problem}")
        outcomes[what]["ok" if code == 0 else "refused"] += 1
    print(f"fuzz: {CASES} cases, {outcomes}, {len(failures)} failures; s per kind "
          f"{ {what: round(value, 1) for what, value in seconds.items()} }")
    assert not failures, "\n".join(failures[:20])
    if CASES >= 500:       # every kind of input both imported or run and refused: the corruptions span both
        assert all(counts["ok"] and counts["refused"] for what, counts in outcomes.items() if what != "train"), outcomes
