"""`kvark train` and `kvark diagnose` take --trim, --rate and --holdout (one sample selection for them, replay and
benchmark --real), and warn about a bag whose ground truth shows contact."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from kvark_ros.cli import main
from kvark_ros.core.config import ConfigError
from kvark_ros.core.estimation.inputs import EstimatorInputs, decimation_step, select_samples

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
FREE = ROOT / "bags" / "panda_excitation_1"        # 8 s at 500 Hz: 4000 samples, no contact
CONTACT = ROOT / "bags" / "panda_contact"          # 5 s at 500 Hz: polishing on a table from 0.9 s
FAST_TRAIN = ("--no-baselines", "--no-plots", "--residual-inputs", "qd", "--jobs", "1")


def _inputs(rate: float = 1000.0, duration: float = 10.0) -> EstimatorInputs:
    stamp = np.arange(int(rate * duration) + 1) / rate
    zeros = np.zeros((len(stamp), 7))
    return EstimatorInputs(stamp, zeros, zeros, zeros, "effort_commands", 3, simulated=True)


def test_trim_drops_seconds_at_both_ends_and_rate_keeps_every_kth_sample():
    inputs = _inputs()                                            # 10 s at 1 kHz: 10 001 samples
    assert len(select_samples(inputs)) == 10001
    trimmed = select_samples(inputs, trim=(1.0, 2.0))
    assert len(trimmed) == 7001 and trimmed.stamp[0] == 1.0 and trimmed.stamp[-1] == 8.0
    assert decimation_step(inputs.stamp, 100.0) == 10 and decimation_step(inputs.stamp, 0.0) == 1
    both = select_samples(inputs, trim=(1.0, 2.0), rate=100.0)
    assert len(both) == 701 and np.allclose(np.diff(both.stamp), 0.01)
    assert (both.torque_source, both.dropped, both.simulated) == ("effort_commands", 3, True)
    with pytest.raises(ConfigError, match="--rate -5"):
        select_samples(inputs, rate=-5.0)
    with pytest.raises(ConfigError, match="--trim 6.0 5.0 leaves 0 samples"):
        select_samples(inputs, trim=(6.0, 5.0))


def test_train_uses_the_trimmed_decimated_samples_and_holds_out_the_share_asked(tmp_path, capsys):
    assert main(["train", "--config", str(CONFIG), "--bags", str(FREE), "--out", str(tmp_path / "all"),
                 "--rate", "100", *FAST_TRAIN]) == 0
    assert main(["train", "--config", str(CONFIG), "--bags", str(FREE), "--out", str(tmp_path / "part"),
                 "--trim", "1", "3", "--rate", "100", "--holdout", "0.5", *FAST_TRAIN]) == 0
    out = capsys.readouterr().out
    assert f"[train] {FREE}: 800 of 4000 samples" in out and f"[train] {FREE}: 400 of 4000 samples" in out
    whole = yaml.safe_load((tmp_path / "all" / "model.yaml").read_text())
    part = yaml.safe_load((tmp_path / "part" / "model.yaml").read_text())
    assert whole["info"]["samples"] == 800 and part["info"]["samples"] == 400     # 8 s and 4 s at 100 Hz
    assert whole["info"]["held_out"] == pytest.approx(0.2 * 800, abs=40)        # default --holdout 0.2
    assert part["info"]["held_out"] == pytest.approx(0.5 * 400, abs=40)
    assert part["info"]["samples_selected"] == {"trim_s": [1.0, 3.0], "rate_hz": 100.0, "holdout": 0.5}
    assert part["sample_rate_hz"] == pytest.approx(100.0)
    assert "warning" not in out


def test_train_warns_about_a_bag_whose_ground_truth_shows_contact(tmp_path, capsys):
    assert main(["train", "--config", str(CONFIG), "--bags", str(FREE), str(CONTACT), "--out", str(tmp_path / "m"),
                 "--rate", "100", *FAST_TRAIN]) == 0
    warnings = [line for line in capsys.readouterr().out.splitlines() if "warning" in line]
    assert warnings == [f"[train] warning: {CONTACT}: ground truth shows external torque up to 8.6 N·m on "
                        "panda_joint4 at 0.9-5.0 s (of 5.0 s); use contact-free bags or --trim it out"]


def test_diagnose_uses_the_selected_samples_and_warns_until_the_contact_is_trimmed_out(tmp_path, capsys):
    common = ["diagnose", "--config", str(CONFIG), "--no-plots", "--effects", "viscous_friction"]
    assert main([*common, "--bags", str(FREE), "--out", str(tmp_path / "all")]) == 0
    assert main([*common, "--bags", str(FREE), "--trim", "1", "3", "--rate", "100", "--holdout", "0.5",
                 "--out", str(tmp_path / "part")]) == 0
    whole = json.loads((tmp_path / "all" / "diagnosis.json").read_text())
    part = json.loads((tmp_path / "part" / "diagnosis.json").read_text())
    assert whole["holdout"] == 0.3 and part["holdout"] == 0.5
    # The diagnosis drops a filter window (0.15 s) at each end and spaces samples ≥ 8 ms apart: 8 s every 8 ms,
    # against 4 s every 10 ms (--rate 100).
    assert sum(whole["samples"].values()) == 963 and sum(part["samples"].values()) == 370
    assert part["samples"]["held_out"] == pytest.approx(part["samples"]["train"], abs=2)
    capsys.readouterr()
    assert main([*common, "--bags", str(CONTACT), "--out", str(tmp_path / "contact")]) == 0
    assert "warning: " + str(CONTACT) + ": ground truth shows external torque" in capsys.readouterr().out
    assert main([*common, "--bags", str(CONTACT), "--trim", "0", "4.2", "--out", str(tmp_path / "free")]) == 0
    out = capsys.readouterr().out
    assert f"{CONTACT}: 400 of 2500 samples" in out and "ground truth shows" not in out
