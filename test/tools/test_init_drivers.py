"""``kvark init --driver franka|ur|lbr``: a file that runs beside the driver as it publishes (docs/ros.md, Drivers):
the torque source and its measurement, the topic, the flange and ee frames and the wrench's base frame; the UR's
motor current needs a scale, refused in one line without one. Also the shipped franka_ros2 file
(config/drivers/franka_panda.yaml) is what the key table generates, and ``kvark init --help`` names every
example-robot-data URDF."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml

from kvark_ros.cli import main
from kvark_ros.core.config import ANY_NAMESPACE, ConfigError, file_parameters, load_config
from kvark_ros.core.config_sources import regenerated_config_text
from kvark_ros.core.estimation.robot_model import EXAMPLE_ROBOT_DATA_URDFS, resolve_urdf

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "test"))
from driver_fixtures import LBR_JOINTS, UR_TORQUE_CONSTANTS, lbr_urdf  # noqa: E402


def _init(*args: str | Path) -> int:
    return main(["init", *map(str, args)])


def _values(path: Path) -> dict:
    document = yaml.safe_load(path.read_text())
    assert list(document) == [ANY_NAMESPACE]                # the node in any namespace, every command alike
    return file_parameters(document, str(path))


@pytest.mark.parametrize("arm", ["panda", "fr3"])
def test_franka_takes_the_1khz_link_torque_stream_with_link8_and_the_hand_tcp(tmp_path, arm):
    """Panda (example-robot-data) and FR3 (the same URDF with franka_description's fr3_ names, the naming is all
    this test needs of it): tau_J of franka/joint_states, a link-side sensor, flange <arm>_link8, ee <arm>_hand_tcp."""
    urdf = tmp_path / f"{arm}.urdf"
    urdf.write_text(resolve_urdf("example-robot-data:panda").replace("panda_", f"{arm}_"))
    out = tmp_path / "config" / f"{arm}.yaml"
    assert _init("--urdf", urdf, "--driver", "franka", "--robot", arm, "--out", out) == 0
    values = _values(out)
    assert values["input.torque_source"] == "joint_states_effort"
    assert values["input.joint_states_topic"] == "franka/joint_states"
    assert values["robot_model.torque_measurement"] == "link_torque_sensor"
    assert (values["robot_model.ee_frame"], values["robot_model.flange_frame"]) == (f"{arm}_hand_tcp", f"{arm}_link8")
    assert values["robot_model.joint_names"] == [f"{arm}_joint{k}" for k in range(1, 8)]
    assert load_config(out).urdf == str(urdf)


def test_franka_without_the_hand_takes_link8_as_ee_frame(tmp_path):
    text = resolve_urdf("example-robot-data:panda")
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(text.replace('name="panda_hand_tcp"', 'name="panda_tcp_of_another_tool"')
                    .replace('link="panda_hand_tcp"', 'link="panda_tcp_of_another_tool"'))
    out = tmp_path / "arm.yaml"
    assert _init("--urdf", urdf, "--driver", "franka", "--robot", "arm", "--out", out) == 0
    assert _values(out)["robot_model.ee_frame"] == "panda_link8"


def test_ur_needs_a_scale_for_its_amperes_and_publishes_in_urs_base(tmp_path, capsys):
    out = tmp_path / "ur10.yaml"
    assert _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--robot", "ur10", "--out", out) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "--driver ur: the driver's joint_states effort is a motor current (A); pass " \
                               "--effort-scale with N·m/A per joint" in error[0]
    assert not out.exists()
    scale = ",".join(map(str, UR_TORQUE_CONSTANTS))
    assert _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--effort-scale", scale, "--robot", "ur10",
                 "--out", out) == 0
    values = _values(out)
    assert values["input.effort_scale"] == list(UR_TORQUE_CONSTANTS) and values["input.effort_offset"] == [0.0]
    assert values["robot_model.torque_measurement"] == "motor_current"
    assert values["input.torque_source"] == "joint_states_effort"
    assert values["input.joint_states_topic"] == "joint_states"
    assert (values["robot_model.ee_frame"], values["robot_model.flange_frame"]) == ("tool0", "tool0")
    assert values["wrench.base_frame"] == "base"
    assert _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--effort-scale", "1", "--robot", "ur10",
                 "--out", out, "--force") == 0
    assert _values(out)["input.effort_scale"] == [1.0]        # a driver that reports torque


@pytest.mark.parametrize("scale", ["nan", "1,,2", "amps"])
def test_an_effort_scale_that_is_no_list_of_numbers_is_refused(tmp_path, scale, capsys):
    with pytest.raises(SystemExit) as stop:
        _init("--urdf", "example-robot-data:ur10", "--effort-scale", scale, "--robot", "ur", "--out",
              tmp_path / "ur.yaml")
    assert stop.value.code == 2 and "expected comma-separated numbers" in capsys.readouterr().err


def test_a_scale_of_the_wrong_count_is_refused_by_the_config_in_one_line(tmp_path, capsys):
    assert _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--effort-scale", "10,10", "--robot", "ur",
                 "--out", tmp_path / "ur.yaml") == 1
    assert "key 'input.effort_scale' has 2 values; give 1 (every joint) or 6" in capsys.readouterr().err


def test_lbr_reads_the_drivers_namespaced_joint_states_with_its_link_sensors(tmp_path):
    urdf = tmp_path / "config" / "iiwa14.urdf"
    urdf.parent.mkdir()
    urdf.write_text(lbr_urdf())
    out = tmp_path / "config" / "iiwa14.yaml"
    assert _init("--urdf", urdf, "--driver", "lbr", "--robot", "iiwa14", "--out", out) == 0
    values = _values(out)
    assert values["robot_model.joint_names"] == list(LBR_JOINTS)
    assert values["input.joint_states_topic"] == "/lbr/joint_states"       # a bag recorded from the driver
    assert values["robot_model.torque_measurement"] == "link_torque_sensor"
    assert (values["robot_model.ee_frame"], values["robot_model.flange_frame"]) == ("lbr_link_ee", "lbr_link_ee")
    assert values["robot_model.urdf"] == "iiwa14.urdf"                       # relative to the file


def test_the_users_frames_win_over_the_drivers(tmp_path):
    out = tmp_path / "ur.yaml"
    assert _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--effort-scale", "1", "--ee-frame",
                 "ee_link", "--robot", "ur", "--out", out) == 0
    values = _values(out)
    assert (values["robot_model.ee_frame"], values["robot_model.flange_frame"]) == ("ee_link", "tool0")


def test_the_shipped_franka_file_is_generated_and_loads(tmp_path):
    path = ROOT / "config" / "drivers" / "franka_panda.yaml"
    text = path.read_text()
    assert regenerated_config_text(text, path.name) == text, "run make generated"
    config = load_config(path)
    assert config.model_dir == str(ROOT / "models" / "panda")
    assert (config.input.torque_source, config.input.joint_states_topic) == ("joint_states_effort",
                                                                             "franka/joint_states")
    assert config.torque_measurement == "link_torque_sensor"


def test_init_help_names_every_example_robot_data_urdf(capsys):
    with pytest.raises(SystemExit):
        main(["init", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(f":{robot}" in text for robot in EXAMPLE_ROBOT_DATA_URDFS), text
    assert "--driver {franka,lbr,ur}" in text


def test_a_file_without_the_nodes_key_is_refused_by_every_command_naming_both_keys(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("/**/controller_manager:\n  ros__parameters: {update_rate: 100}\n")
    with pytest.raises(ConfigError, match=r"'/\*\*/kvark_estimator:' for the node in any namespace"):
        load_config(path)
