"""``kvark init``: a config for a new robot from its URDF or xacro, made from the key table and loadable."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from kvark_ros.cli import main
from kvark_ros.core.config import NODE_NAME, file_parameters, load_config
from kvark_ros.core.config_schema import KEYS, KEYS_BY_NAME
from kvark_ros.core.config_sources import regenerated_config_text
from kvark_ros.core.estimation.robot_model import RobotModel

ROOT = Path(__file__).resolve().parents[2]
PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]


def _link(name: str, mass: float | str = 1.0, mesh: str = "") -> str:
    visual = f'<visual><geometry><mesh filename="{mesh}"/></geometry></visual>' if mesh else ""
    return (f'<link name="{name}"><inertial><mass value="{mass}"/><origin xyz="0 0 0.1"/>'
            f'<inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>{visual}</link>')


def _joint(name: str, parent: str, child: str, kind: str = "revolute", axis: str = "0 0 1") -> str:
    limit = '<limit lower="-3" upper="3" effort="50" velocity="2"/>' if kind != "fixed" else ""
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="0 0 0.3"/><axis xyz="{axis}"/>{limit}</joint>')


def small_arm_urdf() -> str:
    """Three revolute joints, a fixed flange and tool point, and a two-finger gripper (a branch)."""
    parts = [_link("base"), _link("l1"), _link("l2"), _link("l3"), _link("flange", 0.1), _link("tcp", 0.01),
             _link("finger_a", 0.05), _link("finger_b", 0.05),
             _joint("j1", "base", "l1"), _joint("j2", "l1", "l2", axis="0 1 0"), _joint("j3", "l2", "l3", axis="0 1 0"),
             _joint("flange_joint", "l3", "flange", "fixed"), _joint("tcp_joint", "flange", "tcp", "fixed"),
             _joint("finger_a_joint", "flange", "finger_a", "prismatic", "1 0 0"),
             _joint("finger_b_joint", "flange", "finger_b", "prismatic", "-1 0 0")]
    return f'<?xml version="1.0"?><robot name="arm">{"".join(parts)}</robot>'


def _init(*args: str | Path) -> int:
    return main(["init", *map(str, args)])


def _parameters(path: Path) -> dict:
    return file_parameters(yaml.safe_load(path.read_text()), str(path))


def _urdf_of(config_path: Path) -> Path:
    """The URDF a config names, resolved against the config's own folder (the path rule)."""
    value = Path(_parameters(config_path)["robot_model.urdf"])
    return value if value.is_absolute() else config_path.parent / value


def test_panda_from_example_robot_data_proposes_the_arm_and_the_tcp(tmp_path, capsys):
    out = tmp_path / "config" / "panda2.yaml"
    assert _init("--urdf", "example-robot-data:panda", "--robot", "panda2", "--out", out) == 0
    printed = capsys.readouterr().out
    assert "Locked (not estimated): panda_finger_joint1, panda_finger_joint2" in printed
    assert "ee_frame: panda_hand_tcp (Proposed by kvark init: the last link of the chain" in printed
    parameters = _parameters(out)
    # every key, in the table's order within each section (the YAML nests a section's keys together)
    sections = list(dict.fromkeys(key.name.split(".")[0] for key in KEYS))
    assert list(parameters) == [key.name for key in sorted(KEYS, key=lambda k: sections.index(k.name.split(".")[0]))]
    for key in KEYS:
        if key.default is not None:
            assert parameters[key.name] == key.default, key.name
    config = load_config(out)
    assert list(config.joint_names) == PANDA_JOINTS == list(load_config(ROOT / "config" / "panda.yaml").joint_names)
    assert (config.ee_frame, config.flange_frame, config.robot) == ("panda_hand_tcp", "panda_hand_tcp", "panda2")
    assert parameters["residual_model.model_dir"] == "../models/panda2"    # config/ and models/ side by side
    RobotModel.from_config(config)


