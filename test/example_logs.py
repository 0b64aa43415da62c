"""The committed robot logs of the README's bring-your-own-robot walk-through (``examples/``), made physical.

Each log is what an arm's own logger writes while it follows a smooth multi-sine excitation and touches
nothing: the measured torque is the rigid-body inverse dynamics of the robot's URDF (pinocchio RNEA) with
what a real arm adds that its URDF lacks, so that ``kvark diagnose`` has something to find and ``kvark
replay --ground-truth zero`` something to judge:

- UR5, RTDE CSV at 100 Hz with jittered stamps: an unmodelled 1 kg tool 6 cm past ``tool0``, Coulomb
  (tanh, 1.5-4 N·m) and viscous friction, commanded torque ``target_moment`` and motor current
  ``actual_current`` = torque / (torque constant × gear ratio);
- Panda, libfranka-style text log at 1 kHz with three lost packets: a 0.5 kg part held in the hand
  (15 cm past ``panda_link8``), small Coulomb friction in the link-side torque ``tau_J``.

Two logs per robot (different seeds): the first to diagnose and train on, the second to replay.
``python test/example_logs.py`` rewrites ``examples/``; ``tools/test_import_robot_logs.py`` checks the files are these.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import yaml

from kvark_ros.core.estimation.payload import Payload
from kvark_ros.core.estimation.robot_model import RobotModel

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
UR_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
             "wrist_3_joint")
PANDA_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
UR_HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
PANDA_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
UR_TORQUE_CONSTANTS = (13.5, 13.5, 13.5, 9.8, 9.8, 9.8)   # N·m/A at the joint (illustrative)
UR_COULOMB = np.array([4.0, 4.0, 3.0, 1.5, 1.5, 1.5])    # N·m
PANDA_COULOMB = np.array([0.4, 0.4, 0.3, 0.3, 0.15, 0.15, 0.1])
UR_TOOL = Payload(1.0, (0.0, 0.0, 0.06), (2e-3, 2e-3, 1e-3, 0.0, 0.0, 0.0))
PANDA_TOOL = Payload(0.5, (0.0, 0.0, 0.15), (5e-4, 5e-4, 5e-4, 0.0, 0.0, 0.0))      # a part in the hand
FILES = {"ur5_rtde_1.csv": ("ur", 20.0, 1), "ur5_rtde_2.csv": ("ur", 10.0, 2),
         "panda_log_1.txt": ("panda", 8.0, 3), "panda_log_2.txt": ("panda", 4.0, 4)}
UR_MAPPING = {
    "time": {"column": "timestamp", "unit": "s"},
    "first_index": 0,
    "position": "actual_q_{i}",
    "velocity": "actual_qd_{i}",
    "effort": {"pattern": "actual_current_{i}", "scale": list(UR_TORQUE_CONSTANTS)},
    "command": "target_moment_{i}",
}
PANDA_MAPPING = {
    "time": {"column": "time", "unit": "ms"},
    "first_index": 1,
    "joints": list(PANDA_JOINTS),
    "position": "q{i}",
    "velocity": "dq{i}",
    "effort": "tau_J{i}",
}
UR_MAPPING_HEADER = """\
# Column mapping of `kvark import` for a Universal Robots RTDE log (rtde_data_recording / record.py CSV).
# Joint names come from --joints or --config (robot_model.joint_names); {i} counts from first_index.
# actual_current is the motor current (A): the scale turns it into joint torque, N·m/A per joint.
# These factors are illustrative: take your arm's (torque constant x gear ratio) or leave effort out.
# target_moment (the controller's commanded torque) becomes /effort_commands, the torque kvark uses.
"""
PANDA_MAPPING_HEADER = """\
# Column mapping of `kvark import` for a libfranka-style text log: whitespace separated, one header row,
# time = franka::RobotState::time in ms, q/dq = q and dq, tau_J = the measured link-side joint torque.
# tau_J becomes the effort of /joint_states; with no command column kvark takes tau_m from it
# (set input.torque_source: joint_states_effort to say so). A column tau_ext_hat_filtered{i} is
# Franka's own estimate, not a measurement: do not map it as external_torque (the ground truth).
"""


def _motion(t: np.ndarray, home: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Multi-sine q, q̇, q̈ (T, n) about ``home``: 3 sines per joint, 0.1-0.5 Hz, at most 0.6 rad in all."""
    rng = np.random.default_rng(seed)
    n = len(home)
    frequency = rng.uniform(0.1, 0.5, (3, n))
    amplitude = rng.uniform(0.1, 0.2, (3, n))
    phase = rng.uniform(0.0, 2.0 * np.pi, (3, n))
    omega = 2.0 * np.pi * frequency
    arg = omega[None] * t[:, None, None] + phase[None]
    q = home + np.sum(amplitude * (np.sin(arg) - np.sin(phase)), axis=1)      # starts at home
    qd = np.sum(amplitude * omega * np.cos(arg), axis=1)
    qdd = -np.sum(amplitude * omega ** 2 * np.sin(arg), axis=1)
    return q, qd, qdd


