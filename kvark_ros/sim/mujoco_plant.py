"""The simulated robot: MuJoCo built from the same URDF as the nominal model, plus a plant file.

MuJoCo and pinocchio are two independent dynamics engines; on the bare URDF they agree to
rounding error, so every difference an estimator sees comes from the plant file (friction,
armature, payload, drive gain, offset, ripple) or from external forces.

Only inertias matter: visual and collision geometry are stripped, joints that are not
simulated (the Panda's fingers) become fixed (pinocchio locks them at 0 too), URDF joint
damping/friction and joint limits are dropped, gravity is −9.81 m/s² along base z, and the
physics step is 1 ms (semi-implicit Euler).

Joint-level plant effects are applied as generalized forces on every physics step from the state
at the start of the step. Smooth friction (Gaz sigmoid, viscous) is explicit; dry
(Coulomb/Stribeck) friction is MuJoCo's ``dof_frictionloss`` constraint, which also holds the
joint at rest (stiction) and is stable for any friction level.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import numpy.typing as npt

from kvark_ros.core.payload import Payload
from kvark_ros.sim.plant import PlantSpec, actuator_torque, dry_friction_level, friction_torque
from kvark_ros.sim.robots import RobotSetup, urdf_xml

FloatArray = npt.NDArray[np.float64]
PHYSICS_DT = 1e-3          # s
GRAVITY = (0.0, 0.0, -9.81)  # m/s², base frame
PAYLOAD_BODY = "kvark_payload"
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


def _add_payload(spec: mujoco.MjSpec, flange: str, payload: Payload) -> None:
    """Weld the payload to the flange body as a rigid body with its own inertia."""
    ixx, iyy, izz, ixy, ixz, iyz = payload.inertia
    principal, axes = np.linalg.eigh(np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]))
    if np.linalg.det(axes) < 0.0:
        axes[:, 2] *= -1.0
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, axes.flatten())
    spec.body(flange).add_body(name=PAYLOAD_BODY, mass=payload.mass, ipos=list(payload.com),
                               iquat=list(quat), inertia=list(np.clip(principal, 0.0, None)),
                               explicitinertial=True)


def build_model(setup: RobotSetup, plant: PlantSpec) -> mujoco.MjModel:
    """Compile the MuJoCo model of ``setup`` with the inertial part of ``plant``."""
    spec = mujoco.MjSpec.from_string(_strip_urdf(urdf_xml(setup.urdf), setup.joint_names))
    if plant.payload is not None:
        _add_payload(spec, setup.flange_frame, plant.payload)
    model = spec.compile()
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

    def reset(self, q: npt.ArrayLike, qd: npt.ArrayLike | None = None) -> None:
        """Put the arm at joint state (q rad, q̇ rad/s) at time 0, with no external wrench."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = q
        self.data.qvel[:] = 0.0 if qd is None else qd
        self._update_dry_friction()
        mujoco.mj_forward(self.model, self.data)

    def _update_dry_friction(self) -> None:
        """Stribeck: the dry-friction level depends on q̇; MuJoCo reads it when it builds the
        constraints (position stage), so it is set before that stage."""
        if self.plant.friction_model == "stribeck":
            self.model.dof_frictionloss[:] = dry_friction_level(self.plant, self.data.qvel)

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

        Returns, for the state at the start of the step: the drive torque (N·m, the noise-free
        measured effort), the friction torque the plant applied (N·m, τ_f slot, stiction
        included) and the joint acceleration (rad/s²). The step is split (mj_step2 then
        mj_step1) so that between steps poses and velocities describe the current state.
        """
        plant, data = self.plant, self.data
        drive = actuator_torque(plant, data.qpos, tau_m)
        smooth = plant.viscous * data.qvel if plant.dry_friction else friction_torque(plant, data.qvel)
        data.qfrc_applied[:] = drive - smooth
        mujoco.mj_step2(self.model, data)
        # The only constraints are dry friction, so qfrc_constraint is minus its torque.
        friction, qacc = smooth - data.qfrc_constraint, data.qacc.copy()
        self._update_dry_friction()
        mujoco.mj_step1(self.model, data)
        return drive, friction, qacc
