"""kvark benchmark --real: train on the first part of a contact-free recording, judge false τ_ext on the rest."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.cli import main
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.io import write_run
from kvark_ros.tools.real_benchmark import split


def test_split_is_by_time_and_decimates_to_the_rate():
    stamp = 0.001 * np.arange(1000)                              # 1 kHz for 1 s
    inputs = EstimatorInputs(stamp, np.zeros((1000, 7)), np.zeros((1000, 7)), np.zeros((1000, 7)), "x", 0)
    train, held = split(inputs, 0.7, 500.0)
    assert np.allclose(np.diff(train.stamp), 0.002) and np.allclose(np.diff(held.stamp), 0.002)
    assert train.stamp[-1] < 0.7 * 0.999 <= held.stamp[0] and len(train) + len(held) == 500
    everything, _ = split(inputs, 0.9, 0.0)
    assert len(everything) == 900


@pytest.fixture(scope="module")
def simulated():
    """A 5 s contact-free simulated Panda run."""
    from kvark_ros.sim.scenarios import simulate
    return simulate("panda", "excitation", seed=4, duration=5.0, progress=False)


@pytest.fixture(scope="module")
def recording(simulated, tmp_path_factory):
    """The simulated run recorded like a real robot: joint states with the measured effort, no command topic."""
    path = tmp_path_factory.mktemp("real") / "recording"
    write_run(path, replace(simulated, commands=None))
    return path


def test_real_benchmark_reports_false_torque_coverage_and_contacts_nominal_and_augmented(simulated, recording,
                                                                                            tmp_path, capsys):
    """The command end to end without its figures (--no-plots: the figures are test_plots_honest.py's). The KMP takes
    q̇ alone on every joint: what --residual-inputs auto chooses in both trainings on this recording (the same figures,
    checked), without the selection's fits of every input kind (about half the test's time)."""
    out = tmp_path / "out"
    code = main(["benchmark", "--real", str(recording), "--out", str(out), "--no-baselines",
                 "--observers", "kvark,kf,momentum", "--no-plots", "--residual-inputs", "qd"])
    assert code == 0
    results = json.loads((out / "results.json").read_text())
    assert results["residual_inputs"] == "qd"
    assert [load_model(out / folder).residual.inputs for folder in ("model", "model_augmented")] == [("qd",) * 7] * 2
    assert results["torque_source"] == "joint_states effort (the bag has no effort commands)"
    # 5 s at 500 Hz: 2 500 samples, the first 70 % of the time to train, the rest held out
    assert results["samples"]["train"] == pytest.approx(1750, abs=2)
    assert results["samples"]["held_out"] == pytest.approx(750, abs=2)
    states = simulated.joint_states
    held = states.stamp >= states.stamp[0] + 0.7 * (states.stamp[-1] - states.stamp[0])
    measured = np.mean(np.sqrt(np.mean(np.square(states.effort[held]), axis=0)))     # RMS τ_m, mean of the joints
    for model in ("nominal", "augmented"):
        assert set(results[model]) == {"kvark", "kf", "momentum"}
        for name, entry in results[model].items():
            assert entry["contact"]["contact_free_samples"] == entry["estimates"]
        assert 0.0 <= results[model]["kvark"]["coverage95"] <= 1.0 and results[model]["momentum"]["coverage95"] is None
        # The error is against a zero truth: false torque. kvark's stays below 2.5 % of the torque the drives
        # measure on the held-out part (measured 1.7 % nominal, 1.1 % augmented, of 9.75 N·m), and its residual model
        # learns the friction the model lacks: below 0.7 × the momentum observer's, which has none (measured 0.42
        # nominal, 0.58 augmented).
        kvark = results[model]["kvark"]["joint_rmse_mean"]
        assert kvark < 0.025 * measured, (model, kvark, measured)
        assert kvark < 0.7 * results[model]["momentum"]["joint_rmse_mean"], (model, results[model])
    # The diagnosed augmentation takes the model gap out of every observer's false torque on the held-out part:
    # at most 0.8 × the nominal model's (measured 0.63 kvark, 0.60 kf, 0.46 momentum).
    for name in ("kvark", "kf", "momentum"):
        assert (results["augmented"][name]["joint_rmse_mean"]
                <= 0.8 * results["nominal"][name]["joint_rmse_mean"]), (name, results)
    assert (out / "report.md").read_text().count("| kvark |") == 1
    assert (out / "model" / "model.yaml").is_file() and (out / "diagnosis" / "augmentation.yaml").is_file()
    assert not list(out.rglob("*.png")), "--no-plots draws no figure, the diagnosis' neither"
    # The diagnosis is bounded by the priors of the config's torque measurement, as `kvark diagnose` bounds it:
    # the Panda's link-side sensors (±2 % gain), not the default motor current's ±10 %.
    priors = json.loads((out / "diagnosis" / "diagnosis.json").read_text())["priors"]
    assert (priors["torque_measurement"], priors["max_gain_error"]) == ("link_torque_sensor", 0.02)


def test_real_benchmark_refuses_a_train_share_that_leaves_nothing_to_judge(recording, tmp_path, capsys):
    code = main(["benchmark", "--real", str(recording), "--out", str(tmp_path / "out"), "--train-share", "0.95"])
    assert code == 1 and "--train-share 0.95 is outside [0.1, 0.9]" in capsys.readouterr().err
