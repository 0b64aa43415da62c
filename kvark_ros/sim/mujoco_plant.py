"""The simulated robot: MuJoCo built from the same URDF as the nominal model, plus a plant file.

MuJoCo and pinocchio are two independent dynamics engines; on the bare URDF they agree to
rounding error, so every difference an estimator sees comes from the plant file (friction,
armature, link inertia, tool, payload, drive gain, offsets, ripple, drifts) or from external forces.
The rigid body is compiled from ``true_model.true_urdf`` (payload included), the URDF the oracle
can load in pinocchio.

Only inertias matter: visual and collision geometry are stripped, joints that are not
simulated (the Panda's fingers) become fixed (pinocchio locks them at 0 too), URDF joint
damping/friction and joint limits are dropped, gravity is −9.81 m/s² along base z, and the
physics step is 1 ms (semi-implicit Euler).

Joint-level plant effects are applied as generalized forces on every physics step from the state
at the start of the step. Smooth friction (Gaz sigmoid, viscous) is explicit; dry
(Coulomb/Stribeck) friction is MuJoCo's ``dof_frictionloss`` constraint, which also holds the
joint at rest (stiction) and is stable for any friction level.

The plant clock ``MujocoPlant.time`` (s since the robot was switched on) drives the friction and
torque-offset drifts: ``reset`` sets it (0 unless told: a cold robot) and every step advances it
by ``PHYSICS_DT``.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import numpy.typing as npt

from kvark_ros.sim.plant import (PlantSpec, actuator_torque, dry_friction_level, friction_drift_factor,
                                 friction_torque, torque_offset_drift)
from kvark_ros.sim.robots import RobotSetup
from kvark_ros.sim.true_model import true_urdf

FloatArray = npt.NDArray[np.float64]
PHYSICS_DT = 1e-3          # s
GRAVITY = (0.0, 0.0, -9.81)  # m/s², base frame
# Dry friction as a near-hard constraint: time constant 2·dt and impedance ≈ 1 keep the creep
# velocity under a held load around 1e-3 rad/s (MuJoCo's defaults let it creep ~0.05 rad/s).
_DRY_FRICTION_SOLREF = (2.0 * PHYSICS_DT, 1.0)
_DRY_FRICTION_SOLIMP = (0.99, 0.999, 0.001, 0.5, 2.0)


@dataclass(frozen=True)
class AppliedWrench:
    """An external wrench on one body: force (3,) N and torque (3,) N·m about ``point`` (3,) m,
    all in base (world) coordinates. This is ``F_ext`` of docs/method.md §1.2 at ``point``."""

    body: str
    point: FloatArray
    force: FloatArray
    torque: FloatArray


def _strip_urdf(urdf: str, joint_names: Sequence[str]) -> str:
    """URDF with inertias and kinematics only, other movable joints fixed, MuJoCo options added."""
    root = ET.fromstring(urdf)
    for tag in ("transmission", "gazebo", "mujoco"):
        for element in root.findall(tag):
            root.remove(element)
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for element in link.findall(tag):
                link.remove(element)
    for joint in root.findall("joint"):
        for tag in ("dynamics", "safety_controller", "mimic", "calibration"):
            for element in joint.findall(tag):
                joint.remove(element)
        if joint.get("type") != "fixed" and joint.get("name") not in joint_names:
            joint.set("type", "fixed")
            for tag in ("limit", "axis"):
                for element in joint.findall(tag):
                    joint.remove(element)
    extension = ET.SubElement(root, "mujoco")
    # fusestatic=false keeps fixed links (flange, TCP) as bodies we can push on and read.
    ET.SubElement(extension, "compiler", fusestatic="false", discardvisual="true",
                  balanceinertia="false")
    return ET.tostring(root, encoding="unicode")


def build_model(setup: RobotSetup, plant: PlantSpec) -> mujoco.MjModel:
    """Compile the MuJoCo model of ``setup`` with the inertial part of ``plant`` (its true rigid
    body with the payload, and the armature)."""
    model = mujoco.MjSpec.from_string(_strip_urdf(true_urdf(setup, plant, with_payload=True),
                                                  setup.joint_names)).compile()
    names = tuple(model.joint(i).name for i in range(model.njnt))
    if names != setup.joint_names or model.nv != setup.n:
        raise ValueError(f"{setup.name}: MuJoCo joints {names} differ from {setup.joint_names}")
    model.opt.timestep = PHYSICS_DT
    model.opt.gravity[:] = GRAVITY
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model.jnt_limited[:] = 0
    model.dof_damping[:] = 0.0
    model.dof_armature[:] = plant.armature
    model.dof_frictionloss[:] = dry_friction_level(plant, np.zeros(setup.n))
    model.dof_solref[:] = _DRY_FRICTION_SOLREF
    model.dof_solimp[:] = _DRY_FRICTION_SOLIMP
    return model


class MujocoPlant:
    """One simulated arm: state, external wrenches (``xfrc_applied``) and a 1 ms step."""

    def __init__(self, setup: RobotSetup, plant: PlantSpec) -> None:
        if plant.n != setup.n:
            raise ValueError(f"plant is for {plant.n} joints, {setup.name} has {setup.n}")
        self.setup = setup
        self.plant = plant
        self.model = build_model(setup, plant)
        self.data = mujoco.MjData(self.model)
        self._start = 0.0
        self._steps = 0

    @property
    def time(self) -> float:
        """The plant clock, s since the robot was switched on (the drifts depend on it)."""
        return self._start + self._steps * PHYSICS_DT

    @property
    def q(self) -> FloatArray:
        """Joint positions, rad (copy)."""
        return self.data.qpos.copy()

    @property
    def qd(self) -> FloatArray:
        """Joint velocities, rad/s (copy)."""
        return self.data.qvel.copy()

    def body_id(self, name: str) -> int:
        """MuJoCo id of a body (a URDF link name); ValueError if absent."""
        body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if body < 0:
            raise ValueError(f"{self.setup.name} has no link {name!r}")
        return body

    def in_flange_subtree(self, name: str) -> bool:
        """Whether a wrench on body ``name`` passes through the wrist (flange) F/T sensor."""
        flange, body = self.body_id(self.setup.flange_frame), self.body_id(name)
        while body > 0:
            if body == flange:
                return True
            body = int(self.model.body_parentid[body])
        return False

    def reset(self, q: npt.ArrayLike, qd: npt.ArrayLike | None = None, time: float = 0.0) -> None:
        """Put the arm at joint state (q rad, q̇ rad/s) with no external wrench and the plant clock
        at ``time`` s since power-on (0: cold)."""
        if not np.isfinite(time) or time < 0.0:
            raise ValueError(f"plant time must be >= 0 s, got {time}")
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = q
        self.data.qvel[:] = 0.0 if qd is None else qd
        self._start, self._steps = float(time), 0
        self._update_dry_friction()
        mujoco.mj_forward(self.model, self.data)

    def _update_dry_friction(self) -> None:
        """The dry-friction level depends on q̇ (Stribeck) and on the plant clock (drift); MuJoCo
        reads it when it builds the constraints (position stage), so it is set before that stage."""
        if self.plant.dry_friction:
            self.model.dof_frictionloss[:] = (friction_drift_factor(self.plant, self.time)
                                              * dry_friction_level(self.plant, self.data.qvel))

    def frame_pose(self, name: str) -> tuple[FloatArray, FloatArray]:
        """Position (3,) m and rotation (3, 3) of a body frame in the base frame."""
        body = self.body_id(name)
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def frame_velocity(self, name: str) -> tuple[FloatArray, FloatArray]:
        """Linear (3,) m/s and angular (3,) rad/s velocity of a body frame origin, base axes."""
        out = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_XBODY,
                                 self.body_id(name), out, 0)
        return out[3:], out[:3]

    def apply(self, wrenches: Sequence[AppliedWrench]) -> None:
        """Set the external wrenches for the next step (replacing earlier ones).

        ``xfrc_applied`` takes force and torque about the body's centre of mass, so the torque
        is shifted from ``point`` to ``xipos``.
        """
        self.data.xfrc_applied[:] = 0.0
        for wrench in wrenches:
            body = self.body_id(wrench.body)
            lever = wrench.point - self.data.xipos[body]
            self.data.xfrc_applied[body, :3] += wrench.force
            self.data.xfrc_applied[body, 3:] += wrench.torque + np.cross(lever, wrench.force)

    def step(self, tau_m: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Advance one physics step (1 ms) under command τ_m (N·m) and the applied wrenches.

        Returns, for the state and plant clock at the start of the step: the drive torque (N·m,
        the noise-free measured effort, offset drift included), the friction torque the plant
        applied (N·m, τ_f slot, drift and stiction included) and the joint acceleration (rad/s²).
        The step is split (mj_step2 then mj_step1) so that between steps poses and velocities
        describe the current state.
        """
        plant, data = self.plant, self.data
        drive = actuator_torque(plant, data.qpos, tau_m) + torque_offset_drift(plant, self.time)
        smooth = friction_drift_factor(plant, self.time) * (
            plant.viscous * data.qvel if plant.dry_friction else friction_torque(plant, data.qvel))
        data.qfrc_applied[:] = drive - smooth
        mujoco.mj_step2(self.model, data)
        # The only constraints are dry friction; the torque they applied is what moved q̈ off the
        # unconstrained q̈_smooth: M (q̈ − q̈_smooth). That is −qfrc_constraint at solver convergence,
        # and stays exact when the solver stops at its tolerance (~1e-5 N·m off under stiction).
        constraint = np.zeros(self.model.nv)
        mujoco.mj_mulM(self.model, data, constraint, data.qacc - data.qacc_smooth)
        friction, qacc = smooth - constraint, data.qacc.copy()
        self._steps += 1
        self._update_dry_friction()
        mujoco.mj_step1(self.model, data)
        return drive, friction, qacc
