"""The shared configuration: shipped files load, bad keys and values are named."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from kvark_ros.core.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("robot, joints", [("panda", 7), ("ur5", 6)])
def test_shipped_configs_load(robot, joints):
    config = load_config(ROOT / "config" / f"{robot}.yaml")
    assert config.robot == robot and config.n_joints == joints
    assert config.observer == "kvark" and config.payload is None


def test_every_shipped_key_has_a_comment():
    for path in (ROOT / "config").glob("*.yaml"):
        lines = path.read_text().splitlines()
        for index, line in enumerate(lines):
            stripped = line.strip()
            if ":" in stripped and not stripped.startswith("#") and not stripped.endswith(":") \
                    and not stripped.startswith(("panda_joint", "wrist_")):
                above = lines[index - 1].strip()
                assert "#" in line or above.startswith("#"), f"{path.name}:{index + 1} has no comment"


def write(tmp_path, parameters) -> Path:
    (tmp_path / "config").mkdir(exist_ok=True)
    path = tmp_path / "config" / "test.yaml"
    path.write_text(yaml.safe_dump({"kvark_estimator": {"ros__parameters": parameters}}))
    return path


def base_parameters() -> dict:
    document = yaml.safe_load((ROOT / "config" / "panda.yaml").read_text())
    return document["kvark_estimator"]["ros__parameters"]


@pytest.mark.parametrize("group, key, value, message", [
    ("filter", "ewma_time", -1.5, r"filter\.ewma_time.*\(0\.0, 1000000\.0\]"),
    ("filter", "vb_iterations", 0, r"filter\.vb_iterations.*integer in \[1, 50\]"),
    ("filter", "vb_variant", "magic", r"filter\.vb_variant.*one of paper, huang"),
    ("wrench", "frame", "tool", r"wrench\.frame.*base, end_effector"),
    ("filter", "initial_covariance", float("nan"), r"filter\.initial_covariance"),
    (None, "observer", "bogus", r"observer.*kvark"),
])
def test_bad_values_name_the_key_and_the_allowed_range(tmp_path, group, key, value, message):
    parameters = base_parameters()
    (parameters[group] if group else parameters)[key] = value
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, parameters))


def test_unknown_key_is_refused_with_its_dotted_name(tmp_path):
    parameters = base_parameters()
    parameters["filter"]["ewma_rat"] = 0.1
    with pytest.raises(ConfigError, match=r"unknown key 'filter\.ewma_rat'"):
        load_config(write(tmp_path, parameters))


def test_missing_required_key_is_named(tmp_path):
    parameters = base_parameters()
    del parameters["robot_model"]["joint_names"]
    with pytest.raises(ConfigError, match="robot_model.joint_names"):
        load_config(write(tmp_path, parameters))


def test_invalid_yaml_and_wrong_layout_are_reported(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("kvark_estimator: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML at line"):
        load_config(broken)
    flat = tmp_path / "flat.yaml"
    flat.write_text("observer: kvark\n")
    with pytest.raises(ConfigError, match="ros__parameters"):
        load_config(flat)
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "absent.yaml")


def test_overrides_and_payload(tmp_path):
    parameters = base_parameters()
    parameters["robot_model"]["payload"]["mass"] = 1.5
    config = load_config(write(tmp_path, parameters), observer="kf")
    assert config.observer == "kf" and config.payload.mass == 1.5

