"""The offline half (issue 4): `kvark train`, `kvark replay`, ground truth, metrics, every observer.

Simulated bags are short (3-4 s at 500 Hz) and made once per module; the trainer runs twice
(the `kvark train` CLI on simulated excitation bags, and `train_model` on a frictionless
synthetic stream for the known-answer observer test), both without the learned baselines.
The three learned baselines are fitted directly with light settings (see `frictionless`).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from kvark_ros import __version__
from kvark_ros.cli import main
from kvark_ros.core.config import OBSERVER_NAMES, load_config
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import MODEL_FILE, load_model, save_model
from kvark_ros.core.estimation.residual import ResidualModelError
from kvark_ros.core.estimation.robot_model import RobotModel, resolve_urdf
from kvark_ros.io import BagWriter, TopicNames, read_run, write_run
from kvark_ros.io.recorded_inputs import estimator_inputs
from kvark_ros.tools.metrics import observer_metrics
from kvark_ros.tools.replay import GroundTruth, ObserverRun, ground_truth, replay, run_observer

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
N = 7
RATE = 500.0
EXCITATION_S = 3.0
PAYLOAD_S = 4.0
REPLAY_OBSERVERS = ("kvark", "kf", "momentum")
INPUT_TOPICS = ("/joint_states", "/effort_commands", "/ft_sensor/wrench", "/ground_truth/external_joint_torque")
METRIC_SCALARS = ("joint_rmse_mean", "force_rmse_mean", "moment_rmse_mean", "mean_abs", "p95", "max",
                  "temporal_std", "us_per_step")


# --------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


@pytest.fixture(scope="module")
def robot(config) -> RobotModel:
    return RobotModel.from_config(config)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """Two excitation bags (MCAP and sqlite3) for training and one payload bag (MCAP) for replay."""
    from kvark_ros.sim.scenarios import run_scenario, simulate
    root = tmp_path_factory.mktemp("bags")
    mcap, sqlite, payload = root / "excitation_mcap", root / "excitation_sqlite", root / "payload"
    write_run(mcap, simulate("panda", "excitation", seed=1, duration=EXCITATION_S, progress=False))
    write_run(sqlite, simulate("panda", "excitation", seed=2, duration=EXCITATION_S, progress=False),
              storage="sqlite3")
    payload_sim = run_scenario("panda", "payload", seed=1, duration=PAYLOAD_S, progress=False)
    write_run(payload, payload_sim.run)
    return SimpleNamespace(root=root, mcap=mcap, sqlite=sqlite, payload=payload, payload_sim=payload_sim)


@pytest.fixture(scope="module")
def cli_model(bags, tmp_path_factory) -> Path:
    """`kvark train` on the MCAP and the sqlite3 excitation bag (no baselines, with plots)."""
    out = tmp_path_factory.mktemp("models") / "panda"
    code = main(["train", "--config", str(CONFIG), "--bags", str(bags.mcap), str(bags.sqlite),
                 "--out", str(out), "--no-baselines"])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def cli_replay(bags, cli_model, tmp_path_factory) -> Path:
    """`kvark replay` of the payload bag with kvark, kf and momentum."""
    out = tmp_path_factory.mktemp("replay")
    code = main(["replay", "--config", str(CONFIG), "--model", str(cli_model), "--bag", str(bags.payload),
                 "--observers", ",".join(REPLAY_OBSERVERS), "--out", str(out)])
    assert code == 0
    return out


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def _bag_sha256(path: Path) -> str:
    """Independent hash of a bag directory: sha256 over the sha256 hex digests of its files, by path."""
    digest = hashlib.sha256()
    for file in sorted(p for p in path.rglob("*") if p.is_file()):
        digest.update(hashlib.sha256(file.read_bytes()).hexdigest().encode())
    return digest.hexdigest()


def _check_observer_schema(name: str, entry: dict, covariance: bool) -> None:
    """One observer entry of metrics.json against issue 4, item 4."""
    assert len(entry["joint_rmse"]) == N and all(isinstance(v, float) and v >= 0 for v in entry["joint_rmse"]), name
    for key in ("force_rmse", "moment_rmse"):
        assert len(entry[key]) == 3 and all(isinstance(v, float) and v >= 0 for v in entry[key]), (name, key)
    for key in METRIC_SCALARS:
        assert isinstance(entry[key], float) and np.isfinite(entry[key]) and entry[key] >= 0, (name, key)
    assert entry["joint_rmse_mean"] == pytest.approx(np.mean(entry["joint_rmse"]), abs=2e-6)
    assert entry["force_rmse_mean"] == pytest.approx(np.mean(entry["force_rmse"]), abs=2e-6)
    assert entry["moment_rmse_mean"] == pytest.approx(np.mean(entry["moment_rmse"]), abs=2e-6)
    assert entry["mean_abs"] <= entry["max"] and entry["p95"] <= entry["max"]
    if covariance:
        assert isinstance(entry["coverage95"], float) and 0.0 <= entry["coverage95"] <= 1.0, name
    else:
        assert "coverage95" in entry and entry["coverage95"] is None, name


# --------------------------------------------------------------------------- 1. kvark train

def test_cli_train_writes_model_yaml_with_provenance_and_it_round_trips(config, bags, cli_model, tmp_path):
    document = yaml.safe_load((cli_model / MODEL_FILE).read_text())
    info = document["info"]
    assert document["robot"] == "panda" and info["robot"] == "panda"
    assert document["joint_names"] == list(config.joint_names) == info["joint_names"]
    assert document["kvark_ros_version"] == __version__ == info["kvark_ros_version"]
    assert info["urdf_sha256"] == hashlib.sha256(resolve_urdf(config.urdf).encode()).hexdigest()
    assert info["bags"] == [{"name": "excitation_mcap", "sha256": _bag_sha256(bags.mcap)},
                            {"name": "excitation_sqlite", "sha256": _bag_sha256(bags.sqlite)}]
    assert any(p.suffix == ".db3" for p in bags.sqlite.iterdir())       # really the sqlite3 storage
    # Both bags were used, every sample of each (500 Hz, no dropped commands).
    assert info["samples"] == 2 * int(EXCITATION_S * RATE)
    for key in ("process_noise_density", "measurement_variance", "empirical_variance", "residual_variance"):
        values = document["filter_tuning"][key]
        assert len(values) == N and all(v > 0 for v in values), key
    assert set(document["momentum_noise"]) >= {"momentum_variance", "torque_density"}
    assert all(len(v) == N for v in document["momentum_noise"].values())
    for key in ("length_scale", "lambda1", "lambda2"):                  # hyperparameters are recorded
        assert len(info["kmp"][key]) == N and all(v > 0 for v in info["kmp"][key])
    assert document["baselines"] == {}                                  # --no-baselines
    assert (cli_model / "training_residuals.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    loaded = load_model(cli_model, config.joint_names)
    assert loaded.robot == "panda" and loaded.joint_names == tuple(config.joint_names)
    assert loaded.tuning.to_dict() == document["filter_tuning"]
    assert loaded.momentum_noise.to_dict() == document["momentum_noise"]
    assert loaded.info == info and loaded.baselines == {}
    # Save the loaded model elsewhere and read it again: same file content, same predictions.
    save_model(tmp_path / "copy", loaded)
    again = load_model(tmp_path / "copy", config.joint_names)
    assert yaml.safe_load((tmp_path / "copy" / MODEL_FILE).read_text()) == document
    qd, q, g = np.random.default_rng(0).uniform(-1.5, 1.5, (3, 50, N))    # pose inputs for joints that take them
    for a, b in zip(loaded.residual.predict_batch(qd, q, g), again.residual.predict_batch(qd, q, g)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ResidualModelError, match="differ"):
        load_model(cli_model, tuple(reversed(config.joint_names)))


# --------------------------------------------------------------------------- 2. atomic write

def _previous_model(cli_model: Path, tmp_path: Path) -> tuple[Path, dict[str, bytes]]:
    """A copy of the trained model alone in its own parent directory, and its bytes."""
    target = tmp_path / "models" / "panda"
    shutil.copytree(cli_model, target)
    return target, _snapshot(target)


def test_cli_train_on_a_bag_without_joint_states_fails_in_one_line_and_keeps_the_model(
        bags, cli_model, tmp_path, capsys):
    target, before = _previous_model(cli_model, tmp_path)
    no_states = tmp_path / "no_joint_states"
    with BagWriter(no_states) as bag:
        for k in range(10):
            bag.float64_array("/effort_commands", k / RATE, np.zeros(N))
    capsys.readouterr()
    code = main(["train", "--config", str(CONFIG), "--bags", str(bags.mcap), str(no_states),
                 "--out", str(target), "--no-baselines", "--no-plots", "--force"])
    assert code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("kvark: error:") and "\n" not in err
    assert str(no_states) in err and "/joint_states" in err
    assert _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


def test_training_that_raises_keeps_the_previous_model(bags, cli_model, tmp_path, monkeypatch):
    import kvark_ros.core.learning.training as baselines

    def broken_fit(*args, **kwargs):
        raise RuntimeError("GP fit failed")

    monkeypatch.setattr(baselines, "fit_kmp", broken_fit)
    target, before = _previous_model(cli_model, tmp_path)
    with pytest.raises(RuntimeError, match="GP fit failed"):
        main(["train", "--config", str(CONFIG), "--bags", str(bags.mcap), "--out", str(target),
              "--no-baselines", "--no-plots", "--force", "--residual-inputs", "qd"])   # straight to the KMP fit
    assert _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


def test_save_that_fails_halfway_keeps_the_previous_model_and_leaves_no_staging(config, cli_model, tmp_path):
    target, before = _previous_model(cli_model, tmp_path)
    trained = load_model(cli_model, config.joint_names)
    # kmp.npz/kmp.yaml are staged first, then model.yaml cannot be serialised.
    broken = replace(trained, info={**trained.info, "not yaml": object()})
    with pytest.raises(yaml.YAMLError):
        save_model(target, broken)
    assert _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]
    # A successful save over it replaces the content and leaves no staging or backup behind.
    save_model(target, replace(trained, info={**trained.info, "note": "second"}))
    assert yaml.safe_load((target / MODEL_FILE).read_text())["info"]["note"] == "second"
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


def test_save_whose_final_rename_fails_keeps_the_previous_model(config, cli_model, tmp_path, monkeypatch):
    target, before = _previous_model(cli_model, tmp_path)
    trained = load_model(cli_model, config.joint_names)
    real_replace = os.replace

    def failing_replace(src, dst):
        if Path(dst) == target and not str(src).endswith(".previous"):   # staging -> target fails
            raise OSError("rename failed")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError):
        save_model(target, trained)
    monkeypatch.undo()
    assert target.is_dir() and _snapshot(target) == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["panda"]


# --------------------------------------------------------------------------- 3. kvark replay

def test_cli_replay_writes_estimates_bag_metrics_report_and_plots(config, bags, cli_replay):
    estimates = cli_replay / "estimates"
    with Reader(estimates) as reader:
        counts: dict[str, int] = {}
        for conn in reader.connections:
            counts[conn.topic] = counts.get(conn.topic, 0) + conn.msgcount
        samples = int(PAYLOAD_S * RATE)
        for topic in INPUT_TOPICS:
            assert counts[topic] == samples, topic
        for name in REPLAY_OBSERVERS:
            assert counts[f"/kvark/{name}/external_joint_torque"] == samples - 1   # one warm-up sample
            assert counts[f"/kvark/{name}/external_wrench"] == samples - 1
        assert counts["/kvark/kvark/external_joint_torque_stddev"] == samples - 1
        assert counts["/kvark/kf/external_joint_torque_stddev"] == samples - 1
        assert "/kvark/momentum/external_joint_torque_stddev" not in counts   # reports no covariance
        store = get_typestore(Stores.ROS2_JAZZY)
        conns = [c for c in reader.connections if c.topic == "/kvark/kvark/external_joint_torque_stddev"]
        for _, _, raw in reader.messages(connections=conns):
            msg = store.deserialize_cdr(raw, conns[0].msgtype)
            assert msg.layout.dim[0].label == ",".join(config.joint_names)
            assert len(msg.data) == N and np.all(msg.data > 0)
            break

    # The inputs went through unchanged.
    original, copied = read_run(bags.payload, config.joint_names), read_run(estimates, config.joint_names)
    np.testing.assert_array_equal(copied.joint_states.position, original.joint_states.position)
    np.testing.assert_array_equal(copied.commands.effort, original.commands.effort)

    metrics = json.loads((cli_replay / "metrics.json").read_text())
    assert metrics["bag"] == str(bags.payload)
    assert metrics["ground_truth"].startswith("true external joint torque")
    assert list(metrics["observers"]) == list(REPLAY_OBSERVERS)
    for name, entry in metrics["observers"].items():
        _check_observer_schema(name, entry, covariance=name != "momentum")

    # The estimates in the bag are the ones scored: RMSE recomputed from the bag matches metrics.json.
    truth = original.external_torque.effort
    for name in REPLAY_OBSERVERS:
        topic = f"/kvark/{name}/external_joint_torque"
        out = read_run(estimates, config.joint_names, TopicNames(joint_states=topic)).joint_states
        rows = np.searchsorted(original.joint_states.stamp, out.stamp)
        np.testing.assert_array_equal(original.joint_states.stamp[rows], out.stamp)
        rmse = np.sqrt(np.mean((out.effort - truth[rows]) ** 2, axis=0))
        np.testing.assert_allclose(rmse, metrics["observers"][name]["joint_rmse"], atol=2e-6)

    report = (cli_replay / "report.md").read_text()
    for name in REPLAY_OBSERVERS:
        assert f"| {name} |" in report
    for figure in ("joint_torques.png", "wrench.png", "joint_rmse.png"):
        assert (cli_replay / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", figure
        assert f"({figure})" in report


@pytest.mark.parametrize("observer", ["oracle", "gmr_gp"])
def test_cli_replay_observer_the_model_cannot_build_is_a_one_line_user_error(bags, cli_model, tmp_path,
                                                                            capsys, observer):
    argv = ["replay", "--config", str(CONFIG), "--model", str(cli_model), "--bag", str(bags.payload),
            "--observers", observer, "--out", str(tmp_path / "out"), "--no-bag"]
    message = ""
    try:
        code = main(argv)
    except SystemExit as exc:            # SystemExit("kvark: error: ...") prints the text and exits 1
        code, message = (1, exc.code) if isinstance(exc.code, str) else (exc.code, "")
    err = (capsys.readouterr().err + message).strip()
    assert code == 1 and err.startswith("kvark: error:") and "\n" not in err
    assert observer in err


def test_diagnose_then_train_on_the_augmented_model_then_replay(config, bags, cli_model, cli_replay, tmp_path,
                                                                 capsys):
    """`make demo`'s chain (issue 6 scope 2): the augmentation travels with the model, its residuals
    are relative to the augmented model, and the oracle (nominal model + true friction) refuses it."""
    diagnosis, model = tmp_path / "diagnosis", tmp_path / "model"
    assert main(["diagnose", "--config", str(CONFIG), "--bags", str(bags.mcap), str(bags.sqlite),
                 "--out", str(diagnosis), "--no-plots"]) == 0
    named = [effect["name"] for effect in json.loads((diagnosis / "diagnosis.json").read_text())["effects"]]
    assert "coulomb_friction" in named or "viscous_friction" in named    # the default plant's friction
    # q̇ alone on every joint: what --residual-inputs auto chooses here once the augmentation holds the friction (the
    # same KMP bit for bit, checked), without the selection's fits of every input kind (8 of the test's 11 s)
    assert main(["train", "--config", str(CONFIG), "--bags", str(bags.mcap), str(bags.sqlite), "--out", str(model),
                 "--augmentation", str(diagnosis / "augmentation.yaml"), "--no-baselines", "--no-plots",
                 "--residual-inputs", "qd"]) == 0
    assert (model / "augmentation.yaml").read_text() == (diagnosis / "augmentation.yaml").read_text()
    trained, nominal = load_model(model, config.joint_names), load_model(cli_model, config.joint_names)
    assert trained.info["augmentation"]["effects"] == named
    # friction moved from the learned residual into the model: the KMP's residual is smaller (at the bag's first
    # pose, q̇ 0.5 rad/s on every joint, g(q) of each model for joints that take it)
    q = estimator_inputs(read_run(bags.mcap, config.joint_names), config.input.command_max_age).q[0]
    sizes = [np.mean(np.abs(model.residual.predict(np.full(N, 0.5), q, RobotModel.from_config(
        config, model.augmentation).gravity(q))[0])) for model in (trained, nominal)]
    assert sizes[0] < sizes[1], sizes
    plant = str(ROOT / "kvark_ros/sim/plants/panda_default.yaml")
    assert main(["replay", "--config", str(CONFIG), "--model", str(model), "--bag", str(bags.payload),
                 "--observers", "kvark,kf", "--plant", plant, "--out", str(tmp_path / "replay"), "--no-bag"]) == 0
    capsys.readouterr()
    assert main(["replay", "--config", str(CONFIG), "--model", str(model), "--bag", str(bags.payload),
                 "--observers", "oracle", "--plant", plant, "--out", str(tmp_path / "oracle"), "--no-bag"]) == 1
    assert "augmented" in capsys.readouterr().err
    # On the payload bag the augmented model's kvark errs no more than the nominal model's (cli_replay, same bag;
    # 10 % margin: measured 0.249 against 0.258 N·m), and its residual still helps: below kf's, the same filter
    # without it (measured 0.249 against 0.412 N·m: bound 0.75 ×)
    observers = json.loads((tmp_path / "replay" / "metrics.json").read_text())["observers"]
    nominal = json.loads((cli_replay / "metrics.json").read_text())["observers"]
    assert observers["kvark"]["joint_rmse_mean"] <= 1.1 * nominal["kvark"]["joint_rmse_mean"], (observers, nominal)
    assert observers["kvark"]["joint_rmse_mean"] < 0.75 * observers["kf"]["joint_rmse_mean"], observers


# --------------------------------------------------------------------------- 4. ground truth

def test_ground_truth_is_the_true_torque_when_the_bag_has_it(config, robot, bags):
    run = read_run(bags.payload, config.joint_names)
    inputs = estimator_inputs(run)
    truth = ground_truth(robot, config, run, inputs, None)
    assert truth.kind.startswith("true external joint torque")
    np.testing.assert_array_equal(truth.tau_ext, bags.payload_sim.truth.tau_ext)
    assert truth.wrench is not None and np.isfinite(truth.wrench).all()


def test_ground_truth_from_the_wrist_ft_alone_is_jt_w_of_the_payload(config, robot, bags, tmp_path):
    """Payload beyond the flange: the F/T sees all of it, so Jᵀw equals the simulator's τ_ext.

    Tolerance 1e-3 N·m (measured 1.2e-4 N·m: positions are quantised to 2^19 counts/rev) against
    a truth of up to ~20 N·m on joint 2.
    """
    sim = bags.payload_sim
    write_run(tmp_path / "ft_only", replace(sim.run, external_torque=None))
    run = read_run(tmp_path / "ft_only", config.joint_names)
    assert run.external_torque is None and run.wrench is not None
    inputs = estimator_inputs(run)
    truth = ground_truth(robot, config, run, inputs, None)
    assert "J^T w" in truth.kind
    assert np.abs(sim.truth.tau_ext).max() > 5.0
    np.testing.assert_allclose(truth.tau_ext, sim.truth.tau_ext, atol=1e-3)


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """The same reference trajectory, controller and noise seed, without and with the 2 kg payload.

    (run_scenario seeds the trajectory with the scenario index, so its excitation and payload
    runs follow different trajectories; these two are built with run_simulation instead.)
    Bags carry neither the F/T nor the true torque, so only the reference run gives ground truth.
    """
    from kvark_ros.sim.controllers import JointTrackingController
    from kvark_ros.sim.excitation import ExcitationLimits, random_trajectory
    from kvark_ros.sim.plant import default_plant_path, load_plant
    from kvark_ros.sim.robots import robot_setup
    from kvark_ros.sim.scenarios import run_simulation
    root = tmp_path_factory.mktemp("two_runs")
    setup = robot_setup("panda")
    plant = load_plant(default_plant_path("panda"), setup.n)
    trajectory = random_trajectory(ExcitationLimits.for_robot(setup), 3.0, np.random.default_rng(5))
    nominal = setup.nominal_model()
    sims = {}
    for name, spec in (("free", plant), ("loaded", replace(plant, payload=setup.payload))):
        controller = JointTrackingController(nominal, trajectory, setup.kp, setup.kd)
        sims[name] = run_simulation(setup, spec, controller, 3.0, trajectory(0.0)[0], np.random.default_rng(9),
                                    progress=False)
        write_run(root / name, replace(sims[name].run, wrench=None, external_torque=None))
    assert not sims["free"].truth.tau_ext.any()
    return SimpleNamespace(free=root / "free", loaded=root / "loaded", truth=sims["loaded"].truth.tau_ext)


def test_ground_truth_from_a_reference_bag_is_the_free_minus_loaded_torque(config, robot, two_runs):
    """τ_ext = τ_free − τ_loaded (v2 eq. 40). The controller's tracking differs slightly between
    the runs (the payload sags the arm by up to 0.03 rad), so after a 0.2 s start-up transient the
    difference matches the true payload torque within 0.35 N·m RMS per joint and 5 % overall
    (measured: ≤ 0.25 N·m, 2.7 %); a flipped sign would give ~200 %."""
    run = read_run(two_runs.loaded, config.joint_names)
    inputs = estimator_inputs(run)
    reference = estimator_inputs(read_run(two_runs.free, config.joint_names))
    assert ground_truth(robot, config, run, inputs, None) is None
    truth = ground_truth(robot, config, run, inputs, reference)
    assert truth.kind.startswith("two-run difference")
    settled = inputs.stamp >= 0.2
    error = truth.tau_ext[settled] - two_runs.truth[settled]
    assert np.sqrt(np.mean(error ** 2, axis=0)).max() < 0.35
    assert np.sqrt(np.mean(error ** 2)) < 0.05 * np.sqrt(np.mean(two_runs.truth[settled] ** 2))


def test_reference_bag_replay_metrics_have_the_full_schema(config, cli_model, two_runs, tmp_path):
    trained = load_model(cli_model, config.joint_names)
    metrics = replay(config, trained, two_runs.loaded, tmp_path / "out", ["kvark"],
                     reference_bag=two_runs.free, write_bag=False, plots=False, log=lambda _line: None)
    assert metrics["ground_truth"].startswith("two-run difference")
    _check_observer_schema("kvark", metrics["observers"]["kvark"], covariance=True)


# --------------------------------------------------------------------------- 5. metrics

def test_metrics_of_hand_made_errors():
    """Rows: 0 has no estimate (huge error, ignored), 5 has no truth (ignored), 3 has no wrench truth.

    Joint errors on rows 1-4: joint 0 [1, −1, 1, −1], joint 1 [0, 0, 0, 4].
    """
    tau_true = np.zeros((6, 2))
    tau_true[5] = np.nan
    tau_hat = np.array([[100.0, 100.0], [1.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [-1.0, 4.0], [7.0, 7.0]])
    tau_std = np.ones((6, 2))
    tau_std[2, 0] = 0.5                      # |error| 1 > 1.96·0.5: outside
    wrench_true = np.zeros((6, 6))
    wrench_true[3] = np.nan
    wrench_hat = np.zeros((6, 6))
    wrench_hat[:, 3:] = 1.0                  # moment error 1 everywhere
    wrench_hat[1, 0] = 3.0                   # force x error 3 on row 1
    wrench_hat[4, 1] = 6.0                   # force y error 6 on row 4
    wrench_hat[0] = 50.0                     # invalid row
    valid = np.array([False, True, True, True, True, True])
    result = ObserverRun("x", tau_hat, tau_std, wrench_hat, None, valid, 12.345, {}, np.zeros(6, dtype=bool),
                         np.zeros(6, dtype=bool))
    stamp = 0.002 * np.arange(6)
    entry = observer_metrics(result, GroundTruth("hand", tau_true, wrench_true), stamp)

    assert entry["estimates"] == 5 and entry["us_per_step"] == 12.35
    assert entry["joint_rmse"] == pytest.approx([1.0, 2.0], abs=1e-6)
    assert entry["joint_rmse_mean"] == pytest.approx(1.5, abs=1e-6)
    # |errors| = 0,0,0,1,1,1,1,4: mean 1; p95 by linear interpolation at rank 0.95·7 = 6.65: 1 + 0.65·3.
    assert entry["mean_abs"] == pytest.approx(1.0, abs=1e-6)
    assert entry["p95"] == pytest.approx(2.95, abs=1e-6)
    assert entry["max"] == pytest.approx(4.0, abs=1e-6)
    assert entry["temporal_std"] == pytest.approx((1.0 + np.sqrt(3.0)) / 2.0, abs=1e-6)   # std 1 and √3
    assert entry["coverage95"] == pytest.approx(6 / 8, abs=1e-6)                          # 4 and row-2 miss
    # Wrench rows 1, 2, 4: force errors (3,0,0), (0,0,0), (0,6,0); moments all 1.
    assert entry["force_rmse"] == pytest.approx([np.sqrt(3.0), np.sqrt(12.0), 0.0], abs=1e-6)
    assert entry["moment_rmse"] == pytest.approx([1.0, 1.0, 1.0], abs=1e-6)
    assert entry["force_rmse_mean"] == pytest.approx(np.sqrt(3.0), abs=1e-6)
    assert entry["moment_rmse_mean"] == pytest.approx(1.0, abs=1e-6)

    no_cov = observer_metrics(replace(result, tau_std=None), GroundTruth("hand", tau_true, wrench_true), stamp)
    assert no_cov["coverage95"] is None and no_cov["joint_rmse"] == entry["joint_rmse"]
    bare = observer_metrics(result, None, stamp)
    assert set(bare) == {"us_per_step", "estimates", "rejected", "collision_share", "wrench"}
    assert bare["collision_share"] == 0.0


# --------------------------------------------------------------------------- 6. every observer, known answer

STEP_TORQUE = np.array([3.0, -2.0, 1.5, 2.0, -1.0, 0.8, 0.5])    # N·m, on at t = 2 s
TORQUE_NOISE = 0.02                                               # N·m std on τ_m


def _frictionless(robot: RobotModel, duration: float, seed: int, external=None) -> tuple[EstimatorInputs, np.ndarray]:
    """Synthetic Panda stream with exact dynamics and no friction: τ_m = ID(q, q̇, q̈) − τ_ext + noise."""
    from kvark_ros.tools.synthetic import synthetic_stream
    s = synthetic_stream(robot, duration, seed=seed, external=external, torque_noise_std=TORQUE_NOISE)
    return EstimatorInputs(s.stamp, s.q, s.qd, s.tau_m - s.friction, "synthetic", 0), s.tau_ext


@pytest.fixture(scope="module")
def frictionless(robot):
    """A model trained on two 3 s frictionless streams, with the three learned baselines. Every joint's residual takes
    q̇ alone: the residual is noise about zero here, which no second input explains (input selection is tested with
    ``cli_model`` and in core/test_kmp_second_inputs.py), and selecting would triple the training time.

    train_model(baselines=True) spends most of its time in the sparse GP's exact hyperparameter fit
    with restarts, so the baselines are fitted directly with light settings on the same residuals and
    share K-VARK's covariance-matched tuning.
    """
    from kvark_ros.core.estimation.residual import GMRGPResidualModel, MLPResidualModel, SparseGPResidualModel
    from kvark_ros.core.learning.training import train_model, training_data
    segments = [_frictionless(robot, 3.0, seed)[0] for seed in (100, 200)]
    trained = train_model(robot, "panda", segments, baselines=False, log=lambda _line: None, residual_inputs="qd")
    data = training_data(robot, segments)
    baselines = {
        "gmr_gp": GMRGPResidualModel.fit(None, None, samples_per_support=2, reference=trained.residual.reference),
        "gpadkf": SparseGPResidualModel.fit(data.qd, data.tau_r, n_inducing=20, n_hyper_subset=300, n_restarts=0),
        "nnadkf": MLPResidualModel.fit(data.qd, data.tau_r, max_epochs=50, batch_size=128),
    }
    return replace(trained, baselines=baselines, baseline_tunings={name: trained.tuning for name in baselines})


@pytest.fixture(scope="module")
def step_stream(robot):
    return _frictionless(robot, 6.0, seed=7, external=lambda t: STEP_TORQUE if t >= 2.0 else np.zeros(N))


@pytest.mark.parametrize("name", OBSERVER_NAMES)
def test_every_observer_converges_to_a_constant_external_torque_step(config, frictionless, step_stream, name):
    """Exact dynamics, zero friction (the oracle's plant file is empty: load_plant({}, 7)), 0.02 N·m
    torque noise, τ_ext stepping from 0 to STEP_TORQUE at 2 s. Tolerances: mean |error| < 0.03 N·m
    before the step (1-2 s) and after settling (4-6 s), max |error| < 0.15 N·m after settling
    (measured for all 14: mean ≤ 0.008, max ≤ 0.043 N·m)."""
    from kvark_ros.sim.plant import OracleResidual, load_plant
    inputs, tau_true = step_stream
    result = run_observer(config, frictionless, inputs, name, oracle=OracleResidual(load_plant({}, N), N))
    assert result.valid[1:].all() and not result.valid[0]
    assert np.isfinite(result.tau_ext).all() and np.isfinite(result.wrench).all()
    assert (result.tau_std is None) == (name in ("momentum", "eso"))      # the two without a covariance
    if result.tau_std is not None:
        assert np.all(result.tau_std[1:] > 0) and np.isfinite(result.tau_std[1:]).all()
    before = (inputs.stamp >= 1.0) & (inputs.stamp < 2.0)
    settled = inputs.stamp >= 4.0
    assert np.abs(result.tau_ext[before]).mean() < 0.03, name
    error = np.abs(result.tau_ext[settled] - tau_true[settled])
    assert error.mean() < 0.03, f"{name}: mean |error| {error.mean():.4f} N·m"
    assert error.max() < 0.15, f"{name}: max |error| {error.max():.4f} N·m"


def test_model_with_learned_baselines_round_trips(config, frictionless, tmp_path):
    save_model(tmp_path / "m", frictionless)
    loaded = load_model(tmp_path / "m", config.joint_names)
    assert set(loaded.baselines) == {"gmr_gp", "gpadkf", "nnadkf"}
    qd = np.random.default_rng(1).uniform(-1.0, 1.0, (40, N))
    for name, model in frictionless.baselines.items():
        for a, b in zip(model.predict_batch(qd), loaded.baselines[name].predict_batch(qd)):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
        assert loaded.baseline_tunings[name].to_dict() == frictionless.tuning.to_dict()


# --------------------------------------------------------------------------- 7. throughput

def test_replay_throughput_of_kvark_on_a_500_hz_bag(config, bags, cli_model, tmp_path, capsys):
    trained = load_model(cli_model, config.joint_names)
    started = time.perf_counter()
    metrics = replay(config, trained, bags.payload, tmp_path / "out", ["kvark"], write_bag=False, plots=False,
                     log=lambda _line: None)
    wall = time.perf_counter() - started
    factor = metrics["duration_s"] / wall
    with capsys.disabled():
        print(f"\n[throughput] kvark replay of a {metrics['duration_s']:.1f} s, 500 Hz, 7-joint bag "
              f"(decode included): {wall:.2f} s wall, {factor:.1f}x real time, "
              f"{metrics['observers']['kvark']['us_per_step']} µs/step")
    samples = len(read_run(bags.payload, config.joint_names).joint_states.stamp)
    assert metrics["samples"] == samples == int(PAYLOAD_S * RATE)
    assert metrics["observers"]["kvark"]["estimates"] >= 0.99 * samples


def test_cli_replay_of_free_motion_with_zero_truth_and_a_trim(bags, cli_model, tmp_path, capsys):
    """`--ground-truth zero` on a contact-free bag: every estimate is error against zero; `--trim` drops the
    first and last seconds; asking for a truth the bag does not have is one error line."""
    out = tmp_path / "free"
    assert main(["replay", "--config", str(CONFIG), "--model", str(cli_model), "--bag", str(bags.mcap),
                 "--observers", "kvark,momentum", "--ground-truth", "zero", "--trim", "0.5", "0.25",
                 "--out", str(out), "--no-bag"]) == 0
    printed = capsys.readouterr().out          # which URDF and model, and what the model was trained on
    assert f"model {cli_model}," in printed and "trained on excitation_mcap, excitation_sqlite" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ground_truth"].startswith("zero") and metrics["trim_s"] == [0.5, 0.25]
    # 1.5 s of the bag kept at 500 Hz, ± one sample at each cut
    assert abs(metrics["samples"] - (EXCITATION_S - 0.75) * RATE) <= 2
    # Contact-free motion: the error is false torque. kvark's residual model takes out the friction the nominal
    # model lacks, so it reports at most half the false torque of the momentum observer, which has no residual model
    # (measured 0.068 against 0.373 N·m); its intervals, calibrated to hold 95 % of the contact-free τ̂ on these
    # training recordings, hold the zero truth on at least 90 % of the samples (measured 0.983)
    kvark, momentum = metrics["observers"]["kvark"], metrics["observers"]["momentum"]
    assert kvark["joint_rmse_mean"] < 0.5 * momentum["joint_rmse_mean"], (kvark, momentum)
    assert kvark["coverage95"] >= 0.9 and momentum["coverage95"] is None
    capsys.readouterr()
    code, err = _cli_error(capsys, ["replay", "--config", str(CONFIG), "--model", str(cli_model), "--bag",
                                    str(bags.mcap), "--ground-truth", "reference", "--out", str(tmp_path / "ref"),
                                    "--no-bag"])
    assert code == 1 and "--ground-truth reference needs --reference-bag" in err
    code, err = _cli_error(capsys, ["replay", "--config", str(CONFIG), "--model", str(cli_model), "--bag",
                                    str(bags.mcap), "--trim", "5", "5", "--out", str(tmp_path / "t"), "--no-bag"])
    assert code == 1 and "--trim 5.0 5.0 leaves" in err


def _cli_error(capsys, argv: list[str]) -> tuple[int, str]:
    """Exit code and the one stderr line of a CLI run expected to fail."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = 1 if isinstance(exc.code, str) else exc.code
        capsys.readouterr()
        return code, str(exc.code)
    return code, capsys.readouterr().err.strip()
