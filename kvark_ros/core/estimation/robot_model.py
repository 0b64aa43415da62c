"""Nominal rigid-body model of the arm (pinocchio), reduced to the estimated joints.

Everything the filters need from the robot lives here: generalized momentum and its input
(paper v1 eqs. 5-8), inverse dynamics (eq. 27's tau_EL), the frame Jacobian, and the damped
pseudo-inverse that maps external joint torques to a wrench (paper v2 eq. 39), with the wrench directions
it cannot sense near singular poses (docs/method.md §1.4.1).

An ``Augmentation`` (``kvark diagnose``, docs/method.md §8) adds the physical effects the URDF lacks:
payload and armature inside M, C, g; the joint offset as a corrected q; friction, drive gain,
offsets and ripple as a joint torque ``τ_aug(q, q̇, τ_m)`` the drive spends beyond the rigid body.

Sign convention (docs/method.md §1.2): ``M q̈ + C q̇ + g + τ_f = τ_m + τ_ext`` with ``τ_ext = Jᵀ F_ext``,
``F_ext`` the wrench the environment applies *to the robot* at the end-effector frame origin.
"""
from __future__ import annotations

import functools
import hashlib
import math
import os
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Sequence

import numpy as np
import pinocchio as pin

from kvark_ros.core.estimation.augmentation import Augmentation
from kvark_ros.core.config import EXAMPLE_ROBOT_DATA_PREFIX
from kvark_ros.core.hints import did_you_mean, listing
from kvark_ros.core.estimation.compiled.layouts import EstimatorParam, Outcome, pack
from kvark_ros.core.estimation.compiled.wrench import solve_wrench
from kvark_ros.core.estimation.payload import Payload, inertia_problem

if TYPE_CHECKING:
    from kvark_ros.core.config import EstimatorConfig

EXAMPLE_ROBOT_DATA_URDFS = {
    "panda": "robots/panda_description/urdf/panda.urdf",
    "ur5": "robots/ur_description/urdf/ur5_robot.urdf",
    "ur10": "robots/ur_description/urdf/ur10_robot.urdf",
}


def flange_link_parameters(model: pin.Model, flange_frame_id: int, change: np.ndarray | None = None) -> np.ndarray:
    """The 10 dynamic parameters (joint frame) of the link carrying the flange, plus ``change`` (10,) given in
    the flange frame: a change of reference frame of a spatial inertia is linear, so a negative mass (a
    tool lighter than the URDF's) maps as well as a positive one."""
    frame = model.frames[flange_frame_id]
    total = model.inertias[frame.parentJoint].toDynamicParameters().copy()
    if change is not None:
        rotation, translation = frame.placement.rotation, frame.placement.translation
        m, h = float(change[0]), rotation @ np.asarray(change[1:4], dtype=float)
        ixx, ixy, iyy, ixz, iyz, izz = change[4:10]
        inertia = rotation @ np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]) @ rotation.T
        # parallel axis for first and second moments: I_o' = I_o − [t]×[h]× − [h]×[t]× − m [t]×[t]×
        t_x, h_x = pin.skew(translation), pin.skew(h)
        inertia = inertia - t_x @ h_x - h_x @ t_x - m * t_x @ t_x
        h = h + m * translation
        total += np.array([m, *h, inertia[0, 0], inertia[0, 1], inertia[1, 1], inertia[0, 2], inertia[1, 2],
                           inertia[2, 2]])
    return total


def condition_numbers(jacobians: np.ndarray) -> np.ndarray:
    """κ = σ_max/σ_min of each 6×n Jacobian of a (T, 6, n) stack (∞ for n < 6 or σ_min = 0), one batched SVD;
    the same in base and ee axes."""
    sigma = np.linalg.svd(jacobians, compute_uv=False)
    if sigma.shape[-1] < 6:
        return np.full(len(jacobians), math.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma[:, -1] > 0.0, sigma[:, 0] / sigma[:, -1], math.inf)


def condition_number(jac: np.ndarray) -> float:
    """κ of one 6×n Jacobian (``condition_numbers``)."""
    return float(condition_numbers(jac[None])[0])


