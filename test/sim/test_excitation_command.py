"""``kvark excitation``: the simulator's optimised trajectory for a real arm, within its limits, as a CSV, a
trajectory_msgs/JointTrajectory in YAML and a bag of it; without MuJoCo."""
from __future__ import annotations

import csv
import importlib
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from kvark_ros.cli import main
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io.bag_messages import read_messages
from kvark_ros.io.cdr_messages import JOINT_TRAJECTORY
from kvark_ros.io.common import typestore

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "panda.yaml"
CENTRE = [0.0, -0.6, 0.0, -2.2, 0.0, 1.6, 0.8]      # rad: the Panda's usual ready pose, well inside its limits
# A short, cheap optimisation: the limits hold whatever it finds (the final scaling makes them hold).
FAST = ["--duration", "6", "--ramp", "1", "--population", "8", "--generations", "4", "--rate", "50"]


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("excitation") / "panda"
    assert main(["excitation", "--config", str(CONFIG), "--centre", ",".join(map(str, CENTRE)), "--half-range",
                 "0.4", "--acceleration", "2", "--velocity-scale", "0.3", *FAST, "--out", str(out)]) == 0
    return out


def _table(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as stream:
        rows = list(csv.reader(stream))
    return rows[0], np.array(rows[1:], dtype=float)


def test_the_csv_keeps_within_the_window_the_velocity_and_the_acceleration(written):
    """Every row within centre ± 0.4 rad, 0.3 × the URDF's velocity limits and 2 rad/s², starting and ending at rest
    at the centre; q̇ is the derivative of q (central differences at 50 Hz agree to 2 % of the velocity bound: the
    harmonics are at most 2 Hz, so the differences' error is below (2π·2/50)²/6 ≈ 1 %)."""
    header, table = _table(written / "excitation.csv")
    names = list(load_config(CONFIG).joint_names)
    assert header == ["time", *[f"{kind}:{name}" for kind in ("q", "qd", "qdd") for name in names]]
    time, q, qd, qdd = table[:, 0], table[:, 1:8], table[:, 8:15], table[:, 15:22]
    assert time[0] == 0.0 and time[-1] == pytest.approx(6.0) and np.allclose(np.diff(time), 0.02)
    velocity = 0.3 * np.array(RobotModel(str(load_config(CONFIG).urdf), names, "panda_link8").model.velocityLimit)
    assert (np.abs(q - CENTRE) <= 0.4).all() and (np.abs(qd) <= velocity).all() and (np.abs(qdd) <= 2.0).all()
    assert np.abs(q - CENTRE).max() > 0.05, "it moves"
    for row in (0, -1):
        assert np.allclose(q[row], CENTRE, atol=1e-12) and np.allclose(qd[row], 0.0, atol=1e-12)
    assert np.abs(np.gradient(q, time, axis=0)[1:-1] - qd[1:-1]).max() < 0.02 * velocity.max()


def test_the_yaml_is_a_joint_trajectory_a_controller_takes(written):
    """Every key of the YAML is a field of trajectory_msgs/JointTrajectory with a value of its type (set on the
    real message class, which checks them as ``ros2 topic pub`` sets them); the points are the CSV's rows, the
    first ``--start-delay`` (5 s) after the message."""
    if not (sys.platform == "linux" and platform.machine() == "x86_64"):
        pytest.skip("the ROS 2 Jazzy wheels exist for linux x86_64 only")
    from trajectory_msgs.msg import JointTrajectory

    def fill(message, values: dict) -> None:
        """Set ``values`` on ``message`` field by field, as ros2cli's set_message_fields does."""
        types = message.get_fields_and_field_types()
        for name, value in values.items():
            assert name in types, name
            if isinstance(value, dict):
                fill(getattr(message, name), value)
            elif types[name].startswith("sequence<") and "/" in types[name]:
                package, kind = types[name][len("sequence<"):-1].split("/")
                item_class = getattr(importlib.import_module(f"{package}.msg"), kind)
                items = []
                for item in value:
                    items.append(item_class())
                    fill(items[-1], item)
                setattr(message, name, items)
            else:
                setattr(message, name, value)

    document = yaml.safe_load((written / "joint_trajectory.yaml").read_text())
    message = JointTrajectory()
    fill(message, document)
    _, table = _table(written / "excitation.csv")
    assert list(message.joint_names) == list(load_config(CONFIG).joint_names) and len(message.points) == len(table)
    first, last = message.points[0], message.points[-1]
    assert (first.time_from_start.sec, first.time_from_start.nanosec) == (5, 0)
    assert last.time_from_start.sec + last.time_from_start.nanosec * 1e-9 == pytest.approx(11.0)
    assert np.array_equal([list(p.positions) for p in message.points], table[:, 1:8])
    assert np.array_equal([list(p.accelerations) for p in message.points], table[:, 15:22])


def test_the_bag_holds_the_same_trajectory_on_the_controllers_topic(written):
    messages = read_messages(written / "joint_trajectory",
                             {"/joint_trajectory_controller/joint_trajectory": ("--topic", {JOINT_TRAJECTORY})})
    assert len(messages) == 1
    message = typestore().deserialize_cdr(messages.data[0], JOINT_TRAJECTORY)
    _, table = _table(written / "excitation.csv")
    assert np.array_equal([p.velocities for p in message.points], table[:, 8:15])
    assert [p.time_from_start.sec for p in message.points[:1]] == [5]


def test_a_centre_outside_the_limits_and_a_wrong_count_are_refused_in_one_line(tmp_path, capsys):
    bad = [*CENTRE[:3], -3.5, *CENTRE[4:]]                     # panda_joint4 lies in [-3.07, -0.07] rad
    assert main(["excitation", "--config", str(CONFIG), "--centre", ",".join(map(str, bad)), *FAST,
                 "--out", str(tmp_path / "x")]) == 1
    assert "--centre: panda_joint4 = -3.5 rad is not within its URDF limits × --position-scale" in \
        capsys.readouterr().err
    assert main(["excitation", "--config", str(CONFIG), "--centre", "0,0", *FAST, "--out", str(tmp_path / "x")]) == 1
    assert "give one number or 7 comma-separated" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_command_needs_no_mujoco():
    """It lives with the trajectory it drives (sim/), but only ``simulate`` needs the [sim] extra's MuJoCo: its
    parser and module load without importing it, and the command is listed whether MuJoCo is there or not."""
    code = ("import sys\n"
            "from kvark_ros.cli import COMMANDS, build_parser\n"
            "build_parser('excitation')\n"
            "assert 'mujoco' not in sys.modules, 'excitation imported mujoco'\n"
            "assert [c.name for c in COMMANDS if c.name == 'excitation']\n")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    import kvark_ros.cli as cli
    assert "excitation" in [command.name for command in cli.available_commands()]
