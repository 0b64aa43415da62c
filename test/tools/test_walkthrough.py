"""The README's bring-your-own-robot walk-through, as a user runs it: kvark init → kvark import → kvark diagnose →
kvark train → kvark replay --ground-truth zero, on the committed UR5 RTDE logs (examples/, 100 Hz), no script."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from kvark_ros.cli import main

from example_logs import UR_TOOL

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def walked(tmp_path_factory):
    """Every step of the walk-through in a fresh folder (cwd), as the README lists them; training skips the
    baselines and the input selection, which cost minutes and are covered elsewhere."""
    folder = tmp_path_factory.mktemp("walkthrough")
    steps = [
        ["init", "--urdf", "example-robot-data:ur5", "--robot", "myur5", "--out", "config/myur5.yaml"],
        *(["import", str(EXAMPLES / f"ur5_rtde_{i}.csv"), "--mapping", str(EXAMPLES / "ur_rtde_mapping.yaml"),
           "--config", "config/myur5.yaml", "--out", f"bags/myur5_{i}"] for i in (1, 2)),
        ["diagnose", "--config", "config/myur5.yaml", "--bags", "bags/myur5_1", "--out", "results/diagnosis"],
        ["train", "--config", "config/myur5.yaml", "--bags", "bags/myur5_1", "--augmentation",
         "results/diagnosis/augmentation.yaml", "--out", "models/myur5", "--no-baselines", "--residual-inputs", "qd"],
        ["replay", "--config", "config/myur5.yaml", "--bag", "bags/myur5_2", "--ground-truth", "zero",
         "--observers", "kvark,kf,momentum", "--out", "results/replay", "--no-bag"],
    ]
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        for step in steps:
            assert main(step) == 0, step
    return folder


def test_the_diagnosis_finds_the_tool_and_the_friction(walked):
    """The logs' arm carries an unmodelled 1 kg tool and 1.5-4 N·m of Coulomb friction (example_logs.py): the
    diagnosis names both, the tool's mass within 10 % (measured 0.99 kg)."""
    effects = yaml.safe_load((walked / "results/diagnosis/augmentation.yaml").read_text())["effects"]
    names = {effect["name"] for effect in effects}
    assert {"payload", "coulomb_friction"} <= names
    [payload] = [effect for effect in effects if effect["name"] == "payload"]
    assert payload["parameters"]["mass"] == pytest.approx(UR_TOOL.mass, rel=0.1)


def test_the_replay_judges_the_held_out_log_against_zero(walked):
    """On the second log (not trained on) the true external torque is zero: K-VARK's false τ_ext stays under
    0.3 N·m mean joint RMSE (measured 0.13; the unmodelled tool alone weighs several N·m on the shoulder and
    elbow) and the model was trained at the data's rate, so nothing is warned about."""
    metrics = json.loads((walked / "results/replay/metrics.json").read_text())
    assert metrics["ground_truth"].startswith("zero")
    assert metrics["warnings"] == [] and metrics["sample_rate_hz"] == pytest.approx(100.0, rel=0.01)
    assert metrics["model_sample_rate_hz"] == pytest.approx(100.0, rel=0.01)
    assert metrics["observers"]["kvark"]["joint_rmse_mean"] < 0.3