class WrenchSolution(NamedTuple):
    """``RobotModel.solve_wrench``'s result, all in the axes it was asked for (a tuple: cheap per sample).

    wrench: (6,) [N, N·m]; cov: (6, 6) or None; weak: (6, k) orthonormal wrench directions (columns,
    mixed force/moment like δ) with σ_i < δ, whose component the damping sets rather than the data
    (docs/method.md §1.4.1), k = 0 almost always; jacobian: the (6, n) J it came from.
    """

    wrench: np.ndarray
    cov: np.ndarray | None
    weak: np.ndarray
    jacobian: np.ndarray

    @property
    def condition(self) -> float:
        """κ = σ_max/σ_min of J (an SVD: computed when asked, not per sample)."""
        return condition_number(self.jacobian)


class LiveTerms(NamedTuple):
    """Views of a pinocchio ``Data``'s results, rewritten in place by every pass (pinocchio's functions return
    copies; these are not): g (n,), rnea's τ (n,), the Coriolis matrix C (n, n) and the ee frame's rotation (3, 3)."""

    gravity: np.ndarray
    rnea: np.ndarray
    coriolis: np.ndarray
    ee_rotation: np.ndarray


class RobotModelError(ValueError):
    """The URDF, a joint name or a frame name is unusable."""


def resolve_urdf(spec: str) -> str:
    """Return URDF XML from a file path, an XML string, or ``example-robot-data:<robot>``.

    The last form finds the URDF shipped by the ``example-robot-data`` pip package
    (installed with ``pip install kvark_ros[sim]``).
    """
    text = spec.strip()
    if text.startswith("<"):
        return text
    if text.startswith(EXAMPLE_ROBOT_DATA_PREFIX):
        return Path(_example_robot_data_path(text[len(EXAMPLE_ROBOT_DATA_PREFIX):])).read_text()
    path = Path(os.path.expanduser(text))
    if not path.is_file():
        raise RobotModelError(f"{text}: URDF file not found; set robot_model.urdf to an existing file, "
                              f"or to {EXAMPLE_ROBOT_DATA_PREFIX}panda / {EXAMPLE_ROBOT_DATA_PREFIX}ur5")
    return path.read_text()


def urdf_sha256(spec: str) -> str:
    """sha256 of the URDF text ``spec`` resolves to: recorded by training, checked before estimation."""
    return hashlib.sha256(resolve_urdf(spec).encode()).hexdigest()


@functools.lru_cache(maxsize=None)
def _example_robot_data_path(robot: str) -> str:
    """Path of an example-robot-data URDF inside the installed pip distribution (looked up once per process: the
    listing of the distribution's files costs ~50 ms of interpreter time, which a node's reload should not)."""
    if robot not in EXAMPLE_ROBOT_DATA_URDFS:
        raise RobotModelError(f"{EXAMPLE_ROBOT_DATA_PREFIX}{robot}: unknown robot; "
                              f"known: {', '.join(sorted(EXAMPLE_ROBOT_DATA_URDFS))}")
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError as exc:
        raise RobotModelError(f"{EXAMPLE_ROBOT_DATA_PREFIX}{robot}: the example-robot-data package is not "
                              "installed; run `pip install kvark_ros[sim]` or point robot_model.urdf "
                              "at a URDF file") from exc
    suffix = EXAMPLE_ROBOT_DATA_URDFS[robot]
    for file in dist.files or ():
        if str(file).endswith(suffix):
            return str(dist.locate_file(file))
    raise RobotModelError(f"{EXAMPLE_ROBOT_DATA_PREFIX}{robot}: {suffix} missing from example-robot-data")


