"""The compiled ``Estimator.step`` of one estimator (``filter.kernel: numba``): its buffers and the kernel calls.

``Estimator`` builds a ``CompiledStep`` when its observer is a ``KVARKKernelFilter`` and hands it every accepted
sample after the first: the pinocchio passes run from Python (``RobotModel.compute_terms``), the rest in one call
of ``step_kernel.estimate_step`` on buffers allocated here once (and ``weak_wrench`` at a pose with a direction the
joints cannot sense); only the sample's outputs (τ̂, Cov τ̂, F, Σ_F, R, the weak directions) are new arrays, because
an ``Estimate`` is a snapshot its consumers keep (replay, the tests) or publish later (the node's ``/diagnostics``).
The numpy code in ``Estimator`` is the reference (docs/method.md; ``test/test_kernel.py``).
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.augmentation import TANH_EPSILON, Augmentation
from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.model_kernels import (A_COULOMB, A_DRIVE_GAIN, A_OFFSET, A_RIPPLE, A_STRIBECK, A_VISCOUS,
                                          augmentation_torque)
from kvark_ros.core.observers.kvark_kernel import KVARKKernelFilter
from kvark_ros.core.robot_model import RobotModel
from kvark_ros.core.step_kernel import (AUGMENTED, DIVERGED, E_DAMPING, E_PARAMS, E_PRIOR_FORCE, E_PRIOR_MOMENT,
                                        E_STICTION_VELOCITY, E_Z, END_EFFECTOR, FILTER, MOMENTUM, POST, R_AUG, R_BAND,
                                        R_P_PREV, R_SCALE, R_U_PREV, ROWS, SCALED, SINGULAR, STICTION, TARED, WEAK,
                                        estimate_step, finite_sample, weak_wrench)
from kvark_ros.core.tare import Tare


class CompiledStep:
    """The compiled step of one ``Estimator`` around its ``KVARKKernelFilter``: buffers, constants and the calls.

    ``previous`` (p_{k−1}, u_{k−1}) are views of its buffer, which the Estimator keeps as its own; ``configure``
    takes the run-time keys (``Estimator.configure`` calls it). The kernels compile (or load from numba's cache)
    here, on dummy data, so the first sample does not wait; the caller resets the filter afterwards.
    """

    finite = staticmethod(finite_sample)

    def __init__(self, robot: RobotModel, observer: KVARKKernelFilter, tare: Tare, band: np.ndarray | None,
                 scale: np.ndarray | None, config: EstimatorConfig, z: float) -> None:
        """``band``: the static friction band F_s (n,) N·m or None; ``scale``: the interval factors c (n,) or None;
        ``z``: the collision test's z."""
        n = self.n = robot.n
        self.robot, self.observer = robot, observer
        self.rows = np.zeros((ROWS, n))
        self.previous = self.rows[R_P_PREV], self.rows[R_U_PREV]
        self.params = np.zeros(E_PARAMS)
        self.no_weak = np.zeros((6, 0))
        self.no_weak.flags.writeable = False
        augmentation = robot.augmentation
        self._augmentation = augmentation if augmentation is not None and augmentation.torque_effects else None
        self._aug_entries = None if self._augmentation is None else _augmentation_entries(self._augmentation)
        self._band, self._scale = band, scale
        if band is not None:
            self.rows[R_BAND] = band
        if scale is not None:
            self.rows[R_SCALE] = scale
        terms, packed = robot.terms, observer.packed
        # The arrays every call passes, bound once: none of them is ever replaced, only written in place.
        self._pinocchio = (terms.gravity, terms.rnea, terms.coriolis)
        self._buffers = (self.rows, tare.offset, self.params, packed.flat, packed.ints, observer.constants,
                         observer.options)
        self.configure(config, z)
        self._compile()

    def configure(self, config: EstimatorConfig, z: float) -> None:
        """Take the run-time keys wrench.*, filter.stiction_velocity and filter.interval_calibration, and the
        collision's z."""
        velocity, wrench = config.filter.stiction_velocity, config.wrench
        self.params[[E_DAMPING, E_PRIOR_FORCE, E_PRIOR_MOMENT, E_STICTION_VELOCITY, E_Z]] = (
            wrench.damping, wrench.prior_force, wrench.prior_moment, velocity, z)
        self._flags = ((STICTION if self._band is not None and velocity != 0.0 else 0)
                       | (SCALED if self._scale is not None and config.filter.interval_calibration == "trained" else 0)
                       | (END_EFFECTOR if config.wrench.frame != "base" else 0)
                       | (AUGMENTED if self._augmentation is not None else 0))

    def _compile(self) -> None:
        """One call of each kernel on dummy data (its machine code from numba's cache, or compiled)."""
        zeros = np.zeros(self.n)
        finite_sample(0.0, zeros, zeros, zeros)
        self.prime(zeros, zeros, zeros)
        self.observer.prepare(0.002, zeros, zeros, zeros, zeros)
        outputs = np.empty(self.n), np.empty((self.n, self.n)), np.empty(6), np.empty((6, 6))
        jac = self.robot.compute_terms(zeros, zeros)
        self._run(self._flags | MOMENTUM | FILTER | POST, 0.002, zeros, zeros, jac, np.eye(3), *outputs)
        weak_wrench(jac, zeros, np.eye(self.n), self.params, np.eye(3), False, *outputs[2:], np.empty((6, 6)))
        self.observer.prediction = None

    def _terms(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
        """The sample's pinocchio passes (into ``robot.terms``) and τ_aug; returns J (6, n) in base axes."""
        jac = self.robot.compute_terms(q, qd)
        if self._aug_entries is not None:
            augmentation_torque(q, qd, tau_m, *self._aug_entries, self.rows[R_AUG])
        return jac

    def _run(self, flags: int, dt: float, qd: np.ndarray, tau_m: np.ndarray, jac: np.ndarray, rotation: np.ndarray,
             *outputs: np.ndarray) -> tuple[int, float, float]:
        """``estimate_step`` with this estimator's buffers; ``outputs``: τ̂ (n,), Cov τ̂ (n, n), F (6,), Σ_F (6, 6)."""
        return estimate_step(flags, dt, qd, tau_m, *self._pinocchio, jac, rotation, *self._buffers, *outputs)

    def prime(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        """The first sample after a (re)start: p and u only, kept for the next sample."""
        n = self.n
        self._run(self._flags | MOMENTUM, 0.0, qd, tau_m, self._terms(q, qd, tau_m), np.eye(3), np.empty(n),
                  np.empty((n, n)), np.empty(6), np.empty((6, 6)))

    def step(self, stamp: float, dt: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, tare: Tare) -> tuple:
        """One sample after the first: (singular, diverged, contact statistic, collision excess, τ̂, Cov τ̂, F, Σ_F,
        R, J, weak directions), the arrays new; ``tare`` averages or is tracked as in ``Tare.apply``. ``singular``:
        J Jᵀ + δ² I is not positive definite (δ = 0 at a singular pose), F and Σ_F are not set."""
        n, observer, terms = self.n, self.observer, self.robot.terms
        jac = self._terms(q, qd, tau_m)
        observer.prepare(dt, qd, self.rows[R_P_PREV], q, terms.gravity.copy() if "g" in observer.needs else None)
        rotation = terms.ee_rotation.copy()
        outputs = np.empty(n), np.empty((n, n)), np.empty(6), np.empty((6, 6))
        flags = self._flags | POST
        if tare.averaging:      # the averaging takes this sample's untared τ̂ before the wrench (Tare.apply)
            self._run(self._flags | MOMENTUM | FILTER, dt, qd, tau_m, jac, rotation, *outputs)
            tare.apply(stamp, qd, observer.tau)
        else:
            tare.track(qd)
            flags |= MOMENTUM | FILTER
        if tare.active:
            flags |= TARED
        code, statistic, excess = estimate_step(flags, dt, qd, tau_m, *self._pinocchio, jac, rotation, *self._buffers,
                                                *outputs)             # not _run: one Python call less per sample
        weak, diverged = self.no_weak, code & DIVERGED != 0
        if code & WEAK:         # σ_min(J) < δ (docs/method.md §1.4.1): the directions and the damping bias
            tau, tau_cov, wrench, wrench_cov = outputs
            directions = np.empty((6, 6))
            count, finite = weak_wrench(jac, tau, tau_cov, self.params, rotation, self._flags & END_EFFECTOR != 0,
                                        wrench, wrench_cov, directions)
            weak, diverged = directions[:, :count], not finite
        return (code & SINGULAR != 0, diverged, statistic, excess) + outputs + (rotation, jac, weak)


_CODES = {"coulomb_friction": A_COULOMB, "viscous_friction": A_VISCOUS, "stribeck_friction": A_STRIBECK,
          "drive_gain": A_DRIVE_GAIN, "torque_offset": A_OFFSET, "position_ripple": A_RIPPLE}


def _augmentation_entries(augmentation: Augmentation) -> tuple[np.ndarray, ...]:
    """``augmentation_torque``'s arguments for ``augmentation.torque_effects``: one entry per effect and joint, in
    the order ``Augmentation.joint_torque`` adds them (codes, joints, params [ε, v_s or k], θ (m, 2))."""
    codes, joints, params, theta = [], [], [], []
    for effect in augmentation.torque_effects:
        variant = effect.variant
        second = variant.get("stribeck_velocity", variant.get("cycles_per_rev", 0.0))
        for row, joint in enumerate(effect.joints):
            codes.append(_CODES[effect.name])
            joints.append(int(joint))
            params.append((variant.get("epsilon", TANH_EPSILON), second))
            theta.append(np.pad(np.asarray(effect.theta[row], dtype=float), (0, 2 - effect.theta.shape[1])))
    return (np.array(codes, dtype=np.int64), np.array(joints, dtype=np.int64), np.array(params, dtype=float),
            np.array(theta, dtype=float))
