"""The simulated robots: joints, frames, home pose, limits the URDF lacks, controller gains.

The URDFs come from the ``example-robot-data`` package (docs/method.md §10). Everything here is what a
robotics engineer sets up once per arm and never per run.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache

import numpy as np

from kvark_ros.core.estimation.payload import Payload
from kvark_ros.core.estimation.robot_model import RobotModel, resolve_urdf


@cache
def urdf_xml(spec: str) -> str:
    """URDF text of a path or ``example-robot-data:<robot>``, read once per process (finding the
    example-robot-data file scans the installed package)."""
    return resolve_urdf(spec)


def cylinder_payload(mass: float, radius: float, length: float, com_z: float) -> Payload:
    """Solid cylinder along the flange z axis: a stand-in for a grasped part or a weight."""
    side = mass * (3.0 * radius**2 + length**2) / 12.0
    return Payload(mass, (0.0, 0.0, com_z), (side, side, 0.5 * mass * radius**2, 0.0, 0.0, 0.0))


@dataclass(frozen=True)
class RobotSetup:
    """One arm as the simulator uses it.

    home: joint angles (rad) where contact runs start and holds happen.
    acceleration_limit: rad/s², for excitation design (URDFs carry none).
    excitation_half_range: rad, optional window about ``home`` that replaces the URDF range
        midpoint for excitation design (stand-in for collision avoidance on arms whose URDF
        allows ±2π).
    kp, kd: joint PD gains of the inertia-shaped tracking controller, 1/s² and 1/s
        (critically damped, bandwidth √kp rad/s).
    payload: the default payload of the ``payload`` scenario (in the flange frame).
    push_link: link the ``collision`` scenario pushes.
    """

    name: str
    urdf: str
    joint_names: tuple[str, ...]
    ee_frame: str
    flange_frame: str
    home: tuple[float, ...]
    acceleration_limit: tuple[float, ...]
    kp: tuple[float, ...]
    kd: tuple[float, ...]
    payload: Payload
    push_link: str
    excitation_half_range: tuple[float, ...] | None = None

    @property
    def n(self) -> int:
        """Number of actuated joints."""
        return len(self.joint_names)

    def nominal_model(self, payload: Payload | None = None) -> RobotModel:
        """The pinocchio model the estimators use (optionally with a payload)."""
        return RobotModel(urdf_xml(self.urdf), self.joint_names, self.ee_frame, self.flange_frame, payload)

    def home_array(self) -> np.ndarray:
        """``home`` as an (n,) float array, rad."""
        return np.array(self.home, dtype=float)


ROBOTS: dict[str, RobotSetup] = {
    "panda": RobotSetup(
        name="panda",
        urdf="example-robot-data:panda",
        joint_names=tuple(f"panda_joint{i}" for i in range(1, 8)),
        ee_frame="panda_hand_tcp",
        flange_frame="panda_link8",
        home=(0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4),
        # Franka's published joint acceleration limits.
        acceleration_limit=(15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0),
        kp=(2500.0,) * 7,
        kd=(100.0,) * 7,
        payload=cylinder_payload(2.0, 0.04, 0.08, 0.14),
        push_link="panda_link5",
    ),
    "ur5": RobotSetup(
        name="ur5",
        urdf="example-robot-data:ur5",
        joint_names=("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                     "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"),
        ee_frame="tool0",
        flange_frame="tool0",
        home=(0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0),
        # Moderate values below what UR5 drives reach; UR publishes no per-joint limit.
        acceleration_limit=(8.0, 8.0, 10.0, 15.0, 15.0, 15.0),
        kp=(1600.0,) * 6,
        kd=(80.0,) * 6,
        payload=cylinder_payload(2.0, 0.04, 0.08, 0.05),
        push_link="forearm_link",
        excitation_half_range=(1.5, 1.2, 1.2, 1.5, 1.5, 1.5),
    ),
}
# UR10-class (UR10/UR10e reach 1.3 m, 10-12.5 kg payload): the UR5's joints, frames, home, gains and push link at
# twice its link masses; accelerations below the UR5's on the base joints (longer, heavier links and 330 N·m drives;
# UR publishes no limit).
ROBOTS["ur10"] = replace(ROBOTS["ur5"], name="ur10", urdf="example-robot-data:ur10",
                         acceleration_limit=(5.0, 5.0, 8.0, 12.0, 12.0, 12.0))


def robot_setup(name: str) -> RobotSetup:
    """The setup of ``name`` (``panda``, ``ur5`` or ``ur10``); ValueError names the known robots."""
    try:
        return ROBOTS[name]
    except KeyError:
        raise ValueError(f"unknown robot {name!r}; known: {', '.join(sorted(ROBOTS))}") from None