class RobotModel:
    """Pinocchio model reduced to ``joint_names``; one ``Data`` reused on every call.

    Args:
        urdf: URDF file path, XML string, or ``example-robot-data:<robot>``.
        joint_names: the estimated joints, in output order; every other joint is locked at 0.
        ee_frame: frame whose origin is the wrench reference point (e.g. ``panda_hand_tcp``).
        flange_frame: frame a payload is attached to (defaults to ``ee_frame``).
        payload: optional tool/payload added to the nominal model.
        augmentation: optional effects found by ``kvark diagnose`` (same joints).
    """

    def __init__(self, urdf: str, joint_names: Sequence[str], ee_frame: str,
                 flange_frame: str | None = None, payload: Payload | None = None,
                 augmentation: Augmentation | None = None) -> None:
        try:
            full = pin.buildModelFromXML(resolve_urdf(urdf))
        except RuntimeError as exc:
            raise RobotModelError(f"URDF could not be parsed: {exc}") from exc
        self.urdf_name = "the URDF" if urdf.lstrip().startswith("<") else f"the URDF {urdf}"
        self._built_from = (urdf, tuple(joint_names), ee_frame, flange_frame, payload)
        missing = [name for name in joint_names if not full.existJointName(name)]
        if missing:
            raise RobotModelError(self._not_a_joint(full, missing[0]))
        locked = [jid for jid in range(1, full.njoints) if full.names[jid] not in joint_names]
        self.model = pin.buildReducedModel(full, locked, pin.neutral(full)) if locked else full
        order = [self.model.getJointId(name) for name in joint_names]
        several = [(name, self.model.joints[jid].nv) for name, jid in zip(joint_names, order)
                   if self.model.joints[jid].nv != 1]
        if several:
            raise RobotModelError(f"robot_model.joint_names: {several[0][0]!r} of {self.urdf_name} has {several[0][1]} "
                                  "degrees of freedom; only one-degree-of-freedom joints are supported")
        # Column of each requested joint in pinocchio's v ordering (pinocchio orders by tree).
        self._index = np.array([self.model.joints[jid].idx_v for jid in order])
        if not np.array_equal(self._index, np.arange(len(order))):
            raise RobotModelError(f"robot_model.joint_names must follow the kinematic chain order of {self.urdf_name}: "
                                  f"{', '.join(self.model.names[j] for j in range(1, self.model.njoints))}")
        self.joint_names = tuple(joint_names)
        self.ee_frame_id = self._frame_id(ee_frame, "robot_model.ee_frame")
        self.flange_frame_id = self._frame_id(flange_frame or ee_frame,
                                              "robot_model.flange_frame" if flange_frame else "robot_model.ee_frame")
        self.augmentation = augmentation
        self._q_offset: np.ndarray | None = None
        if augmentation is not None:
            self._augment(augmentation)
        self._nominal_inertias = [pin.Inertia(inertia) for inertia in self.model.inertias]
        self.data = self.model.createData()
        self.terms = LiveTerms(self.data.g, self.data.tau, self.data.C, self.data.oMf[self.ee_frame_id].rotation)
        self._zero = np.zeros(self.model.nv)
        self._below_diagonal = np.tril_indices(self.model.nv, -1)
        self.payload: Payload | None = None
        if payload is not None:
            self.set_payload(payload)

    def with_augmentation(self, augmentation: Augmentation | None) -> "RobotModel":
        """The same robot (URDF, joints, frames, the payload it was built with) with another ``augmentation`` instead
        of its own."""
        return RobotModel(*self._built_from, augmentation)

    @classmethod
    def from_config(cls, config: "EstimatorConfig", augmentation: Augmentation | None = None,
                    urdf: str | None = None) -> "RobotModel":
        """The model a config describes; ``urdf`` overrides ``config.urdf`` (e.g. robot_description)."""
        return cls(urdf or config.urdf, config.joint_names, config.ee_frame, config.flange_frame, config.payload,
                   augmentation)

    @property
    def root_link(self) -> str:
        """Name of the URDF root link (the frame whose axes ``wrench.frame: base`` uses)."""
        for frame in self.model.frames:
            if frame.parentJoint == 0 and str(frame.type) == "BODY":
                return frame.name
        return "base"

    @property
    def n(self) -> int:
        """Number of estimated joints."""
        return self.model.nv

    def _not_a_joint(self, full: pin.Model, name: str) -> str:
        """The error of a ``robot_model.joint_names`` entry that is not a moving joint of the URDF ``full``."""
        moving = list(full.names[1:])
        fixed = full.existFrame(name) and full.frames[full.getFrameId(name)].type == pin.FrameType.FIXED_JOINT
        problem = f"is a fixed joint of {self.urdf_name}, not a moving one" if fixed else \
            f"is not a joint of {self.urdf_name}"
        hint = did_you_mean(name, moving) or f"; its moving joints: {listing(moving)}"
        return f"robot_model.joint_names: {name!r} {problem}{hint}"

    def _frame_id(self, name: str, key: str = "the wrench's header.frame_id") -> int:
        """The id of frame ``name``; an error naming ``key`` (the config key or message field that names the frame)
        and the nearest frame if there is none."""
        if not self.model.existFrame(name):
            frames = [frame.name for frame in self.model.frames]
            links = [frame.name for frame in self.model.frames if frame.type == pin.FrameType.BODY]
            hint = did_you_mean(name, frames) or f"; its links: {listing(links)}"
            raise RobotModelError(f"{key}: {name!r} is not a frame of {self.urdf_name}{hint}")
        return self.model.getFrameId(name)

    def _augment(self, augmentation: Augmentation) -> None:
        """Build the structural effects into the pinocchio model (before ``Data`` is made)."""
        if augmentation.joint_names != self.joint_names:
            raise RobotModelError(f"{augmentation.source}: augmentation joints {list(augmentation.joint_names)} "
                                  f"differ from the model's {list(self.joint_names)}")
        if augmentation.link_inertia is not None:
            for i, change in enumerate(augmentation.link_inertia, start=1):
                total = self.model.inertias[i].toDynamicParameters() + change
                problem = inertia_problem(total)
                if problem is not None:
                    raise RobotModelError(f"{augmentation.source}: link_inertia makes the link of joint {i} physically "
                                          f"inconsistent ({problem}); diagnose again with `kvark diagnose`")
                self.model.inertias[i] = pin.Inertia.FromDynamicParameters(total)
        if augmentation.payload is not None:    # a change of the flange link's inertia, possibly lighter (docs §8)
            frame = self.model.frames[self.flange_frame_id]
            total = flange_link_parameters(self.model, self.flange_frame_id, augmentation.payload)
            problem = inertia_problem(total)
            if problem is not None:
                raise RobotModelError(f"{augmentation.source}: the payload effect makes the flange link "
                                      f"physically inconsistent ({problem}); diagnose again with `kvark diagnose`")
            self.model.inertias[frame.parentJoint] = pin.Inertia.FromDynamicParameters(total)
        self.model.armature[self._index] += augmentation.armature
        if np.any(augmentation.joint_offset):
            self._q_offset = np.array(augmentation.joint_offset, dtype=float)

    def _true_q(self, q: np.ndarray) -> np.ndarray:
        """Joint position the model is evaluated at: the measured one minus the encoder offset."""
        return q if self._q_offset is None else q - self._q_offset

    def model_position(self, q: np.ndarray) -> np.ndarray:
        """The position (n,) rad pinocchio evaluates this model at for a measured q (the encoder offset removed)."""
        return self._true_q(q)

    def set_payload(self, payload: Payload | None) -> None:
        """Attach (or with ``None`` remove) a payload at the flange; replaces any earlier one."""
        frame = self.model.frames[self.flange_frame_id]
        joint = frame.parentJoint
        self.model.inertias[joint] = pin.Inertia(self._nominal_inertias[joint])
        if payload is not None:
            if payload.mass <= 0.0:
                raise RobotModelError(f"payload mass must be positive, got {payload.mass}")
            self.model.inertias[joint] = self.model.inertias[joint] + frame.placement.act(payload.to_pinocchio())
        self.payload = payload

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q): (n, n) kg·m², symmetric."""
        pin.crba(self.model, self.data, self._true_q(q))    # fills M's upper triangle
        matrix = self.data.M.copy()
        matrix[self._below_diagonal] = matrix.T[self._below_diagonal]
        matrix += 0.0       # as triu(M) + triu(M, 1)ᵀ: a −0.0 becomes +0.0, so the bits are that sum's
        return matrix

    def momentum_terms(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Generalized momentum and its model input.

        Returns ``p = M(q) q̇`` (eq. 5, N·m·s) and ``u = Cᵀ(q, q̇) q̇ − g(q) + τ_m`` (eq. 7, N·m),
        so that ``ṗ = u + τ_ext − τ_f`` in our sign convention. With an augmentation ``u`` uses
        the torque the drive applies to the rigid body, ``τ_m − τ_aug``.
        """
        q_model = self._true_q(q)
        gravity = pin.computeGeneralizedGravity(self.model, self.data, q_model).copy()
        # rnea(q, 0, q̇) = M q̇ + g: one O(n) pass instead of forming M.
        p = pin.rnea(self.model, self.data, q_model, self._zero, qd) - gravity    # eq. 5
        coriolis = pin.computeCoriolisMatrix(self.model, self.data, q_model, qd)
        u = coriolis.T @ qd - gravity + tau_m                                     # eq. 7
        if self.augmentation is not None and self.augmentation.torque_effects:
            u -= self.augmentation.joint_torque(q, qd, tau_m)
        return p, u

    def compute_terms(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """The pinocchio passes of ``momentum_terms`` and ``jacobian``,
        for the compiled step (core.estimation.compiled).

        g(q), rnea(q, 0, q̇) = M q̇ + g and C(q, q̇) are left in ``terms`` (with the ee rotation R); returns J (6, n)
        of the ee frame origin in base axes.
        """
        q_model = q if self._q_offset is None else q - self._q_offset      # _true_q, inline: called per sample
        model, data = self.model, self.data
        pin.computeGeneralizedGravity(model, data, q_model)
        pin.rnea(model, data, q_model, self._zero, qd)
        pin.computeCoriolisMatrix(model, data, q_model, qd)
        return pin.computeFrameJacobian(model, data, q_model, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """g(q): gravity torque (n,) N·m of the (augmented) model, an input of pose-aware residual models."""
        return pin.computeGeneralizedGravity(self.model, self.data, self._true_q(q)).copy()

    def inverse_dynamics(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """τ_EL = M q̈ + C q̇ + g (eq. 27), N·m (augmented M, C, g; without τ_aug)."""
        return pin.rnea(self.model, self.data, self._true_q(q), qd, qdd).copy()

    def model_torque(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
        """What the improved model expects the drive to be commanded on a contact-free motion:
        ``τ_EL + τ_aug(q, q̇, τ_m)`` (N·m); the nominal τ_EL without an augmentation."""
        tau = self.inverse_dynamics(q, qd, qdd)
        if self.augmentation is not None and self.augmentation.torque_effects:
            tau += self.augmentation.joint_torque(q, qd, tau_m)
        return tau

    def forward_dynamics(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """q̈ from the articulated-body algorithm, rad/s²."""
        return pin.aba(self.model, self.data, self._true_q(q), qd, tau).copy()

    def jacobian(self, q: np.ndarray, frame: str = "base") -> np.ndarray:
        """(6, n) Jacobian of the end-effector frame origin: linear rows first.

        ``frame="base"`` expresses it in base axes (LOCAL_WORLD_ALIGNED), ``"end_effector"`` in the
        end-effector axes (LOCAL). Either way ``τ_ext = Jᵀ F`` for ``F`` expressed in the same axes.
        """
        reference = pin.LOCAL_WORLD_ALIGNED if frame == "base" else pin.LOCAL
        return pin.computeFrameJacobian(self.model, self.data, self._true_q(q), self.ee_frame_id, reference)

    def wrench_from_torque(self, q: np.ndarray, tau_ext: np.ndarray, tau_cov: np.ndarray | None,
                           damping: float, frame: str = "base") -> tuple[np.ndarray, np.ndarray | None]:
        """External wrench and its covariance from external joint torques, without the damping bias.

        ``F = (J Jᵀ + δ² I)⁻¹ J τ_ext`` (paper v2 eq. 39) and ``Σ_F = J⁺ P J⁺ᵀ`` with
        ``J⁺ = (J Jᵀ + δ² I)⁻¹ J``. F: (6,) [N, N·m]; Σ_F: (6, 6), ``None`` when ``tau_cov`` is.
        """
        solution = self.solve_wrench(q, tau_ext, tau_cov, damping, frame)
        return solution.wrench, solution.cov

    def solve_wrench(self, q: np.ndarray, tau_ext: np.ndarray, tau_cov: np.ndarray | None, damping: float,
                     frame: str = "base", prior: tuple[float, float] | None = None) -> WrenchSolution:
        """The wrench of ``wrench_from_torque``, its Jacobian and the unobservable directions (docs/method.md §1.4.1),
        by the estimator's own compiled solve (``compiled.wrench.solve_wrench``).

        Whether some σ_i < δ is one 6×6 Cholesky; only then an SVD gives the directions. ``prior``: (force N,
        moment N·m) standard deviations of the unknown wrench; with it (and ``tau_cov``) Σ_F adds the damping
        bias along the weak directions and equals ``wrench_from_torque``'s elsewhere. All in ``frame``'s axes.
        ``numpy.linalg.LinAlgError`` when J Jᵀ + δ² I is not positive definite (δ = 0 at a singular pose).
        """
        n = self.n
        jac = self.jacobian(q, "base")
        rotation = self.terms.ee_rotation.copy()
        force, moment = prior if prior is not None else (0.0, 0.0)
        params = np.array(pack(EstimatorParam, {EstimatorParam.DAMPING: damping, EstimatorParam.PRIOR_FORCE: force,
                                                EstimatorParam.PRIOR_MOMENT: moment,
                                                EstimatorParam.STICTION_VELOCITY: 0.0, EstimatorParam.Z: 0.0,
                                                EstimatorParam.KMP_SIZE: 0.0}))
        cov = np.zeros((n, n)) if tau_cov is None else np.ascontiguousarray(tau_cov, dtype=float)
        wrench, wrench_cov, directions = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
        end_effector = frame != "base"
        code, k = solve_wrench(jac, np.ascontiguousarray(tau_ext, dtype=float), np.zeros(n), cov, True, params,
                               rotation, end_effector, wrench, wrench_cov, directions)
        if code & Outcome.SINGULAR:
            raise np.linalg.LinAlgError(f"J Jᵀ + δ² I is not positive definite (damping {damping:g} at a singular "
                                        "pose)")
        if end_effector:                                                  # J in the ee axes: diag(Rᵀ, Rᵀ) J
            jac = np.vstack((rotation.T @ jac[:3], rotation.T @ jac[3:]))
        return WrenchSolution(wrench, None if tau_cov is None else wrench_cov, directions[:, :k].copy(), jac)

    def sensor_torque(self, q: np.ndarray, frame: str, wrench: np.ndarray) -> np.ndarray:
        """``τ = Jᵀ w`` (paper v2 eq. 37) for a wrench (6,) measured in ``frame``'s own axes at its origin."""
        jac = pin.computeFrameJacobian(self.model, self.data, self._true_q(q), self._frame_id(frame), pin.LOCAL)
        return jac.T @ wrench

    def wrenches_at_end_effector(self, q: np.ndarray, frame: str, wrench: np.ndarray,
                                 axes: str = "base") -> np.ndarray:
        """Re-express wrenches (T, 6) [f, m], each given in ``frame`` (its axes, its origin) at the pose q (T, n) rad,
        at the end-effector origin in base or end-effector axes: how a wrist F/T reading compares with our estimate.

        With the frame's pose (R_s, p_s) and the ee origin p_e in base: f_b = R_s f, m_b = R_s m + (p_s − p_e) × f_b
        (pinocchio's SE3 action on a force, then the moment about p_e); in ee axes both are rotated by R_eᵀ. One
        forward-kinematics pass per sample, the rest in batch; rows with a non-finite wrench are NaN."""
        sensor, ee, model, data = self._frame_id(frame), self.ee_frame_id, self.model, self.data
        count = len(q)
        rotation, ee_rotation, arm = np.empty((count, 3, 3)), np.empty((count, 3, 3)), np.empty((count, 3))
        for k in range(count):
            pin.framesForwardKinematics(model, data, self._true_q(q[k]))
            at_sensor, at_ee = data.oMf[sensor], data.oMf[ee]
            rotation[k], ee_rotation[k] = at_sensor.rotation, at_ee.rotation
            arm[k] = at_sensor.translation - at_ee.translation
        force = np.einsum("kij,kj->ki", rotation, wrench[:, :3])
        moment = np.einsum("kij,kj->ki", rotation, wrench[:, 3:]) + np.cross(arm, force)
        if axes != "base":
            force, moment = (np.einsum("kji,kj->ki", ee_rotation, v) for v in (force, moment))
        result = np.hstack((force, moment))
        result[~np.isfinite(wrench).all(axis=1)] = np.nan
        return result
