"""The shared configuration: shipped files load, bad keys and values are named."""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest
import yaml

from kvark_ros.core.config import ConfigError, EstimatorConfig, FilterSettings, load_config
from kvark_ros.core.config_schema import KEYS, KEYS_BY_NAME, keys_table
from kvark_ros.core.config_sources import (comment_lines, describe, parse_config_text, document_with_keys_table,
                                           regenerated_config_text)
from kvark_ros.core.settings import SETTINGS_BY_GROUP

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


@pytest.mark.parametrize("value", ["numpy", "numba"])
def test_the_removed_kernel_key_says_the_step_is_always_compiled(tmp_path, value):
    """filter.kernel (numpy or numba) is gone: one error line saying so, not 'unknown key'."""
    parameters = base_parameters()
    parameters["filter"]["kernel"] = value
    with pytest.raises(ConfigError, match=r"key 'filter\.kernel' was removed: the momentum-form K-VARK step is "
                                          r"always compiled") as error:
        load_config(write(tmp_path, parameters))
    assert "\n" not in str(error.value)


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



def test_settings_groups_are_typed_frozen_dataclasses_with_the_table_defaults():
    hints = typing.get_type_hints(FilterSettings)
    assert hints["vb_variant"] == typing.Literal["paper", "huang", "smoothed", "window"]
    assert hints["vb_iterations"] is int and hints["ewma_time"] is float
    assert typing.get_type_hints(EstimatorConfig)["joint_names"] == tuple[str, ...]
    for group, settings in SETTINGS_BY_GROUP.items():
        defaults = settings()
        assert all(getattr(defaults, key.attr) == (tuple(key.default) if isinstance(key.default, list) else key.default)
                   for key in KEYS if key.group == group), group        # lists are held as tuples
    with pytest.raises(dataclasses.FrozenInstanceError):
        FilterSettings().ewma_time = 1.0  # type: ignore[misc]
    config = load_config(ROOT / "config" / "panda.yaml")
    assert type(config.filter) is FilterSettings and config.n_joints == 7


def test_regenerating_a_config_rewrites_key_comments_and_keeps_values_notes_and_prose():
    """A stale table comment is replaced, a missing key is written with its default, the rest stays."""
    text = (ROOT / "config" / "ur5.yaml").read_text()
    key = KEYS_BY_NAME["filter.ewma_time"]
    table_comment = "\n".join(f"      {line}" for line in comment_lines(describe(key), key.name))
    assert table_comment in text
    note = "      #\n      # A note of this file.\n"
    edited = (text.replace(table_comment, "      # an old meaning of the key")
              .replace("      vb_iterations: 1\n", "      vb_iterations: 3\n")
              .replace("      max_gap: 0.05\n", f"{note}      max_gap: 0.05\n"))
    topic = KEYS_BY_NAME["input.wrench_topic"]                         # a key without a note: as a new row
    assert topic.name not in parse_config_text(text).notes
    topic_lines = "".join(f"      {line}\n" for line in [*comment_lines(describe(topic), topic.name),
                                                          "wrench_topic: /ft_sensor/wrench"])
    edited = edited.replace(topic_lines, "")
    assert "wrench_topic" not in edited and "an old meaning" in edited
    expected = text.replace("      vb_iterations: 1\n", "      vb_iterations: 3\n").replace(
        "      max_gap: 0.05\n", f"{note}      max_gap: 0.05\n")
    assert regenerated_config_text(edited) == expected
    assert "onset_threshold: 0.0" in expected and "Off on the UR5" in expected     # the robot's own value and note


def test_regenerating_refuses_a_file_with_an_unknown_key():
    text = (ROOT / "config" / "panda.yaml").read_text().replace("      ewma_time: 0.2\n", "      ewma_rate: 0.01\n")
    with pytest.raises(ValueError, match="unknown key 'filter.ewma_rate'"):
        regenerated_config_text(text)


def test_the_documented_table_of_keys_is_replaced_whole_and_a_document_without_one_is_refused():
    """``make generated`` rewrites docs/configuration.md's table of keys from the table, leaving the text around it."""
    stale = ("intro\n\n| key | allowed | default | run time | meaning |\n|---|---|---|---|---|\n"
             "| `old` | x | y | no | z |\n\nafter\n")
    fresh = document_with_keys_table(stale)
    assert fresh == "intro\n\n" + keys_table() + "\n\nafter\n"
    assert document_with_keys_table(fresh) == fresh
    with pytest.raises(ValueError, match="no table of keys"):
        document_with_keys_table("intro\n")


@pytest.mark.parametrize("value", ["link_torque_sensor", "motor_current", "commanded_effort"])
def test_torque_measurement_takes_its_three_values(tmp_path, value):
    parameters = base_parameters()
    parameters["robot_model"]["torque_measurement"] = value
    assert load_config(write(tmp_path, parameters)).torque_measurement == value


def test_torque_measurement_refuses_others_with_a_did_you_mean(tmp_path):
    parameters = base_parameters()
    parameters["robot_model"]["torque_measurement"] = "motor_curent"
    with pytest.raises(ConfigError, match=r"robot_model\.torque_measurement.*did you mean 'motor_current'"):
        load_config(write(tmp_path, parameters))
    del parameters["robot_model"]["torque_measurement"]      # unknown robots: motor_current (the key's comment)
    assert load_config(write(tmp_path, parameters)).torque_measurement == "motor_current"
    assert load_config(ROOT / "config" / "panda.yaml").torque_measurement == "link_torque_sensor"
    assert load_config(ROOT / "config" / "ur5.yaml").torque_measurement == "motor_current"
