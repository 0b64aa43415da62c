"""What ``kvark init --driver`` sets for the ROS 2 drivers labs run: the torque source and how it is measured, the
frames, the topic and the wrench's base frame, as each driver publishes them (docs/ros.md, *Drivers*).

- ``franka`` (franka_ros2, FR3 and Panda): the joint_state_broadcaster publishes ``franka/joint_states`` at the
  controller manager's 1 kHz with the measured link-side torque τ_J (gravity included) in the effort field; the
  ``joint_states`` topic beside it is joint_state_publisher's 30 Hz merge with the gripper. The flange is
  ``<arm>_link8``, the ee frame ``<arm>_hand_tcp`` where the URDF has the hand.
- ``ur`` (ur_robot_driver, e-Series): ``joint_states`` at 500 Hz whose effort is the motor current in A, unless the
  driver reports torque (``use_currents_as_efforts:=false`` where the driver and PolyScope have it): the effort
  needs ``--effort-scale`` (N·m/A per joint, or 1 for torques). Flange and ee frame ``tool0`` (the tool flange
  UR's set_payload refers to); the wrench's base frame UR's ``base``.
- ``lbr`` (lbr_fri_ros2_stack, KUKA LBR iiwa/Med): ``/<robot>/joint_states`` (the driver runs in the namespace of
  its robot name, ``lbr``, the prefix of its joints) at the controller manager's rate (100 Hz), the measured torque
  in the effort field; flange and ee frame ``<robot>_link_ee``. The topic is absolute, so that the commands read a
  bag recorded from the driver with the same file; the node may run in that namespace too.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ["DRIVERS", "Driver"]


def _prefix(joints: Sequence[str], suffix: str) -> str:
    """``fr3`` of ``fr3_joint1`` (suffix ``_joint1``), ``lbr`` of ``lbr_A1``; '' when the first joint lacks it."""
    first = joints[0] if joints else ""
    return first[: -len(suffix)] if first.endswith(suffix) else ""


def _franka_frames(joints: Sequence[str], has_frame: Callable[[str], bool]) -> tuple[str | None, str | None]:
    arm = _prefix(joints, "_joint1")
    ee = f"{arm}_hand_tcp" if has_frame(f"{arm}_hand_tcp") else f"{arm}_link8"
    return ee, f"{arm}_link8"


def _ur_frames(joints: Sequence[str], has_frame: Callable[[str], bool]) -> tuple[str | None, str | None]:
    return "tool0", "tool0"


def _lbr_frames(joints: Sequence[str], has_frame: Callable[[str], bool]) -> tuple[str | None, str | None]:
    link = f"{_prefix(joints, '_A1')}_link_ee"
    return (link, link) if has_frame(link) else (None, None)


def _lbr_topics(joints: Sequence[str]) -> dict[str, Any]:
    return {"input.joint_states_topic": f"/{_prefix(joints, '_A1') or 'lbr'}/joint_states"}


@dataclass(frozen=True)
class Driver:
    """A driver's settings: config values (``topics``: more of them from the joint names), a rule for the frames
    from the joints and the URDF's frames (None: the chain's last link, as without a driver), whether the effort
    needs a scale, and a note per key for the file."""

    name: str
    values: dict[str, Any]
    frames: Callable[[Sequence[str], Callable[[str], bool]], tuple[str | None, str | None]]
    topics: Callable[[Sequence[str]], dict[str, Any]] = lambda joints: {}
    base_frame: str = ""                          # wrench.base_frame when the URDF has it
    needs_effort_scale: bool = False
    notes: dict[str, str] = field(default_factory=dict)


DRIVERS: dict[str, Driver] = {
    "franka": Driver(
        "franka", {"robot_model.torque_measurement": "link_torque_sensor",
                   "input.torque_source": "joint_states_effort", "input.joint_states_topic": "franka/joint_states"},
        _franka_frames,
        notes={"input.joint_states_topic": "franka_ros2: the joint_state_broadcaster's 1 kHz stream with the "
                                           "measured link-side torque tau_J in effort; joint_states is the 30 Hz "
                                           "merge with the gripper. Relative: it follows the node's namespace.",
               "wrench.convention": "Franka's O_F_ext_hat_K is applied_by_robot; this file keeps kvark's sign."}),
    "ur": Driver(
        "ur", {"robot_model.torque_measurement": "motor_current", "input.torque_source": "joint_states_effort",
               "input.joint_states_topic": "joint_states"},
        _ur_frames, base_frame="base", needs_effort_scale=True,
        notes={"input.effort_scale": "ur_robot_driver publishes the motor current (A) as effort: N·m/A per joint "
                                     "(the robot's own: actual_current_as_torque / actual_current on PolyScope >= "
                                     "5.23), or 1 where the driver reports torque (use_currents_as_efforts: false).",
               "wrench.base_frame": "UR's base frame, turned 180 degrees about z from base_link."}),
    "lbr": Driver(
        "lbr", {"robot_model.torque_measurement": "link_torque_sensor", "input.torque_source": "joint_states_effort"},
        _lbr_frames, _lbr_topics,
        notes={"input.joint_states_topic": "lbr_fri_ros2_stack: the driver's joint states in its namespace (its "
                                           "robot name), the measured torque in effort, absolute so that a bag "
                                           "recorded from it reads with this file. Loosen the driver's torque "
                                           "filter (measured_torque_tau, or measured_torque_cutoff_frequency in "
                                           "older releases) or tau_m lags."}),
}
