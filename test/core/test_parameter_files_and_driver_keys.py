"""What a driver's user writes into a parameter file, read as the node and every command read it: the node's key in
any namespace, paths relative to the file that set them, the effort's scale and offset, and a payload inertia in
geometry_msgs/Inertia's order (the former order refused in one line with the values rewritten)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from kvark_ros.core.config import (ANY_NAMESPACE, ConfigError, applies_to, config_from_parameters, flatten_parameters,
                                   load_config, path_folders, with_folders)
from kvark_ros.core.estimation.inputs import EffortCalibration, EstimatorInputs
from kvark_ros.core.estimation.payload import Payload

ROOT = Path(__file__).resolve().parents[2]
PANDA = ROOT / "config" / "panda.yaml"


def panda_parameters(**changes) -> dict:
    """config/panda.yaml's dotted parameters with ``changes`` (``__`` for ``.``)."""
    flat = flatten_parameters(yaml.safe_load(PANDA.read_text())["kvark_estimator"]["ros__parameters"])
    flat.update({name.replace("__", "."): value for name, value in changes.items()})
    return flat


def write(path: Path, document: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize("key, node, expected", [
    ("kvark_estimator", "/kvark_estimator", True),           # no leading /: a fully qualified name all the same
    ("/kvark_estimator", "/kvark_estimator", True),
    ("kvark_estimator", "/lbr/kvark_estimator", False),      # the root namespace's node only
    ("/**/kvark_estimator", "/lbr/kvark_estimator", True),
    ("/**/kvark_estimator", "/kvark_estimator", True),       # ** is any number of names, none too
    ("/**/kvark_estimator", "/a/b/kvark_estimator", True),
    ("/**", "/lbr/kvark_estimator", True),
    ("/lbr/*", "/lbr/kvark_estimator", True),
    ("/left/kvark_estimator", "/lbr/kvark_estimator", False),
    ("/**/joint_state_broadcaster", "/lbr/kvark_estimator", False),
    ("/lbr/kvark_estimator", None, True),                    # the commands: the node in any namespace
    ("/**", None, True),
    ("/**/controller_manager", None, False),
])
def test_a_parameter_files_key_applies_as_rcl_matches_it(key, node, expected):
    assert applies_to(key, node) is expected


def test_every_command_reads_the_key_for_any_namespace_and_merges_what_applies(tmp_path):
    """A file keyed ``/**/kvark_estimator`` (the convention for a node started in a namespace) loads as the plain
    key does; a later key that applies overrides an earlier one, as rcl applies them; a controller's key beside it
    is not ours. A file with no key for the node says which keys would do."""
    document = yaml.safe_load(PANDA.read_text())
    plain = load_config(PANDA)
    section = document.pop("kvark_estimator")
    path = write(tmp_path / "config" / "arm.yaml", {
        "/**/controller_manager": {"ros__parameters": {"update_rate": 500}},
        ANY_NAMESPACE: section,
        "/lbr/kvark_estimator": {"ros__parameters": {"contact": {"debounce": 0.05}}}})
    config = load_config(path)
    assert config.contact.debounce == 0.05 and config.joint_names == plain.joint_names
    assert config.model_dir == str(tmp_path / "models" / "panda")
    bad = write(tmp_path / "other.yaml", {"/**/controller_manager": {"ros__parameters": {"update_rate": 500}}})
    with pytest.raises(ConfigError, match=r"other.yaml: expected a top-level 'kvark_estimator: ros__parameters:' "
                                          r"mapping \(or '/\*\*/kvark_estimator:' for the node in any namespace\)"):
        load_config(bad)


def test_the_node_resolves_each_path_against_the_parameter_file_that_set_it(tmp_path):
    """``--params-file a.yaml --params-file b.yaml``: a path is resolved against the folder of the last file that
    sets it for this node (the file rcl took it from); a file for another node, or none, leaves it to the fallback
    (the package's config folder)."""
    first = write(tmp_path / "robot" / "a.yaml", {ANY_NAMESPACE: {"ros__parameters": {
        "robot_model": {"urdf": "arm.urdf"}, "residual_model": {"model_dir": "../models/arm"}}}})
    second = write(tmp_path / "site" / "b.yaml", {"/lbr/kvark_estimator": {"ros__parameters": {
        "residual_model": {"model_dir": "model"}}}})
    other = write(tmp_path / "other" / "c.yaml", {"/left/kvark_estimator": {"ros__parameters": {
        "model_augmentation": "augmentation.yaml"}}})
    config = config_from_parameters(panda_parameters(robot_model__urdf="arm.urdf", residual_model__model_dir="model",
                                                     model_augmentation="augmentation.yaml"))
    fallback = tmp_path / "share"
    folders = path_folders([first, second, other], "/lbr/kvark_estimator", fallback)
    resolved = with_folders(config, folders)
    assert resolved.urdf == str(tmp_path / "robot" / "arm.urdf")
    assert resolved.model_dir == str(tmp_path / "site" / "model")
    assert resolved.model_augmentation == str(fallback / "augmentation.yaml")
    kept = config_from_parameters(panda_parameters(robot_model__urdf="robot_description"))
    assert with_folders(kept, path_folders([first], "/lbr/kvark_estimator", fallback)).urdf == "robot_description"


@pytest.mark.parametrize("scale, offset", [([2.0], [0.0]), ([1.0] * 7, [0.5] * 7), ([10.0, 10.7, 8.5, 9.0, 9.5, 10.1,
                                                                                      1.0], [0.0])])
def test_effort_scale_and_offset_make_torque_of_the_values_read(scale, offset):
    """τ_m = scale ⊙ value + offset per joint (one value repeats for every joint), the same rule for a sample and
    for a recording's (T, n) array."""
    config = config_from_parameters(panda_parameters(input__effort_scale=scale, input__effort_offset=offset))
    calibration = EffortCalibration.from_config(config)
    current = np.array([[0.5, -1.0, 2.0, 0.0, 3.0, -0.25, 1.5], [1.0] * 7])
    expected = current * np.resize(scale, 7) + np.resize(offset, 7)
    assert np.array_equal(calibration.apply(current), expected)
    assert np.array_equal(calibration.apply(current[0]), expected[0])
    inputs = EstimatorInputs(np.arange(2.0), np.zeros((2, 7)), np.zeros((2, 7)), current, "joint_states effort", 0)
    assert np.array_equal(calibration.to_inputs(inputs).tau_m, expected)
    assert not calibration.identity


def test_effort_scale_as_read_is_no_change_and_a_wrong_count_is_refused():
    identity = EffortCalibration.from_config(config_from_parameters(panda_parameters()))
    inputs = EstimatorInputs(np.arange(1.0), np.zeros((1, 7)), np.zeros((1, 7)), np.ones((1, 7)), "x", 0)
    assert identity.identity and identity.to_inputs(inputs) is inputs
    with pytest.raises(ConfigError, match=r"key 'input.effort_scale' has 6 values; give 1 \(every joint\) or 7 "
                                          r"\(one per robot_model.joint_names\)"):
        config_from_parameters(panda_parameters(input__effort_scale=[10.0] * 6))
    with pytest.raises(ConfigError, match="key 'input.effort_offset' has invalid value"):
        config_from_parameters(panda_parameters(input__effort_offset=[]))


def test_payload_inertia_is_in_geometry_msgs_order_and_the_former_order_is_refused_with_the_values_rewritten():
    """[ixx ixy ixz iyy iyz izz] as geometry_msgs/Inertia and URDF write it; a diagonal tool written diagonal first
    (the key's former order) reads as a non-positive inertia in this order and is refused naming the same values
    in this order. Off-diagonal terms land where the order puts them (the pinocchio inertia's matrix)."""
    tool = config_from_parameters(panda_parameters(robot_model__payload__mass=1.0,
                                                   robot_model__payload__inertia=[0.02, 0.001, -0.002, 0.03, 0.003,
                                                                                  0.04])).payload
    assert np.allclose(tool.to_pinocchio().inertia, [[0.02, 0.001, -0.002], [0.001, 0.03, 0.003],
                                                     [-0.002, 0.003, 0.04]], rtol=0.0, atol=1e-15)
    assert tool == Payload.from_message_order(1.0, (0.0, 0.0, 0.0), (0.02, 0.001, -0.002, 0.03, 0.003, 0.04))
    with pytest.raises(ConfigError, match=r"key 'robot_model.payload.inertia' is ordered ixx ixy ixz iyy iyz izz "
                                          r"\(geometry_msgs/Inertia, URDF\); \[0.02, 0.03, 0.04, 0.0, 0.0, 0.0\] is an "
                                          r"inertia only in the former order ixx iyy izz ixy ixz iyz: write "
                                          r"\[0.02, 0, 0, 0.03, 0, 0.04\]"):
        config_from_parameters(panda_parameters(robot_model__payload__mass=1.0,
                                                robot_model__payload__inertia=[0.02, 0.03, 0.04, 0.0, 0.0, 0.0]))
    point = config_from_parameters(panda_parameters(robot_model__payload__mass=1.0)).payload
    assert point.inertia == (0.0,) * 6                   # a point mass: an inertia in either order
