"""The compiled ``Estimator.step`` of one estimator (``filter.kernel: numba``): its buffers and the kernel calls.

``Estimator`` builds a ``CompiledStep`` when its observer is a ``KVARKKernelFilter`` and hands it every accepted
sample after the first: the pinocchio passes run from Python (``RobotModel.compute_terms``), the rest in one call
of ``step_kernel.estimate_step`` on buffers allocated here once; only the sample's outputs (τ̂, Cov τ̂, F, Σ_F, R)
are new arrays, because an ``Estimate`` is a snapshot its consumers keep (replay, the tests) or publish later (the
node's ``/diagnostics``). The numpy code in ``Estimator`` is the reference (docs/method.md; ``test/test_kernel.py``).
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.observers.kvark_kernel import KVARKKernelFilter
from kvark_ros.core.robot_model import RobotModel
from kvark_ros.core.step_kernel import (AUGMENTED, DIVERGED, E_DAMPING, E_PARAMS, E_STICTION_VELOCITY, E_Z,
                                        END_EFFECTOR, FILTER, MOMENTUM, POST, R_AUG, R_BAND, R_P_PREV, R_SCALE,
                                        R_U_PREV, ROWS, SCALED, STICTION, TARED, WEAK, estimate_step,
                                        finite_sample)
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
        """Take the run-time keys wrench.damping, wrench.frame, filter.stiction_velocity and
        filter.interval_calibration, and the collision's z."""
        velocity = config.filter.stiction_velocity
        self.params[E_DAMPING], self.params[E_STICTION_VELOCITY], self.params[E_Z] = (
            config.wrench.damping, velocity, z)
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
        self._run(self._flags | MOMENTUM | FILTER | POST, 0.002, zeros, zeros, self.robot.compute_terms(zeros, zeros),
                  np.eye(3), *outputs)
        self.observer.prediction = None

    def _terms(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
        """The sample's pinocchio passes (into ``robot.terms``) and τ_aug; returns J (6, n) in base axes."""
        jac = self.robot.compute_terms(q, qd)
        if self._augmentation is not None:
            self.rows[R_AUG] = self._augmentation.joint_torque(q, qd, tau_m)
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
        """One sample after the first: (weak, diverged, contact statistic, collision excess, τ̂, Cov τ̂, F, Σ_F, R, J),
        the arrays new (``estimate_step``'s outputs); ``tare`` averages or is tracked as in ``Tare.apply``."""
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
        return (code & WEAK != 0, code & DIVERGED != 0, statistic, excess) + outputs + (rotation, jac)
