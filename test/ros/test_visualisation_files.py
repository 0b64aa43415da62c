"""The RViz config and the PlotJuggler layout shipped for the node's outputs name topics, types and fields the node
publishes, and setup.py installs them under share/kvark_ros."""
from __future__ import annotations

import ast
import platform
import sys
import xml.etree.ElementTree as ET
from glob import glob
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
if not (sys.platform == "linux" and platform.machine() == "x86_64"):
    pytest.skip("the ROS 2 Jazzy wheels exist for linux x86_64 only", allow_module_level=True)

from kvark_ros.core.config import load_config  # noqa: E402
from kvark_ros.ros.publishers import FLAGS, TOPICS  # noqa: E402

NODE = "/kvark_estimator"
DISPLAY_TYPES = {"rviz_default_plugins/Wrench": "WrenchStamped"}       # display class -> the message it draws


def test_rviz_draws_the_ee_frame_wrench_where_it_acts_on_the_arm():
    config = yaml.safe_load((ROOT / "rviz" / "kvark_estimator.rviz").read_text())
    displays = {display["Class"]: display for display in config["Visualization Manager"]["Displays"]}
    assert displays["rviz_default_plugins/RobotModel"]["Description Topic"]["Value"] == "/robot_description"
    assert displays["rviz_default_plugins/RobotModel"]["Description Topic"]["Durability Policy"] == "Transient Local"
    for kind, message in DISPLAY_TYPES.items():
        topic = displays[kind]["Topic"]["Value"]
        assert topic.startswith(f"{NODE}/") and TOPICS[topic.removeprefix(f"{NODE}/")].__name__ == message
    assert displays["rviz_default_plugins/Wrench"]["Topic"]["Value"].endswith("external_wrench_in_ee_frame")
    assert config["Visualization Manager"]["Global Options"]["Fixed Frame"] == "panda_link0"


def test_plotjuggler_curves_are_fields_of_the_topics_it_subscribes():
    root = ET.parse(ROOT / "plotjuggler" / "kvark_estimator.xml").getroot()
    selected = root.find(".//plugin[@ID='ROS2 Topic Subscriber']/selected_topics").get("value").split(";")
    assert all(topic.startswith(f"{NODE}/") and topic.removeprefix(f"{NODE}/") in TOPICS for topic in selected)
    assert root.find(".//plugin/use_header_stamp").get("value") == "true"        # aligned on the input's stamps
    joints = set(load_config(ROOT / "config" / "panda.yaml").joint_names)
    curves = [curve.get("name") for curve in root.iter("curve")]
    assert len(curves) == 6 + 14 + 2
    for curve in curves:
        topic = next(t for t in selected if curve.startswith(t + "/"))
        field = curve.removeprefix(topic + "/").split("/")
        kind = TOPICS[topic.removeprefix(f"{NODE}/")].__name__
        if kind == "JointState":
            assert field[0] in (set(FLAGS) if topic.endswith("contact_state") else joints), curve
            assert field[1] in ("position", "velocity", "effort") and len(field) == 2, curve
        else:
            assert kind == "WrenchStamped" and field[0] == "wrench" and field[1] in ("force", "torque") \
                and field[2] in "xyz", curve


def test_setup_installs_the_files_under_share(monkeypatch):
    """setup.py's own ``_tree`` (run here alone, from the project root as pip and colcon run it) on its calls."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    [function] = [node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == "_tree"]
    scope = {"glob": glob, "PACKAGE": "kvark_ros"}
    exec(compile(ast.Module(body=[function], type_ignores=[]), "setup.py", "exec"), scope)
    calls = {node.args[0].value for node in ast.walk(tree) if isinstance(node, ast.Call)
             and getattr(node.func, "id", "") == "_tree"}
    assert {"rviz", "plotjuggler", "config", "launch"} <= calls
    monkeypatch.chdir(ROOT)
    installed = {target: files for name in calls for target, files in scope["_tree"](name)}
    assert "rviz/kvark_estimator.rviz" in installed["share/kvark_ros/rviz"]
    assert "plotjuggler/kvark_estimator.xml" in installed["share/kvark_ros/plotjuggler"]
    assert "config/drivers/franka_panda.yaml" in installed["share/kvark_ros/config/drivers"]
