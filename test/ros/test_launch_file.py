"""launch_testing: start the real estimator node with launch/estimator.launch.py and check its topics.

Needs ROS 2 (rclpy, launch_testing, launch_ros) and the package built in a colcon workspace;
it is skipped where those are missing (the rest of the suite drives the node through the test
suite's rclpy stand-in, see ros/test_node_logic_stand_in.py). Run under ROS with
``colcon test --packages-select kvark_ros`` or ``launch_test test/ros/test_launch_file.py``.
"""
from __future__ import annotations

import tempfile
import time
import unittest
from pathlib import Path

import pytest

launch_testing = pytest.importorskip("launch_testing")
rclpy = pytest.importorskip("rclpy")
if getattr(rclpy, "STAND_IN", False):
    pytest.skip("rclpy here is the test suite's stand-in, not ROS", allow_module_level=True)
pytest.importorskip("launch_ros")

import launch  # noqa: E402
import launch_testing.actions  # noqa: E402
import launch_testing.asserts  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import WrenchStamped  # noqa: E402
from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool, Float64MultiArray, MultiArrayDimension  # noqa: E402

from kvark_ros.core.config import load_config  # noqa: E402
from kvark_ros.core.estimation.model_store import save_model  # noqa: E402
from kvark_ros.core.estimation.robot_model import RobotModel  # noqa: E402
from kvark_ros.tools.synthetic import synthetic_stream, train_synthetic  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
OUT = "/kvark_estimator"


def _robot() -> RobotModel:
    config = load_config(CONFIG)
    return RobotModel(config.urdf, config.joint_names, config.ee_frame, config.flange_frame)


def _config_with_a_model() -> str:
    """config/panda.yaml with a small freshly trained model, written to a temporary directory."""
    directory = Path(tempfile.mkdtemp(prefix="kvark_launch_test_"))
    save_model(directory / "model", train_synthetic(_robot(), "panda", seed=3, duration=6.0, baselines=False))
    document = yaml.safe_load(CONFIG.read_text())
    document["kvark_estimator"]["ros__parameters"]["residual_model"]["model_dir"] = str(directory / "model")
    path = directory / "panda.yaml"
    path.write_text(yaml.safe_dump(document))
    return str(path)


@pytest.mark.launch_test
def generate_test_description():
    estimator = launch.actions.IncludeLaunchDescription(
        PythonLaunchDescriptionSource(str(ROOT / "launch" / "estimator.launch.py")),
        launch_arguments={"config": _config_with_a_model()}.items())
    return launch.LaunchDescription([estimator, launch_testing.actions.ReadyToTest()]), {}


class TestEstimatorTopics(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        rclpy.init()
        cls.node = rclpy.create_node("kvark_launch_test")

    @classmethod
    def tearDownClass(cls):
        cls.node.destroy_node()
        rclpy.shutdown()

    def _spin(self, seconds: float, until=lambda: False) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not until():
            rclpy.spin_once(self.node, timeout_sec=0.001)

    def test_outputs_for_a_joint_state_and_command_stream(self):
        node = self.node
        got = {"torque": [], "wrench": [], "stddev": [], "covariance": [], "contact": [], "contact_state": [],
               "diagnostics": []}
        for key, kind, topic in (("torque", JointState, f"{OUT}/external_joint_torque"),
                                 ("wrench", WrenchStamped, f"{OUT}/external_wrench"),
                                 ("stddev", Float64MultiArray, f"{OUT}/external_joint_torque_stddev"),
                                 ("covariance", Float64MultiArray, f"{OUT}/external_wrench_covariance"),
                                 ("contact", Bool, f"{OUT}/contact"),
                                 ("contact_state", JointState, f"{OUT}/contact_state"),
                                 ("diagnostics", DiagnosticArray, "/diagnostics")):
            node.create_subscription(kind, topic, got[key].append, 100)
        states = node.create_publisher(JointState, "/joint_states", qos_profile_sensor_data)
        commands = node.create_publisher(Float64MultiArray, "/effort_commands", qos_profile_sensor_data)
        self._spin(30.0, lambda: states.get_subscription_count() > 0 and commands.get_subscription_count() > 0)
        self.assertGreater(states.get_subscription_count(), 0, "the estimator never subscribed to joint_states")

        robot = _robot()
        stream = synthetic_stream(robot, 2.0, seed=5)
        names = list(robot.joint_names)
        start = node.get_clock().now().nanoseconds
        for k in range(len(stream.stamp)):
            ns = start + int(round(stream.stamp[k] * 1e9))
            state = JointState(name=names, position=stream.q[k].tolist(), velocity=stream.qd[k].tolist())
            state.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            states.publish(state)
            command = Float64MultiArray(data=stream.tau_m[k].tolist())
            command.layout.dim = [MultiArrayDimension(label=",".join(names), size=7, stride=7)]
            commands.publish(command)
            self._spin(0.002)
        self._spin(5.0, lambda: len(got["diagnostics"]) > 1)

        self.assertGreater(len(got["torque"]), 100)
        for msg in got["torque"]:
            self.assertEqual(list(msg.name), names)
            self.assertTrue(np.isfinite(msg.effort).all())
        self.assertGreater(len(got["wrench"]), 100)
        self.assertEqual({m.header.frame_id for m in got["wrench"]}, {"panda_link0"})
        self.assertTrue(all(len(m.data) == 7 for m in got["stddev"]) and got["stddev"])
        self.assertTrue(all(len(m.data) == 36 for m in got["covariance"]) and got["covariance"])
        self.assertTrue(got["contact"])
        self.assertTrue(got["contact_state"])
        self.assertEqual({tuple(m.name) for m in got["contact_state"]}, {("contact", "collision")})
        statuses = {s.name: s for array in got["diagnostics"] for s in array.status}
        [model] = [s for name, s in statuses.items() if name.endswith("/kvark_estimator: model")]   # fully qualified
        self.assertEqual(model.level, DiagnosticStatus.OK)


@launch_testing.post_shutdown_test()
class TestEstimatorShutdown(unittest.TestCase):

    def test_exit_code(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info)
