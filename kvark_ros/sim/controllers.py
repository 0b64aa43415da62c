"""Controllers of the simulated robot; both see only measured signals and the nominal model.

Both are called once per control period (``control_rate_hz`` of the plant file: 1 kHz, every
physics step, by default; 500 Hz holds each command for two physics steps) with the measured
(quantised) position and the measured (noisy) velocity, and return the commanded torque τ_m,
clipped to the URDF effort limits. τ_m is what the bag records as the commanded effort.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from kvark_ros.core.estimation.robot_model import RobotModel

FloatArray = npt.NDArray[np.float64]
JointReference = Callable[[float], tuple[FloatArray, FloatArray, FloatArray]]


@dataclass(frozen=True)
class CartesianTarget:
    """Desired end-effector pose and velocity in the base frame: position (3,) m,
    rotation (3, 3), linear velocity (3,) m/s."""

    position: FloatArray
    rotation: FloatArray
    velocity: FloatArray


CartesianReference = Callable[[float], CartesianTarget]


class JointTrackingController:
    """Joint-space PD with nominal inverse-dynamics feedforward, PD shaped by the nominal inertia.

    ``τ_m = ID_nom(q_d, q̇_d, q̈_d) + M_nom(q) (K_p (q_d − q) + K_d (q̇_d − q̇))`` (N·m), K_p in
    1/s², K_d in 1/s. The feedforward is evaluated on the reference, so measurement noise enters
    only through the PD terms; the PD absorbs what the nominal model lacks (friction, payload).
    Scaling the PD by M(q) gives every joint the same bandwidth in every configuration, which
    keeps a 1 kHz loop stable on a plant without motor inertia (coupled light modes, such as
    joints 1 and 3 of a stretched Panda counter-rotating, would otherwise ring).
    """

    def __init__(self, model: RobotModel, reference: JointReference, kp: npt.ArrayLike,
                 kd: npt.ArrayLike) -> None:
        self.model = model
        self.reference = reference
        self.kp = np.asarray(kp, dtype=float)
        self.kd = np.asarray(kd, dtype=float)
        self.limit = np.asarray(model.model.effortLimit, dtype=float)

    def __call__(self, t: float, q: FloatArray, qd: FloatArray) -> FloatArray:
        """Commanded torque (n,) N·m at time t s for measured q (rad), q̇ (rad/s)."""
        q_d, qd_d, qdd_d = self.reference(t)
        feedback = self.model.mass_matrix(q) @ (self.kp * (q_d - q) + self.kd * (qd_d - qd))
        tau = self.model.inverse_dynamics(q_d, qd_d, qdd_d) + feedback
        return np.clip(tau, -self.limit, self.limit)


class CartesianImpedanceController:
    """Cartesian impedance control as in the paper's polishing experiment (v2, exp. 2).

    ``τ_m = Jᵀ (K e − D (ẋ − ẋ_d)) + (I − Jᵀ J^{T+}) (K_n (q_n − q) − D_n q̇) + C(q, q̇) q̇ + g(q)``
    with J the nominal end-effector Jacobian (base axes, linear rows first), e = (p_d − p,
    log(R_d Rᵀ)) the pose error in the base frame, and Coriolis and gravity from the nominal
    model (the structure of Mayr et al.'s controller plus gravity compensation, as the paper
    does). K, D: (6,) N/m, N·m/rad and N·s/m, N·m·s/rad; K_n, D_n: scalars for the nullspace
    posture q_n (a 6-joint arm has no nullspace, so that term vanishes away from
    singularities).
    """

    def __init__(self, model: RobotModel, reference: CartesianReference, stiffness: npt.ArrayLike,
                 damping: npt.ArrayLike, posture: npt.ArrayLike, nullspace_stiffness: float,
                 nullspace_damping: float) -> None:
        self.model = model
        self.reference = reference
        self.stiffness = np.asarray(stiffness, dtype=float)
        self.damping = np.asarray(damping, dtype=float)
        self.posture = np.asarray(posture, dtype=float)
        self.nullspace_stiffness = float(nullspace_stiffness)
        self.nullspace_damping = float(nullspace_damping)
        self.limit = np.asarray(model.model.effortLimit, dtype=float)
        self._zero = np.zeros(model.n)

    def __call__(self, t: float, q: FloatArray, qd: FloatArray) -> FloatArray:
        """Commanded torque (n,) N·m at time t s for measured q (rad), q̇ (rad/s)."""
        target = self.reference(t)
        model = self.model
        jac = model.jacobian(q, "base")        # runs forward kinematics on model.data
        pin.updateFramePlacement(model.model, model.data, model.ee_frame_id)
        pose = model.data.oMf[model.ee_frame_id]
        error = np.concatenate([target.position - pose.translation,
                                pin.log3(target.rotation @ pose.rotation.T)])
        twist_error = jac @ qd
        twist_error[:3] -= target.velocity
        task = jac.T @ (self.stiffness * error - self.damping * twist_error)
        projector = np.eye(model.n) - jac.T @ np.linalg.pinv(jac.T, rcond=1e-4)
        nullspace = projector @ (self.nullspace_stiffness * (self.posture - q) - self.nullspace_damping * qd)
        tau = task + nullspace + model.inverse_dynamics(q, qd, self._zero)   # + C q̇ + g
        return np.clip(tau, -self.limit, self.limit)
