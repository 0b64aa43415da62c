"""Every command that writes follows one output rule: an existing non-empty --out is refused in one line before
any work unless --force, a forced run leaves no file of the old output and a failed one leaves it whole; and
replay's estimates bag is written by default only for short recordings."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from kvark_ros.cli import main

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
MESSAGE = "exists and is not empty; pass --force to replace it or choose another --out"
MISSING = "/nonexistent/kvark"          # every input of the refused commands: reading one would fail otherwise

# Each command with inputs that do not exist: the output check must come first to give the output error.
COMMANDS = {
    "simulate": ["simulate", "--scenario", "excitation", "--plant", f"{MISSING}.yaml"],
    "diagnose": ["diagnose", "--config", f"{MISSING}.yaml", "--bags", MISSING],
    "train": ["train", "--config", f"{MISSING}.yaml", "--bags", MISSING],
    "replay": ["replay", "--config", f"{MISSING}.yaml", "--bag", MISSING],
    "evaluate": ["evaluate", "--bags", MISSING, "--model", MISSING],
    "benchmark": ["benchmark", "--robot", "panda", "--plant", f"{MISSING}.yaml"],
    "benchmark --real": ["benchmark", "--real", MISSING, "--config", f"{MISSING}.yaml"],
    "import": ["import", f"{MISSING}.csv", "--time", "t"],
    "init": ["init", "--urdf", f"{MISSING}.urdf", "--robot", "arm"],
}


def _replay(out: Path, *extra: str) -> list[str]:
    """``kvark replay`` of the committed contact bag with the committed model, K-VARK only, no plots."""
    return ["replay", "--config", str(CONFIG), "--model", str(ROOT / "models" / "panda"), "--bag",
            str(ROOT / "bags" / "panda_contact"), "--no-plots", "--out", str(out), *extra]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_non_empty_output_is_refused_in_one_line_before_any_work(command, tmp_path, capsys):
    if command == "simulate" and importlib.util.find_spec("mujoco") is None:
        pytest.skip("simulate needs mujoco")
    out = tmp_path / ("arm.yaml" if command == "init" else "out")
    if command == "init":
        out.write_text("old")
    else:
        out.mkdir()
        (out / "old.txt").write_text("old")
    assert main([*COMMANDS[command], "--out", str(out)]) == 1
    assert capsys.readouterr().err == f"kvark: error: {out}: {MESSAGE}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]      # nothing written, nothing staged


def test_an_empty_output_directory_is_used_without_force(tmp_path, capsys):
    log = tmp_path / "log.csv"
    log.write_text("t,q0,v0,e0\n0,1,2,3\n0.1,1,2,3\n")
    out = tmp_path / "bag"
    out.mkdir()
    assert main(["import", str(log), "--time", "t", "--joints", "j", "--position", "q{i}", "--velocity", "v{i}",
                 "--effort", "e{i}", "--out", str(out)]) == 0
    assert any(out.glob("*.mcap"))


def test_a_forced_replay_leaves_no_file_of_the_old_output(tmp_path, capsys):
    """The old run had 13 observers, plots and a report; the new one writes metrics.json alone."""
    out = tmp_path / "contact"
    (out / "estimates").mkdir(parents=True)
    for name in ("report.md", "joint_torques.png", "estimates/estimates.mcap"):
        (out / name).write_text("old")
    (out / "metrics.json").write_text(json.dumps({"observers": {"oracle": {}}}))
    assert main(_replay(out, "--no-bag", "--force")) == 0
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"]
    assert list(json.loads((out / "metrics.json").read_text())["observers"]) == ["kvark"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["contact"]


def test_a_failed_forced_replay_leaves_the_old_output_whole(tmp_path, monkeypatch, capsys):
    import kvark_ros.tools.replay as replay_module
    out = tmp_path / "contact"
    out.mkdir()
    (out / "metrics.json").write_text("old")

    def failing_write(path, text):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(replay_module, "write_text_atomically", failing_write)     # after the estimates bag
    with pytest.raises(OSError, match="No space left"):
        main(_replay(out, "--force"))
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json"] and (out / "metrics.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["contact"]


def test_the_estimates_bag_of_a_long_recording_only_on_request(tmp_path, monkeypatch, capsys):
    """Above ESTIMATES_BAG_S (here lowered to 1 s for the 5 s contact bag) the bag is skipped with one line that
    says how to get it; --estimates-bag writes it; --no-bag and --estimates-bag exclude each other."""
    import kvark_ros.tools.replay as replay_module
    assert main(_replay(tmp_path / "short")) == 0
    assert (tmp_path / "short" / "estimates").is_dir()               # 5 s: written by default
    monkeypatch.setattr(replay_module, "ESTIMATES_BAG_S", 1.0)
    capsys.readouterr()
    assert main(_replay(tmp_path / "long")) == 0
    skipped = [line for line in capsys.readouterr().out.splitlines() if "estimates bag" in line]
    assert skipped == ["[replay] estimates bag not written: 5 s of data, over 1 s (it would hold every observer's "
                       "outputs at every sample); pass --estimates-bag to write it"]
    assert sorted(p.name for p in (tmp_path / "long").iterdir()) == ["metrics.json"]
    assert main(_replay(tmp_path / "asked", "--estimates-bag")) == 0
    assert (tmp_path / "asked" / "estimates").is_dir()
    with pytest.raises(SystemExit):
        main(_replay(tmp_path / "both", "--estimates-bag", "--no-bag"))
    assert "not allowed with argument" in capsys.readouterr().err
