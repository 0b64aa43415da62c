"""``kvark evaluate``: bag × observer tasks on a Dask cluster give the figures of sequential in-process runs.

The bags are 1 s slices of the committed simulated bags (20 of them, each with its own figures, so a result filed
under the wrong bag is caught), run through the committed model. Timing figures (``us_per_step``,
``decode_seconds``) are wall-clock measurements and differ between any two runs: they are left out of every
comparison; every other figure must be equal to the bit (the same code runs on the same data with one BLAS thread:
the workers get one, and conftest limits this process to one).
"""
from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.cli import main
from kvark_ros.io import CommandSeries, JointStateSeries, RecordedRun, WrenchSeries, read_run, write_run
from kvark_ros.tools import evaluate
from kvark_ros.tools.evaluate import Setup, TaskResult, dask_client, evaluate_bags, evaluate_task, expand_bags, merge
from kvark_ros.tools.replay import replay

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
MODEL = ROOT / "models" / "panda"
COMMITTED = ("panda_payload", "panda_contact", "panda_collision", "panda_excitation_1", "panda_excitation_2")
SLICE = 1.0              # s per bag: 500 samples, enough for the filters to settle and cheap to run 40 times
SLICES = 4               # from each committed bag (all of them are at least 5 s long): 5 × 4 = 20 bags
OBSERVERS = ("kvark", "momentum")     # one with a covariance (coverage figures), one without
TIMINGS = ("us_per_step", "decode_seconds", "start_up_seconds")       # replay alone builds its estimators first


def _window(series, rows):
    """The rows of a joint-state, command or wrench series."""
    if series is None:
        return None
    if isinstance(series, JointStateSeries):
        return JointStateSeries(series.stamp[rows], series.names, series.position[rows], series.velocity[rows],
                                series.effort[rows])
    if isinstance(series, WrenchSeries):
        return WrenchSeries(series.stamp[rows], series.frame_id, series.force[rows], series.torque[rows])
    return CommandSeries(series.stamp[rows], series.effort[rows])


def _slice(run: RecordedRun, start: float, end: float) -> RecordedRun:
    """The messages of ``run`` stamped from ``start`` to ``end`` s after its first joint state."""
    first = run.joint_states.stamp[0]

    def rows(series):
        return None if series is None else (series.stamp >= first + start) & (series.stamp < first + end)

    parts = (run.joint_states, run.commands, run.wrench, run.external_torque)
    return RecordedRun(*(_window(part, rows(part)) for part in parts), source=run.source)


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> list[str]:
    folder = tmp_path_factory.mktemp("bags")
    made = []
    for name in COMMITTED:
        run = read_run(ROOT / "bags" / name)
        for k in range(SLICES):
            path = folder / f"{name}_{k}"
            write_run(path, _slice(run, k * SLICE, (k + 1) * SLICE))
            made.append(str(path))
    return made


def _without_timings(value):
    if isinstance(value, dict):
        return {key: _without_timings(item) for key, item in value.items() if key not in TIMINGS}
    if isinstance(value, list):
        return [_without_timings(item) for item in value]
    return value


def _sequential(bags: list[str], observers=OBSERVERS) -> dict:
    """results.json's content from the tasks run one after another in this process."""
    setup = Setup(str(CONFIG), str(MODEL))
    return merge(bags, observers, [evaluate_task(setup, bag, name) for bag in bags for name in observers])


def test_twenty_bags_on_two_workers_give_the_sequential_figures(bags):
    assert len(bags) == 20
    setup = Setup(str(CONFIG), str(MODEL))
    lines: list[str] = []
    with dask_client(None, 2, len(bags) * len(OBSERVERS), lines.append) as client:
        assert len(client.scheduler_info()["workers"]) == 2
        assert all(info["nthreads"] == 1 for info in client.scheduler_info()["workers"].values())
        tasks = evaluate_bags(client, setup, bags, OBSERVERS, log=lines.append)
        # the model is loaded once per worker (its cache missed once), not once per task
        assert sorted(client.run(lambda: evaluate._loaded.cache_info().misses).values()) == [1, 1]
    parallel = merge(bags, OBSERVERS, tasks)
    sequential = _sequential(bags)
    assert parallel["failed"] == 0 and not any(task.error for task in tasks)
    assert _without_timings(parallel) == _without_timings(sequential)
    figures = {entry["observers"]["kvark"]["joint_rmse_mean"] for entry in parallel["bags"].values()}
    assert len(figures) == len(bags)              # every slice has figures of its own: a mix-up would show
    progress = [line for line in lines if line.startswith("[evaluate] ") and "/40 " in line]
    assert [line.split()[1] for line in progress] == [f"{k}/40" for k in range(1, 41)]


def test_a_task_gives_what_replay_writes_into_metrics_json(bags, tmp_path):
    """The figures of ``kvark replay --no-plots`` for the same bag and observers, and its per-bag fields."""
    from kvark_ros.core.config import load_config
    from kvark_ros.core.estimation.model_store import load_model
    from kvark_ros.core.estimation.robot_model import urdf_sha256
    config = load_config(CONFIG)
    trained = load_model(MODEL, config.joint_names, urdf_sha256(config.urdf))
    bag = bags[5]                                 # a contact slice: contact figures too
    written = replay(config, trained, Path(bag), tmp_path, list(OBSERVERS), write_bag=False, plots=False,
                     log=lambda line: None)
    assert _without_timings(_sequential([bag])["bags"][bag]) == _without_timings(written)


