"""The wrench as a driver's users read it (``core.estimation.wrench_output``): UR's ``base`` frame, turned 180°
about z from the URDF root, and the applied-by-robot sign of Franka's O_F_ext_hat_K."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.config import config_from_parameters
from kvark_ros.core.estimation.estimator import Estimate
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.wrench_output import WrenchOutput

UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
             "wrist_3_joint"]


def ur10(**changes):
    """(robot, config) of example-robot-data's UR10 (root link world, base_link, base turned π about z)."""
    config = config_from_parameters({"robot": "ur10", "robot_model.urdf": "example-robot-data:ur10",
                                     "robot_model.joint_names": UR_JOINTS, "robot_model.ee_frame": "tool0",
                                     "robot_model.flange_frame": "tool0", "residual_model.model_dir": "m",
                                     **{name.replace("__", "."): value for name, value in changes.items()}})
    return RobotModel.from_config(config), config


def estimate(frame: str, wrench, covariance=None, ee_rotation=None) -> Estimate:
    """An estimate carrying ``wrench`` (6,) in ``frame`` axes."""
    return Estimate(0.0, np.zeros(6), np.eye(6), np.asarray(wrench, dtype=float),
                    np.eye(6) if covariance is None else covariance, False, False, frame,
                    np.eye(3) if ee_rotation is None else ee_rotation, np.zeros((6, 6)), np.zeros((6, 0)))


def test_the_root_link_in_kvarks_sign_changes_nothing():
    robot, config = ur10()
    output = WrenchOutput(robot, config)
    given = estimate("base", [1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    frame, wrench = output.published(given)
    assert frame == "world" and wrench is given.wrench and output.covariance(given) is given.wrench_cov


def test_urs_base_frame_turns_force_and_moment_and_the_covariance():
    """base = Rz(π) of the root: x and y of force and moment change sign, z stays; Σ turns with them (its fx-fy
    and fx-tz correlations keep their sign, fx-fz flips); the ee-frame wrench is not turned. The URDF writes π
    as 3.14159265359, off by 2.1e-13 rad, so values agree to 1e-12 (relative to values of order 1)."""
    robot, config = ur10(wrench__base_frame="base")
    output = WrenchOutput(robot, config)
    covariance = np.arange(36.0).reshape(6, 6)
    covariance = covariance + covariance.T
    given = estimate("base", [1.0, 2.0, 3.0, 0.1, 0.2, 0.3], covariance)
    frame, wrench = output.published(given)
    assert frame == "base" and wrench.tolist() == pytest.approx([-1.0, -2.0, 3.0, -0.1, -0.2, 0.3], abs=1e-12)
    flip = np.diag([-1.0, -1.0, 1.0, -1.0, -1.0, 1.0])
    assert np.allclose(output.covariance(given), flip @ covariance @ flip, rtol=0.0, atol=1e-10)   # entries ≤ 70
    in_ee = estimate("end_effector", [1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    assert output.published(in_ee)[0] == "tool0" and output.published(in_ee)[1] is in_ee.wrench


def test_the_applied_by_robot_convention_negates_the_wrench_not_its_covariance():
    """Franka's O_F_ext_hat_K is the robot's wrench on the environment: −F; a run-time change takes effect."""
    robot, config = ur10(wrench__convention="applied_by_robot")
    output = WrenchOutput(robot, config)
    given = estimate("end_effector", [0.0, 0.0, 14.7, 0.0, 0.5, 0.0])
    assert output.published(given)[1].tolist() == [-0.0, -0.0, -14.7, -0.0, -0.5, -0.0]
    assert output.covariance(given) is given.wrench_cov
    output.configure(replace(config, wrench=replace(config.wrench, convention="acting_on_robot")))
    assert output.published(given)[1] is given.wrench


@pytest.mark.parametrize("frame, message", [
    ("tool0", r"wrench.base_frame 'tool0' moves with joint wrist_3_joint; name a frame fixed to the root link world"),
    ("bse", r"wrench.base_frame 'bse' is not a frame of the URDF example-robot-data:ur10; the frames fixed to its "
            r"root link world are world, base_link, base"),
])
def test_a_base_frame_that_moves_or_does_not_exist_is_refused_naming_the_ones_that_do(frame, message):
    robot, config = ur10(wrench__base_frame=frame)
    with pytest.raises(ValueError, match=message):
        WrenchOutput(robot, config)
