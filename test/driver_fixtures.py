"""What the ROS 2 drivers publish, made from what this project has: message fixtures for the driver recipes' tests.

No driver runs here, so each driver's topics are written as it publishes them (docs/ros.md, *Drivers*), from the
committed simulated Panda bag or from the nominal model's torques along an excitation (``tools.synthetic``):

- franka_ros2: ``/franka/joint_states`` at 1 kHz (the controller manager's rate) with the measured link-side
  torque τ_J in the effort field, and ``/joint_states``, joint_state_publisher's 30 Hz merge with the gripper's
  two finger joints; the 500 Hz simulated bag is brought to 1 kHz by linear interpolation between samples;
- ur_robot_driver: ``/joint_states`` at 500 Hz whose effort is the motor current in A, the torque divided by a
  per-joint torque constant (N·m/A);
- lbr_fri_ros2_stack: ``/lbr/joint_states`` at the controller manager's 100 Hz with the measured torque in effort.

The KUKA arm is :func:`lbr_urdf`: an LBR iiwa 14 as lbr_description names it (joints ``lbr_A1``…``lbr_A7``, links
``lbr_link_0``…``lbr_link_7`` and ``lbr_link_ee``) with KUKA's published kinematic lengths, axis directions and
joint limits and simple cylinder inertias: a stand-in for its URDF (not committed here), whose dynamics are only as
good as the test needs (the node and replay run the same model on it).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer

from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io import read_run
from kvark_ros.io.common import JOINT_STATE, typestore
from kvark_ros.tools.synthetic import synthetic_stream

START = 1000.0       # s: the fixtures' first stamp, as a driver stamps with its clock (not 0)

# UR10e drive gains identified by Mamedov et al. 2020 (N·m/A), used as the fixture's torque constants.
UR_TORQUE_CONSTANTS = (10.0, 10.6956, 8.4566, 9.0029, 9.48, 10.1232)
UR_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
             "wrist_3_joint")
LBR_JOINTS = tuple(f"lbr_A{k}" for k in range(1, 8))
# LBR iiwa 14 R820 data sheet: axis heights (m) between joints, limits (deg, deg/s, N·m).
_LBR_OFFSETS = (0.1575, 0.2025, 0.2045, 0.2155, 0.1845, 0.2155, 0.081)
_LBR_AXES = ("0 0 1", "0 1 0", "0 0 1", "0 -1 0", "0 0 1", "0 1 0", "0 0 1")
_LBR_LIMITS = ((170, 85, 320), (120, 85, 320), (170, 100, 176), (120, 75, 176), (170, 130, 110), (120, 135, 40),
               (175, 135, 40))
_LBR_MASSES = (4.0, 4.0, 3.0, 2.7, 1.7, 1.8, 0.3)


def _cylinder(mass: float, radius: float, length: float) -> str:
    """A URDF <inertial> of a solid cylinder along z with its centre half way up."""
    side = mass * (3 * radius**2 + length**2) / 12
    return (f'<inertial><origin xyz="0 0 {length / 2:.4f}"/><mass value="{mass}"/><inertia ixx="{side:.6f}" '
            f'ixy="0" ixz="0" iyy="{side:.6f}" iyz="0" izz="{mass * radius**2 / 2:.6f}"/></inertial>')


def lbr_urdf() -> str:
    """The KUKA LBR iiwa 14 stand-in (module docstring) as URDF text."""
    parts = ['<link name="lbr_link_0">' + _cylinder(5.0, 0.1, 0.15) + "</link>"]
    for k in range(7):
        degrees, speed, torque = _LBR_LIMITS[k]
        length = _LBR_OFFSETS[k + 1] if k < 6 else 0.045
        parts.append(
            f'<joint name="lbr_A{k + 1}" type="revolute"><parent link="lbr_link_{k}"/><child link="lbr_link_{k + 1}"/>'
            f'<origin xyz="0 0 {_LBR_OFFSETS[k]}"/><axis xyz="{_LBR_AXES[k]}"/>'
            f'<limit lower="{-math.radians(degrees):.6f}" upper="{math.radians(degrees):.6f}" '
            f'velocity="{math.radians(speed):.6f}" effort="{torque}"/></joint>'
            f'<link name="lbr_link_{k + 1}">{_cylinder(_LBR_MASSES[k], 0.06, length)}</link>')
    parts.append('<joint name="lbr_joint_ee" type="fixed"><parent link="lbr_link_7"/><child link="lbr_link_ee"/>'
                 '<origin xyz="0 0 0.045"/></joint><link name="lbr_link_ee"/>')
    return f'<?xml version="1.0"?><robot name="lbr">{"".join(parts)}</robot>'


def _joint_state(ns: int, names, position, velocity, effort) -> bytes:
    """A JointState stamped ``ns``, serialised."""
    types = typestore().types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
        sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id="")
    message = types[JOINT_STATE](header=header, name=list(names), position=np.asarray(position, dtype=float),
                                 velocity=np.asarray(velocity, dtype=float), effort=np.asarray(effort, dtype=float))
    return bytes(typestore().serialize_cdr(message, JOINT_STATE))


def _write(out: Path, messages: list[tuple[int, str, bytes]]) -> Path:
    """A bag at ``out`` of JointState messages (log ns, topic, CDR), in log order."""
    with Writer(out, version=9) as writer:
        connections: dict[str, object] = {}
        for ns, topic, raw in sorted(messages, key=lambda message: message[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, JOINT_STATE, typestore=typestore())
            writer.write(connections[topic], ns, raw)
    return out


def franka_bag(source: Path, out: Path, seconds: float = 2.0) -> Path:
    """franka_ros2's topics (module docstring) from ``source`` (a simulated Panda bag with /joint_states and its
    /effort_commands at 500 Hz), its first ``seconds``: a rosbag2 bag at ``out``."""
    names = [f"panda_joint{k}" for k in range(1, 8)]
    run = read_run(source, names)
    states, commands = run.joint_states, run.commands
    rows = np.flatnonzero(states.stamp - states.stamp[0] <= seconds)
    stamp, q, qd = states.stamp[rows], states.position[rows], states.velocity[rows]
    tau = commands.effort[np.searchsorted(commands.stamp, stamp)]         # each state's own command, as τ_J
    fine = np.arange(2 * len(stamp) - 1) / 2.0                            # 1 kHz: midpoints between samples
    coarse = np.arange(len(stamp))
    stamps = START + np.interp(fine, coarse, stamp)
    q, qd, tau = (np.column_stack([np.interp(fine, coarse, column) for column in values.T])
                  for values in (q, qd, tau))
    messages, last_merge = [], -math.inf
    for k, seconds_k in enumerate(stamps):
        ns = int(round(seconds_k * 1e9))
        messages.append((ns, "/franka/joint_states", _joint_state(ns, names, q[k], qd[k], tau[k])))
        if seconds_k - last_merge >= 1 / 30 - 1e-9:                       # joint_state_publisher's 30 Hz
            last_merge = seconds_k
            messages.append((ns + 100_000, "/joint_states", _joint_state(
                ns, names + ["panda_finger_joint1", "panda_finger_joint2"], [*q[k], 0.04, 0.04], [*qd[k], 0.0, 0.0],
                [*tau[k], 0.0, 0.0])))
    return _write(out, messages)


def synthetic_driver_bag(robot: RobotModel, out: Path, topic: str, rate: float, seconds: float, seed: int,
                         torque_constants: tuple[float, ...] | None = None) -> Path:
    """A driver's joint states (``topic`` at ``rate`` Hz for ``seconds``, stamped from ``START``) along an
    excitation of ``robot`` with the nominal model's torque (``tools.synthetic``), divided by ``torque_constants``
    (N·m/A) where given: a motor current in A."""
    stream = synthetic_stream(robot, seconds, rate=rate, seed=seed)
    effort = stream.tau_m if torque_constants is None else stream.tau_m / np.asarray(torque_constants)
    names = list(robot.joint_names)
    messages = []
    for k, seconds_k in enumerate(START + stream.stamp):
        ns = int(round(seconds_k * 1e9))
        messages.append((ns, topic, _joint_state(ns, names, stream.q[k], stream.qd[k], effort[k])))
    return _write(out, messages)


__all__ = ["franka_bag", "lbr_urdf", "synthetic_driver_bag", "UR_TORQUE_CONSTANTS", "UR_JOINTS", "LBR_JOINTS", "START"]
