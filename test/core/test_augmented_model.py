"""Model augmentation (issue 6 scope 2): the effects `kvark diagnose` names, applied to the model the
estimator and the trainer use, consistent with the regressors the diagnosis fits them with."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kvark_ros.core.estimation.augmentation import AugmentationError, load_augmentation, parse_augmentation
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import AUGMENTATION_FILE, load_model, save_model
from kvark_ros.core.estimation.observers import ObserverError, make_observer
from kvark_ros.core.estimation.residual import ResidualModelError
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.effects import augmentation_gap

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
# A payload of 1.2 kg, CoM 5 cm along the flange z axis, as 10 dynamic parameters [m, m c, I_origin].
PAYLOAD_THETA = pin.Inertia(1.2, np.array([0.0, 0.0, 0.05]), np.diag([2e-3, 2e-3, 1e-3])).toDynamicParameters()


def _document(**extra) -> dict:
    effects = [
        {"name": "payload", "joint_indices": list(range(7)), "theta": PAYLOAD_THETA.tolist()},
        {"name": "armature", "joint_indices": [0, 1, 2, 3], "theta": [0.3, 0.3, 0.2, 0.2]},
        {"name": "coulomb_friction", "joint_indices": [0, 1], "variant": {"epsilon": 0.02}, "theta": [0.5, 0.6]},
        {"name": "viscous_friction", "joint_indices": [2], "theta": [0.2]},
        {"name": "stribeck_friction", "joint_indices": [3], "variant": {"stribeck_velocity": 0.1, "epsilon": 0.02},
         "theta": [0.4]},
        {"name": "drive_gain", "joint_indices": [4], "theta": [0.1]},
        {"name": "torque_offset", "joint_indices": [5], "theta": [0.3]},
        {"name": "position_ripple", "joint_indices": [6], "variant": {"cycles_per_rev": 6.0}, "theta": [0.2, -0.1]},
        {"name": "joint_offset", "joint_indices": [1, 3], "theta": [1e-4, -1e-4]},
    ]
    document = {"robot": "panda", "joint_names": NAMES, "effects": effects}
    document.update(extra)
    return document


def _write(tmp_path: Path, document: dict, name: str = "augmentation.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


@pytest.fixture(scope="module")
def augmentation():
    return parse_augmentation(yaml.safe_dump(_document()), NAMES)


def test_augmented_model_torque_is_nominal_plus_the_fitted_regressors(config, rng):
    """τ_EL + τ_aug of the augmented model equals the nominal τ_EL plus Σ Φ θ, the very regressors
    `kvark diagnose` fits (every effect but the joint offset, whose regressor is first order)."""
    document = _document()
    document["effects"] = [e for e in document["effects"] if e["name"] != "joint_offset"]
    nominal = RobotModel.from_config(config)
    augmented = RobotModel.from_config(config, parse_augmentation(yaml.safe_dump(document), NAMES))
    for _ in range(5):
        q, qd, qdd = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-3, 3, 7)
        tau_m = rng.uniform(-20, 20, 7)
        expected = nominal.inverse_dynamics(q, qd, qdd) + augmentation_gap(document, nominal, q, qd, qdd, tau_m)[0]
        np.testing.assert_allclose(augmented.model_torque(q, qd, qdd, tau_m), expected, atol=1e-9)


def test_joint_offset_evaluates_the_model_at_the_true_position(config, rng):
    """The encoder reads q + δ: the augmented model at the reading is the nominal one at q − δ, and to
    first order that is the diagnosis regressor −∂g/∂q δ at rest."""
    offset = np.array([0.0, 0.02, 0.0, -0.03, 0.0, 0.0, 0.0])
    document = {"joint_names": NAMES, "effects": [
        {"name": "joint_offset", "joint_indices": [1, 3], "theta": [0.02, -0.03]}]}
    nominal = RobotModel.from_config(config)
    augmented = RobotModel.from_config(config, parse_augmentation(yaml.safe_dump(document), NAMES))
    q, qd, qdd, zero = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-3, 3, 7), np.zeros(7)
    np.testing.assert_allclose(augmented.model_torque(q, qd, qdd, zero), nominal.inverse_dynamics(q - offset, qd, qdd))
    np.testing.assert_allclose(augmented.jacobian(q), nominal.jacobian(q - offset))
    first_order = nominal.inverse_dynamics(q, zero, zero) + augmentation_gap(document, nominal, q, zero, zero, zero)[0]
    np.testing.assert_allclose(augmented.model_torque(q, zero, zero, zero), first_order, atol=0.05)


def test_augmented_momentum_uses_the_augmented_inertia_and_the_drive_torque(config, augmentation, rng):
    """p = (M + armature + payload) q̇ (eq. 5) and u = Cᵀq̇ − g + τ_m − τ_aug (eq. 7, improved model)."""
    structural = parse_augmentation(yaml.safe_dump(_document()), NAMES)
    augmented = RobotModel.from_config(config, augmentation)
    q, qd, tau_m = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-20, 20, 7)
    p, u = augmented.momentum_terms(q, qd, tau_m)
    np.testing.assert_allclose(p, augmented.mass_matrix(q) @ qd, atol=1e-10)
    without_torque = replace(structural, torque_effects=())
    _, u_structural = RobotModel.from_config(config, without_torque).momentum_terms(q, qd, tau_m)
    np.testing.assert_allclose(u, u_structural - augmentation.joint_torque(q, qd, tau_m), atol=1e-10)
    nominal_m = RobotModel.from_config(config).mass_matrix(q - augmentation.joint_offset)
    assert np.all(np.diag(augmented.mass_matrix(q) - nominal_m)[:4] >= np.array([0.3, 0.3, 0.2, 0.2]) - 1e-9)


def test_batch_and_single_sample_augmentation_torques_agree(augmentation, rng):
    q, qd, tau = rng.uniform(-1, 1, (6, 7)), rng.uniform(-1, 1, (6, 7)), rng.uniform(-9, 9, (6, 7))
    batch = augmentation.joint_torque(q, qd, tau)
    np.testing.assert_allclose(batch, [augmentation.joint_torque(*x) for x in zip(q, qd, tau)])
    assert augmentation.effect_names[:2] == ("payload", "armature")


@pytest.mark.parametrize("change, message", [
    ({"joint_names": NAMES[:6]}, "written for joints"),
    ({"effects": [{"name": "backlash", "joint_indices": [0], "theta": [1.0]}]}, "unknown effect 'backlash'"),
    ({"effects": [{"name": "armature", "joint_indices": [0, 9], "theta": [1.0, 1.0]}]}, "joint_indices"),
    ({"effects": [{"name": "viscous_friction", "joint_indices": [0], "theta": [1.0, 2.0]}]}, "expected 1"),
    ({"effects": [{"name": "armature", "joint_indices": [0], "theta": [-0.1]}]}, "≥ 0"),
    ({"effects": [{"name": "torque_offset", "joint_indices": [0], "theta": [float("nan")]}]}, "NaN"),
    ({"effects": [{"name": "position_ripple", "joint_indices": [0], "theta": [1.0, 1.0]}]}, "cycles_per_rev"),
    # a negative payload mass is a tool mismatch, refused only if the link becomes unphysical (test_gap_priors)
    ({"effects": [{"name": "link_inertia", "joint_indices": [0], "theta": [0.0] * 10}]}, "expected 60"),
    ({"effects": "none"}, "'effects' list"),
])
def test_bad_augmentation_files_are_rejected_with_the_reason(tmp_path, change, message):
    path = _write(tmp_path, _document(**change))
    with pytest.raises(AugmentationError, match=message) as info:
        load_augmentation(path, NAMES)
    assert str(path) in str(info.value) and "kvark diagnose" in str(info.value)


def test_missing_and_unparsable_augmentation_files(tmp_path):
    with pytest.raises(AugmentationError, match="file not found"):
        load_augmentation(tmp_path / "none.yaml", NAMES)
    (tmp_path / "broken.yaml").write_text("effects: [\n")
    with pytest.raises(AugmentationError, match="invalid YAML"):
        load_augmentation(tmp_path / "broken.yaml", NAMES)


@pytest.fixture(scope="module")
def trained(config):
    return load_model(ROOT / "models" / "panda", config.joint_names)


def test_model_directory_carries_its_augmentation_and_the_estimator_uses_it(config, augmentation, trained,
                                                                              tmp_path, rng):
    save_model(tmp_path / "model", replace(trained, augmentation=augmentation))
    loaded = load_model(tmp_path / "model", config.joint_names)
    assert loaded.augmentation is not None and loaded.augmentation.sha256 == augmentation.sha256
    estimator = Estimator.from_config(replace(config, model_dir=str(tmp_path / "model")))
    assert estimator.robot.augmentation is not None
    q, qd, tau_m = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-9, 9, 7)
    np.testing.assert_allclose(estimator.robot.momentum_terms(q, qd, tau_m)[1],
                               RobotModel.from_config(config, augmentation).momentum_terms(q, qd, tau_m)[1])


def test_edited_augmentation_in_a_model_directory_is_refused(config, augmentation, trained, tmp_path):
    save_model(tmp_path / "model", replace(trained, augmentation=augmentation))
    copy = tmp_path / "model" / AUGMENTATION_FILE
    copy.write_text(copy.read_text().replace("0.3", "0.31", 1))
    with pytest.raises(ResidualModelError, match="changed since training"):
        load_model(tmp_path / "model", config.joint_names)


def test_config_naming_another_augmentation_than_the_model_was_trained_with_is_refused(
        config, augmentation, trained, tmp_path):
    other = _write(tmp_path, _document(effects=_document()["effects"][:2]), "other.yaml")
    save_model(tmp_path / "model", replace(trained, augmentation=augmentation))
    with pytest.raises(AugmentationError, match="trained with another augmentation"):
        Estimator.from_config(replace(config, model_dir=str(tmp_path / "model"), model_augmentation=str(other)))
    with pytest.raises(AugmentationError, match="trained without an augmentation"):
        Estimator.from_config(replace(config, model_augmentation=str(other)), trained)


def test_oracle_refuses_an_augmented_model(config, augmentation, trained):
    from kvark_ros.sim.plant import OracleResidual, load_plant
    oracle = OracleResidual(load_plant(None, 7), 7)
    with pytest.raises(ObserverError, match="augmented"):
        make_observer("oracle", replace(trained, augmentation=augmentation), config.filter, oracle)
