"""The node's tare and collision flag, measured offline by replay (issue 15: they must also work offline)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.metrics import observer_metrics
from kvark_ros.tools.replay import ground_truth, run_observer

ROOT = Path(__file__).resolve().parents[2]
BIAS = np.array([0.3, -0.5, 0.4, 0.6, -0.3, 0.35, -0.4])      # N·m, a drifting sensor's offsets


def test_replay_tare_at_removes_a_rest_bias(panda_config, panda_trained):
    """A robot held still whose torque reads BIAS off: replay with tare_at 0.5 s starts the tare at the first
    sample at rest, and from 1.5 s on τ̂ is rounding (kfmo follows a constant exactly; 1e-9 N·m against a
    0.3 N·m smallest bias). Its outcome is in the metrics."""
    q0 = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8])
    stamp = 0.002 * np.arange(1500)
    tau_m = RobotModel.from_config(panda_config).gravity(q0) - BIAS
    inputs = EstimatorInputs(stamp, np.tile(q0, (1500, 1)), np.zeros((1500, 7)), np.tile(tau_m, (1500, 1)),
                             "test", 0)
    result = run_observer(panda_config, panda_trained, inputs, "kfmo", tare_at=0.5)
    assert result.tare["state"] == "active" and np.allclose(result.tare["offset"], BIAS, atol=1e-6)
    assert np.abs(result.tau_ext[stamp >= 1.6]).max() < 1e-9
    untared = run_observer(panda_config, panda_trained, inputs, "kfmo")
    assert np.abs(untared.tau_ext[-1] - BIAS).max() < 1e-9 and untared.tare is None
    assert observer_metrics(result, None, stamp)["tare"]["state"] == "active"


def test_replay_flags_the_collision_push_and_not_the_table_contact(panda_config):
    """On the committed simulated bags with models/panda (contact.collision_torque 8.5 N·m): the 11.5 N·m
    collision push is flagged within 20 ms of the true torque passing 8.5 N·m, the ~15 N table contact (7 N·m
    at most) never is (measured: largest |τ̂_j| − z σ_j 7.05 N·m at the table, 10.0 in the push)."""
    config = replace(panda_config, model_dir=str(ROOT / "models" / "panda"))
    trained = load_model(config.model_dir, config.joint_names)
    robot = RobotModel.from_config(config)
    shares = {}
    for scene in ("contact", "collision"):
        run, inputs = read_inputs(ROOT / "bags" / f"panda_{scene}", config)
        result = run_observer(config, trained, inputs, "kvark")
        truth = ground_truth(robot, config, run, inputs, None)
        metrics = observer_metrics(result, truth, inputs.stamp)
        shares[scene] = metrics["collision_share"]
        if scene == "collision":
            crossing = inputs.stamp[np.argmax(np.abs(truth.tau_ext).max(axis=1) > config.contact.collision_torque)]
            first = inputs.stamp[np.argmax(result.collision)]
            assert 0.0 <= first - crossing <= 0.02
    assert shares["contact"] == 0.0 and shares["collision"] > 0.0