def test_every_key_is_commented_with_its_meaning_and_allowed_values(tmp_path):
    out = tmp_path / "ur.yaml"
    assert _init("--urdf", "example-robot-data:ur5", "--robot", "ur", "--out", out) == 0
    lines = out.read_text().splitlines()
    rows, path = {}, []
    for row, line in enumerate(lines):
        if line.strip() and not line.lstrip().startswith("#"):
            depth = (len(line) - len(line.lstrip())) // 2 - 2
            name = line.strip().split(":")[0]
            path = path[:max(depth, 0)] + [name]
            rows[".".join(path)] = row
    for key in KEYS:
        comment = []
        for line in reversed(lines[:rows[key.name]]):
            if not line.strip().startswith("#"):
                break
            comment.insert(0, line.strip()[2:])
        text = " ".join(comment)
        assert key.meaning in text and f"Allowed: {key.documented}." in text, key.name
    assert all(len(line) <= 110 for line in lines)
    assert _parameters(out)["robot_model.ee_frame"] == "tool0"           # the deepest link, as config/ur5.yaml
    assert _parameters(out)["residual_model.model_dir"] == "models/ur"


def test_init_writes_through_the_config_file_generator(tmp_path):
    """The same code writes config/*.yaml: the file is what ``--write-configs`` makes of it, init's notes (after a
    lone '#') kept; the header names only keys the loader accepts."""
    out = tmp_path / "config" / "panda2.yaml"
    assert _init("--urdf", "example-robot-data:panda", "--robot", "panda2", "--out", out) == 0
    text = out.read_text()
    assert regenerated_config_text(text) == text
    assert "      #\n      # Proposed by kvark init: the last link of the chain" in text
    header = text[:text.index(f"{NODE_NAME}:")]
    groups = "|".join({key.name.split(".")[0] for key in KEYS if "." in key.name})
    named = re.findall(rf"\b(?:{groups})(?:\.[a-z_]+)+", header)
    assert named and all(name in KEYS_BY_NAME for name in named), named


def test_hand_written_urdf_path_is_relative_to_the_config_folder(tmp_path, capsys):
    urdf = tmp_path / "description" / "arm.urdf"
    urdf.parent.mkdir()
    urdf.write_text(small_arm_urdf())
    out = tmp_path / "config" / "arm.yaml"
    assert _init("--urdf", urdf, "--robot", "arm", "--out", out) == 0
    parameters = _parameters(out)
    assert parameters["robot_model.urdf"] == "../description/arm.urdf"
    assert _urdf_of(out).samefile(urdf)
    assert parameters["robot_model.joint_names"] == ["j1", "j2", "j3"]    # the fingers branch off: locked
    assert parameters["robot_model.ee_frame"] == parameters["robot_model.flange_frame"] == "tcp"
    assert "Locked (not estimated): finger_a_joint, finger_b_joint" in capsys.readouterr().out
    config = load_config(out)
    RobotModel(str(_urdf_of(out)), config.joint_names, config.ee_frame, config.flange_frame)


def test_joints_and_frames_chosen_by_flags(tmp_path):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(small_arm_urdf())
    out = tmp_path / "arm.yaml"
    assert _init("--urdf", urdf, "--robot", "arm", "--joints", "j1,j2", "--ee-frame", "l3", "--flange-frame",
                 "flange", "--out", out) == 0
    parameters = _parameters(out)
    assert parameters["robot_model.joint_names"] == ["j1", "j2"]
    assert (parameters["robot_model.ee_frame"], parameters["robot_model.flange_frame"]) == ("l3", "flange")
    out2 = tmp_path / "arm2.yaml"
    assert _init("--urdf", urdf, "--robot", "arm", "--ee-frame", "l2", "--out", out2) == 0
    assert _parameters(out2)["robot_model.joint_names"] == ["j1", "j2"]   # the joints that move l2


def test_urdf_elsewhere_is_written_absolute(tmp_path):
    urdf = tmp_path / "elsewhere" / "arm.urdf"
    urdf.parent.mkdir()
    urdf.write_text(small_arm_urdf())
    out = tmp_path / "project" / "config" / "arm.yaml"
    assert _init("--urdf", urdf, "--robot", "arm", "--out", out) == 0
    assert _parameters(out)["robot_model.urdf"] == str(urdf.resolve())


@pytest.mark.parametrize("flags, message", [
    (("--ee-frame", "gripper_tip"), "--ee-frame 'gripper_tip' is not a frame of the URDF; the last links of the "
                                    "chain are tcp, flange, l3"),
    (("--flange-frame", "nope"), "--flange-frame 'nope' is not a frame of the URDF"),
    (("--joints", "j1,j9"), "--joints: 'j9' is not a movable joint of the URDF; it has j1, j2, j3, finger_a_joint"),
    (("--joints", "j2,j1"), "joint_names must follow the kinematic chain order"),
    (("--robot", "my robot"), "--robot 'my robot': use letters, digits, _ and - only"),
])
def test_bad_choices_are_one_error_line_and_no_file(tmp_path, capsys, flags, message):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(small_arm_urdf())
    out = tmp_path / "arm.yaml"
    assert _init("--urdf", urdf, "--robot", "arm", "--out", out, *flags) == 1
    err = capsys.readouterr().err
    assert err.startswith("kvark: error: ") and err.count("\n") == 1 and message in err, err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["arm.urdf"]


