"""The effort's scale and offset offline: what every command reads from a bag (``io.recorded_inputs.read_inputs``) turns a
UR's motor currents into N·m with the config's ``input.effort_scale``/``effort_offset``, the rule the node applies to
every message (``core.estimation.inputs.EffortCalibration``), before the samples are checked against the URDF."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.config import config_from_parameters
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io import BagError
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.synthetic import synthetic_stream

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "test"))
from driver_fixtures import START, UR_JOINTS, UR_TORQUE_CONSTANTS, synthetic_driver_bag  # noqa: E402


def ur_config(**changes):
    return config_from_parameters({
        "robot": "ur10", "robot_model.urdf": "example-robot-data:ur10", "robot_model.joint_names": list(UR_JOINTS),
        "robot_model.ee_frame": "tool0", "robot_model.flange_frame": "tool0", "residual_model.model_dir": "m",
        "input.torque_source": "joint_states_effort", **{k.replace("__", "."): v for k, v in changes.items()}})


@pytest.fixture(scope="module")
def current_bag(tmp_path_factory) -> Path:
    """ur_robot_driver's /joint_states at 500 Hz for 1 s, effort = τ_m / k in A (test/driver_fixtures.py)."""
    robot = RobotModel.from_config(ur_config())
    return synthetic_driver_bag(robot, tmp_path_factory.mktemp("ur") / "bag", "/joint_states", 500.0, 1.0, seed=2,
                                torque_constants=UR_TORQUE_CONSTANTS)


def test_every_command_reads_the_currents_as_torque_with_the_scale_and_offset(current_bag):
    """τ_m = k ⊙ i + b per joint: the stream's torque back to rounding (the bag stores i = τ/k as float64, so
    k·i differs from τ by a few ulp of τ: at most 1e-12 N·m for torques below 300 N·m)."""
    robot = RobotModel.from_config(ur_config())
    expected = synthetic_stream(robot, 1.0, rate=500.0, seed=2)
    offset = [0.5, -0.25, 0.0, 0.1, 0.0, 0.0]
    inputs = read_inputs(current_bag, ur_config(input__effort_scale=list(UR_TORQUE_CONSTANTS),
                                                input__effort_offset=offset), log=None)[1]
    assert np.allclose(inputs.stamp, START + expected.stamp, rtol=0.0, atol=1e-9)
    assert np.abs(inputs.tau_m - (expected.tau_m + offset)).max() < 1e-12
    as_read = read_inputs(current_bag, ur_config(), log=None)[1]
    assert np.abs(as_read.tau_m * UR_TORQUE_CONSTANTS - expected.tau_m).max() < 1e-12


def test_the_limits_check_the_torque_not_the_current(current_bag):
    """A scale that makes the torque impossible (1000 N·m/A on every joint: beyond 2× the UR10's effort limits)
    refuses the bag in one line naming the effort scale as the fix: the check sees N·m."""
    with pytest.raises(BagError, match=r"torque beyond 2× the effort limit.*input.effort_scale"):
        read_inputs(current_bag, ur_config(input__effort_scale=[1000.0]), log=None)