def _corrupt_copy(bag: str, path: Path) -> str:
    """A copy of ``bag`` whose MCAP file is cut in half."""
    path.mkdir()
    for source in Path(bag).iterdir():
        data = source.read_bytes()
        (path / source.name).write_bytes(data[: len(data) // 2] if source.suffix == ".mcap" else data)
    return str(path)


def test_bad_bags_are_error_rows_and_the_others_finish(bags, tmp_path, capsys):
    good = [bags[0], bags[9]]
    missing, corrupt = str(tmp_path / "no_such_bag"), _corrupt_copy(bags[4], tmp_path / "cut")
    out = tmp_path / "out"
    code = main(["evaluate", "--bags", good[0], missing, corrupt, good[1], "--model", str(MODEL), "--config",
                 str(CONFIG), "--observers", ",".join(OBSERVERS), "--workers", "2", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 1
    results = json.loads((out / "results.json").read_text())
    assert list(results["bags"]) == [good[0], missing, corrupt, good[1]]
    assert results["failed"] == 4
    for bad in (missing, corrupt):
        entry = results["bags"][bad]
        assert entry["observers"] == {} and list(entry["errors"]) == list(OBSERVERS)
        assert all(error.startswith("BagError: ") for error in entry["errors"].values())
    assert "no such bag" in results["bags"][missing]["errors"]["kvark"]
    # results.json read back is what the tasks computed in this process, for the good bags and their summary
    sequential = _sequential(good)
    for bag in good:
        assert _without_timings(results["bags"][bag]) == _without_timings(sequential["bags"][bag])
    assert results["summary"]["kvark"]["bags"] == 2 and results["summary"]["kvark"]["failed"] == 2
    assert results["summary"]["kvark"]["joint_rmse_mean"] == round(float(np.mean(
        [sequential["bags"][bag]["observers"]["kvark"]["joint_rmse_mean"] for bag in good])), 6)
    report = (out / "report.md").read_text()
    assert f"| {missing} | – | kvark | error: BagError: " in report and f"| {good[1]} | true external" in report
    assert "[evaluate] 8/8 " in printed and "4 failed" in printed


def test_an_unreachable_scheduler_is_one_error_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(evaluate, "CONNECT_TIMEOUT", 1.0)    # s: nothing will answer; do not wait the default
    with socket.socket() as taken:                           # bound, never listening: a connection is refused
        taken.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{taken.getsockname()[1]}"
        code = main(["evaluate", "--bags", str(ROOT / "bags" / "panda_payload"), "--model", str(MODEL),
                     "--scheduler", address, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err
    assert err.startswith(f"kvark: error: --scheduler {address}: no Dask scheduler reached") and "dask scheduler" in err
    assert not (tmp_path / "out").exists()


def test_without_dask_evaluate_is_one_error_line_naming_the_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)       # `import distributed` now raises ImportError
    code = main(["evaluate", "--bags", str(ROOT / "bags" / "panda_payload"), "--model", str(MODEL),
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err
    assert err.startswith("kvark: error: kvark evaluate runs on Dask, which is not installed")
    assert "pip install dask==2026.8.0 distributed==2026.8.0" in err and not (tmp_path / "out").exists()


def test_no_worker_count_below_one(tmp_path, capsys):
    code = main(["evaluate", "--bags", "x", "--model", str(MODEL), "--workers", "0", "--out", str(tmp_path)])
    assert code == 1 and "--workers 0" in capsys.readouterr().err


def test_expand_bags_keeps_order_drops_repeats_and_keeps_unmatched_patterns(tmp_path):
    for name in ("b_2", "b_1", "c"):
        (tmp_path / name).mkdir()
    patterns = [str(tmp_path / "b_*"), str(tmp_path / "c"), str(tmp_path / "b_1"), str(tmp_path / "z_*")]
    assert expand_bags(patterns) == [str(tmp_path / name) for name in ("b_1", "b_2", "c", "z_*")]


def test_summary_means_skip_bags_without_the_figure_and_count_failures():
    with_truth = {"joint_rmse_mean": 0.25, "force_rmse_mean": 1.0, "coverage95": None, "us_per_step": 10.0,
                  "contact": {"false_contact_share": 0.5, "detection_delay_mean": None}}
    without_truth = {"us_per_step": 30.0, "estimates": 5}
    tasks = [TaskResult("a", "kf", {"ground_truth": "topic"}, with_truth),
             TaskResult("b", "kf", {"ground_truth": "none"}, without_truth),
             TaskResult("c", "kf", None, None, "BagError: c: no such bag")]
    summary = merge(["a", "b", "c"], ["kf"], tasks)["summary"]["kf"]
    assert summary == {"bags": 2, "failed": 1, "joint_rmse_mean": 0.25, "force_rmse_mean": 1.0, "coverage95": None,
                       "false_contact_share": 0.5, "detection_delay_mean": None, "us_per_step": 20.0}


def test_help_loads_neither_dask_nor_distributed():
    code = ("import contextlib, io, json, sys\nfrom kvark_ros.cli import main\n"
            "for argv in (['--help'], ['evaluate', '--help']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
            "        main(argv)\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = json.loads(done.stdout)
    assert "kvark_ros.tools.evaluate" in loaded
    assert not [name for name in loaded if name.split(".")[0] in ("dask", "distributed")]