def test_existing_config_is_refused_unless_force(tmp_path, capsys):
    out = tmp_path / "ur.yaml"
    out.write_text("old")
    assert _init("--urdf", "example-robot-data:ur5", "--robot", "ur", "--out", out) == 1
    assert "exists and is not empty; pass --force" in capsys.readouterr().err and out.read_text() == "old"
    assert _init("--urdf", "example-robot-data:ur5", "--robot", "ur", "--out", out, "--force") == 0
    load_config(out)


def _xacro_package(root: Path) -> Path:
    """A description package: a xacro that includes a macro file with $(find ...), which includes a property
    file by package://, and takes a prefix argument."""
    package = root / "my_arm_description"
    (package / "urdf").mkdir(parents=True)
    (package / "urdf" / "mass.xacro").write_text(
        '<?xml version="1.0"?><robot xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<xacro:property name="link_mass" value="1.5"/></robot>')
    (package / "urdf" / "parts.xacro").write_text(
        '<?xml version="1.0"?><robot xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<xacro:include filename="package://my_arm_description/urdf/mass.xacro"/>'
        '<xacro:macro name="arm_link" params="name">'
        + _link("${name}", "${link_mass}", mesh="package://my_arm_description/meshes/${name}.stl")
        + "</xacro:macro></robot>")
    body = "".join(f'<xacro:arm_link name="${{prefix}}{name}"/>' for name in ("base", "l1", "l2"))
    joints = (_joint("${prefix}j1", "${prefix}base", "${prefix}l1")
              + _joint("${prefix}j2", "${prefix}l1", "${prefix}l2", axis="0 1 0"))
    (package / "urdf" / "arm.urdf.xacro").write_text(
        '<?xml version="1.0"?><robot name="arm" xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<xacro:arg name="prefix" default=""/><xacro:property name="prefix" value="$(arg prefix)"/>'
        '<xacro:include filename="$(find my_arm_description)/urdf/parts.xacro"/>' + body + joints + "</robot>")
    return package


def test_xacro_with_find_and_package_path(tmp_path, capsys):
    package = _xacro_package(tmp_path)
    out = tmp_path / "config" / "arm.yaml"
    assert _init("--xacro", package / "urdf" / "arm.urdf.xacro", "--package-path", f"my_arm_description={package}",
                 "--xacro-arg", "prefix:=left_", "--robot", "arm", "--out", out) == 0
    expanded = tmp_path / "config" / "arm.urdf"
    assert f"URDF: {expanded}" in capsys.readouterr().out
    parameters = _parameters(out)
    assert parameters["robot_model.urdf"] == "arm.urdf" and _urdf_of(out) == expanded
    assert parameters["robot_model.joint_names"] == ["left_j1", "left_j2"]
    text = expanded.read_text()
    assert "package://my_arm_description/meshes/left_base.stl" in text and 'mass value="1.5"' in text
    config = load_config(out)
    RobotModel(str(expanded), config.joint_names, config.ee_frame, config.flange_frame)


def test_xacro_without_its_package_path_or_argument_is_one_error(tmp_path, capsys):
    package = _xacro_package(tmp_path)
    xacro_file = package / "urdf" / "arm.urdf.xacro"
    out = tmp_path / "config" / "arm.yaml"
    assert _init("--xacro", xacro_file, "--robot", "arm", "--out", out) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "package 'my_arm_description' is not known" in err
    assert "add --package-path my_arm_description=DIR" in err
    xacro_file.write_text(xacro_file.read_text().replace('<xacro:arg name="prefix" default=""/>', ""))
    assert _init("--xacro", xacro_file, "--package-path", f"my_arm_description={package}", "--robot", "arm",
                 "--out", out) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "xacro argument 'prefix' is undefined; pass --xacro-arg prefix:=VALUE" in err
    assert not out.parent.exists() or not any(out.parent.iterdir())
