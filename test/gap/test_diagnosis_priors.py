"""Believable diagnosis physics: flange-link changes, physical consistency, priors and their warnings."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kvark_ros.core.estimation.augmentation import parse_augmentation
from kvark_ros.core.config import default_config_path, load_config
from kvark_ros.core.estimation.payload import inertia_problem
from kvark_ros.core.estimation.robot_model import RobotModel, RobotModelError, flange_link_parameters
from kvark_ros.gap.effects import Priors, Term, flange_parameter_map, signals
from kvark_ros.gap.plausibility import flange_change, flange_mass_regrouping, plausibility_warnings


@pytest.fixture(scope="module")
def config():
    return load_config(default_config_path("panda"))


@pytest.fixture(scope="module")
def robot(config):
    return RobotModel.from_config(config)


def test_flange_link_change_equals_pinocchio_placement_sum(robot) -> None:
    frame = robot.model.frames[robot.flange_frame_id]
    rng = np.random.default_rng(1)
    a = rng.standard_normal((3, 3))
    body = pin.Inertia(0.7, rng.standard_normal(3) * 0.1, a @ a.T + 0.1 * np.eye(3))
    want = (robot.model.inertias[frame.parentJoint] + frame.placement.act(body)).toDynamicParameters()
    got = flange_link_parameters(robot.model, robot.flange_frame_id, body.toDynamicParameters())
    np.testing.assert_allclose(got, want, atol=1e-12)      # a linear map: exact to rounding


def test_inertia_problem_names_what_is_unphysical() -> None:
    box = pin.Inertia(2.0, np.array([0.1, 0.0, 0.05]), np.diag([0.02, 0.03, 0.04])).toDynamicParameters()
    assert inertia_problem(box) is None
    assert "mass" in inertia_problem(np.concatenate([[-1.0], box[1:]]))
    # [m, m c, ixx, ixy, iyy, ixz, iyz, izz] about the origin, CoM at the origin (pinocchio refuses to build these)
    assert "not positive" in inertia_problem(np.array([1.0, 0, 0, 0, -0.01, 0, 0.02, 0, 0, 0.02]))
    assert "triangle" in inertia_problem(np.array([1.0, 0, 0, 0, 0.01, 0, 0.01, 0, 0, 0.05]))


def _augmentation_text(config, theta: np.ndarray) -> str:
    return yaml.safe_dump({"joint_names": list(config.joint_names), "effects": [
        {"name": "payload", "joint_indices": list(range(7)), "theta": [float(v) for v in theta]}]})


def test_a_lighter_tool_is_accepted_and_an_impossible_one_refused(config, robot) -> None:
    """The flange link scaled by 0.8 (a tool 20 % lighter, same shape) is physical; by −0.2 it is not."""
    jid, a_map = flange_parameter_map(robot)
    link = robot.model.inertias[jid].toDynamicParameters()
    lighter = np.linalg.solve(a_map, -0.2 * link)            # in the flange frame
    text = _augmentation_text(config, lighter)
    augmented = RobotModel.from_config(config, parse_augmentation(text, config.joint_names))
    np.testing.assert_allclose(augmented.model.inertias[jid].toDynamicParameters(), 0.8 * link, atol=1e-9)
    impossible = np.linalg.solve(a_map, -1.2 * link)
    with pytest.raises(RobotModelError, match="physically inconsistent.*mass"):
        RobotModel.from_config(config, parse_augmentation(_augmentation_text(config, impossible), config.joint_names))


def test_parameters_at_a_prior_bound_are_warnings(config) -> None:
    names = config.joint_names
    priors = Priors(flange_mass=1.5)
    gain = Term("drive_gain", (1, 3))
    offset = Term("joint_offset", (5,))
    warnings = plausibility_warnings([gain, offset], [np.array([0.1, 0.02]), np.array([-priors.max_joint_offset])],
                                     priors, names)
    assert len(warnings) == 2
    assert names[1] in warnings[0] and "0.900" in warnings[0] and names[3] not in " ".join(warnings)
    assert names[5] in warnings[1] and "-1.00°" in warnings[1]
    assert plausibility_warnings([gain], [np.array([0.05, -0.05])], priors, names) == []


def test_look_alikes_reports_collinear_effects_only() -> None:
    from kvark_ros.gap.plausibility import look_alikes
    rng = np.random.default_rng(0)
    t, n = 400, 3
    base = rng.standard_normal((t, n, 2))
    scaled = np.concatenate([base @ np.array([[2.0], [-1.0]]), rng.standard_normal((t, n, 1))], axis=2)  # spans a mix
    unrelated = rng.standard_normal((t, n, 2))
    pairs = look_alikes({"a": base}, {"b": scaled, "c": unrelated, "a": base}, np.ones(n))
    assert [(p["accepted"], p["look_alike"]) for p in pairs] == [("a", "b")]    # itself and random columns are not
    assert pairs[0]["cosine"] == pytest.approx(1.0, abs=1e-9)      # 2 a₀ − a₁ lies in both spans exactly


def test_an_effect_listed_again_adds_to_the_earlier_entry(config) -> None:
    """`kvark diagnose --against` writes the base effects, then the new ones: every effect is linear in θ."""
    names = list(config.joint_names)
    payload = np.arange(1.0, 11.0) * 0.01
    text = yaml.safe_dump({"joint_names": names, "effects": [
        {"name": "payload", "joint_indices": list(range(7)), "theta": payload.tolist()},
        {"name": "armature", "joint_indices": [0, 1], "theta": [0.1, 0.2]},
        {"name": "torque_offset", "joint_indices": [2], "theta": [0.3]},
        {"name": "payload", "joint_indices": list(range(7)), "theta": (-0.5 * payload).tolist()},
        {"name": "armature", "joint_indices": [1], "theta": [0.05]},
        {"name": "torque_offset", "joint_indices": [2], "theta": [-0.1]}]})
    parsed = parse_augmentation(text, names)
    np.testing.assert_allclose(parsed.payload, 0.5 * payload)
    np.testing.assert_allclose(parsed.armature[:2], [0.1, 0.25])
    assert parsed.effect_names == ("payload", "armature", "torque_offset")
    tau = parsed.joint_torque(np.zeros(7), np.zeros(7), np.zeros(7))
    assert tau[2] == pytest.approx(-(0.3 - 0.1))      # torque_offset's column is −1: gap −o


def test_the_flange_mass_regroups_with_the_link_before_it(robot) -> None:
    """On the Panda the flange (panda_link8) lies on joint 7's axis: its mass column of the joint-torque regressor is
    a combination of link 6's ten (relative residual ~1e-15 in double precision; the bound 1e-9 leaves six decades
    of rounding). A column the previous link cannot produce (random) is identified (residual of order 1)."""
    rng = np.random.default_rng(3)
    q = rng.uniform(-1.5, 1.5, (40, 7))
    s = signals(robot, q, rng.normal(size=(40, 7)), rng.normal(size=(40, 7)), np.zeros((40, 7)))
    regrouping = flange_mass_regrouping(s, robot)
    assert regrouping["link_before_flange"] == "the link moved by panda_joint6"
    assert regrouping["relative_residual"] < 1e-9 and not regrouping["identified"]
    scrambled = replace(s, payload_regressor=rng.normal(size=s.payload_regressor.shape))
    assert flange_mass_regrouping(scrambled, robot)["relative_residual"] > 0.5
    assert flange_mass_regrouping(scrambled, robot)["identified"]


def test_a_flange_change_that_is_no_body_is_not_called_a_consistent_tool() -> None:
    """The report's consistency claims are checked on what they name: 0.5 kg 5 cm along the UR5's flange axis with
    its ixx 5e-5 kg·m² below a point mass's (a principal moment −5e-5 about its centre, beyond the 1e-6 tolerance)
    leaves the flange link consistent (its own 0.017-0.034 kg·m² absorb it) but is no body itself: not consistent,
    and not called a tool. A tool mismatch (negative mass) is no body and is judged on the link alone."""
    robot = RobotModel.from_config(load_config(default_config_path("ur5")))
    flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    a_map = flange_parameter_map(robot)[1]
    theta = np.array([0.5, 0.0, 0.0, 0.025, 0.00125 - 5e-5, 0.0, 0.00125, 0.0, 0.0, 0.0])
    change = flange_change(flange, a_map, theta)
    assert change["flange_link_consistent"] and change["payload_consistent"] is False
    assert change["physically_consistent"] is False and "not a tool" in change["kind"]
    theta[4] += 5e-5                                     # a point mass: a body (on the boundary, within tolerance)
    assert flange_change(flange, a_map, theta)["physically_consistent"]
    lighter = flange_change(flange, a_map, -0.5 * np.linalg.solve(a_map, flange))
    assert lighter["payload_consistent"] is None and lighter["physically_consistent"]
    assert lighter["kind"].startswith("tool mismatch")