def _torque(robot: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, coulomb: np.ndarray,
            viscous: float) -> np.ndarray:
    """τ (T, n) = RNEA of the real arm (URDF + tool) + Coulomb tanh(q̇/0.02) + viscous q̇."""
    rigid = np.array([robot.inverse_dynamics(q[k], qd[k], qdd[k]) for k in range(len(q))])
    return rigid + coulomb * np.tanh(qd / 0.02) + viscous * qd


def ur_log(seconds: float, seed: int) -> str:
    """A UR5 RTDE CSV at 100 Hz (module docstring)."""
    rng = np.random.default_rng(seed)
    rows = int(round(seconds * 100))
    elapsed = np.arange(rows) * 0.01 + rng.uniform(-5e-4, 5e-4, rows)
    q, qd, qdd = _motion(elapsed, UR_HOME, seed)
    real = RobotModel("example-robot-data:ur5", UR_JOINTS, "tool0", "tool0", UR_TOOL)
    tau = _torque(real, q, qd, qdd, UR_COULOMB, 1.0)
    moment = tau + 0.05 * rng.standard_normal(tau.shape)
    current = (tau + 0.3 * rng.standard_normal(tau.shape)) / np.array(UR_TORQUE_CONSTANTS)
    q_meas, qd_meas = q + 1e-5 * rng.standard_normal(q.shape), qd + 1e-3 * rng.standard_normal(q.shape)
    header = ["timestamp"] + [f"{name}_{i}" for name in ("actual_q", "actual_qd", "actual_current", "target_moment")
                              for i in range(6)]
    lines = [",".join(header)]
    for k in range(rows):
        lines.append(",".join([f"{4502.125 + elapsed[k]:.6f}"] + [f"{v:.5f}" for v in q_meas[k]]
                              + [f"{v:.4f}" for v in qd_meas[k]] + [f"{v:.4f}" for v in current[k]]
                              + [f"{v:.3f}" for v in moment[k]]))
    return "\n".join(lines) + "\n"


def panda_log(seconds: float, seed: int) -> str:
    """A libfranka-style text log at 1 kHz with three lost packets (module docstring)."""
    rng = np.random.default_rng(seed)
    rows = int(round(seconds * 1000))
    time_ms = np.delete(61_000 + np.arange(rows + 3), [rows // 4, rows // 2, rows // 2 + 1])
    q, qd, qdd = _motion((time_ms - time_ms[0]) / 1000.0, PANDA_HOME, seed)
    real = RobotModel("example-robot-data:panda", PANDA_JOINTS, "panda_hand_tcp", "panda_link8", PANDA_TOOL)
    tau = _torque(real, q, qd, qdd, PANDA_COULOMB, 0.1) + 0.05 * rng.standard_normal(q.shape)
    q_meas, qd_meas = q + 1e-5 * rng.standard_normal(q.shape), qd + 2e-3 * rng.standard_normal(q.shape)
    header = ["time"] + [f"{name}{i}" for name in ("q", "dq", "tau_J") for i in range(1, 8)]
    lines = [" ".join(header)]
    for k in range(rows):
        lines.append(" ".join([str(time_ms[k])] + [f"{v:.5f}" for v in q_meas[k]] + [f"{v:.3f}" for v in qd_meas[k]]
                              + [f"{v:.2f}" for v in tau[k]]))
    return "\n".join(lines) + "\n"


def write_examples(folder: Path) -> None:
    """The committed examples: four logs and the two mappings."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, (robot, seconds, seed) in FILES.items():
        (folder / name).write_text((ur_log if robot == "ur" else panda_log)(seconds, seed))
    for name, header, mapping in (("ur_rtde_mapping.yaml", UR_MAPPING_HEADER, UR_MAPPING),
                                  ("franka_log_mapping.yaml", PANDA_MAPPING_HEADER, PANDA_MAPPING)):
        (folder / name).write_text(header + yaml.safe_dump(mapping, sort_keys=False, default_flow_style=None))


if __name__ == "__main__":
    write_examples(Path(sys.argv[1]) if len(sys.argv) > 1 else EXAMPLES)
