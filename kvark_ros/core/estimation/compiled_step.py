"""The compiled ``Estimator.step`` of one estimator (momentum-form K-VARK): its buffers and the kernel calls.

``Estimator`` builds a ``CompiledStep`` when its observer is a ``KVARKKernelFilter`` and hands it every accepted
sample after the first: the pinocchio passes run from Python (``RobotModel.compute_terms``), the rest in one call
of ``step_kernel.estimate_step`` on buffers allocated here once (and ``weak_wrench`` at a pose with a direction the
joints cannot sense); only the sample's outputs (τ̂, Cov τ̂, F, Σ_F, R, the weak directions) are new arrays, because
an ``Estimate`` is a snapshot its consumers keep (replay, the tests) or publish later (the node's ``/diagnostics``).
The numpy code in ``Estimator`` is the reference (docs/method.md;
``test/core/test_compiled_step_matches_reference.py``).

``estimate_step`` computes, in the reference's order:
- p = rnea(q, 0, q̇) − g = M q̇ (eq. 5) and u = Cᵀ q̇ − g + τ_m (− τ_aug) (eq. 7) from pinocchio's outputs (§2.1);
- the filter step ``kvark_step`` on (h, q̇_k, p_k, u_{k−1}) (§4.2-4.7);
- the tare offset (§4.10), the static friction band σ²_s(q̇) on Cov τ̂ (§4.11) and the interval factors c on the
  reported Cov τ̂ = diag(c) P diag(c) + diag σ²_s (§4.13; the tests keep P + diag σ²_s);
- the wrench ``F = J⁺ τ̂``, ``J⁺ = (J Jᵀ + δ² I)⁻¹ J`` and ``Σ_F = J⁺ P J⁺ᵀ`` (§1.4), with one Cholesky of
  ``J Jᵀ − δ² I`` deciding whether some σ_i < δ (§1.4.1): then the caller adds ``weak_wrench``, which takes J's
  SVD for the weak directions and adds the damping bias to Σ_F (a third of random Panda poses, most of the UR5's
  bench stream);
- the contact statistic ``τ̂ᵀ S⁻¹ τ̂`` (§7.1-7.2) and the collision excess ``max_j(|τ̂_j| − z σ_j)`` (§4.10).
The K-VARK momentum filter's P is diagonal (joints are independent 2-state filters, §4.2), so Cov τ̂, S and the
collision's σ are diagonal: S's Cholesky factor is diag(√S_jj), and ``J⁺ P J⁺ᵀ = Σ_j P_jj J⁺_j J⁺_jᵀ``.

Differences from the reference are rounding only (≤ 1e-14 of each quantity's largest value on the committed bags):
sums run in another order than BLAS's, ``exp`` is libm's, the Cholesky factors are ours rather than LAPACK's (a pose
whose smallest σ equals δ to ~1e-16 could be called regular by one and weak by the other).
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.effect_catalog import TORQUE_EFFECTS
from kvark_ros.core.estimation.augmentation import Augmentation
from kvark_ros.core.estimation.calibration import IntervalScale
from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.model_kernels import augmentation_torque
from kvark_ros.core.estimation.observers.kvark_kernel import KVARKKernelFilter
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.kernel_layouts import (ESTIMATOR_PARAMS, ROWS, Effect, EstimatorParam, Flag, Outcome,
                                                      Row, pack)
from kvark_ros.core.estimation.input_kernels import finite_sample
from kvark_ros.core.estimation.step_kernel import estimate_step, weak_wrench
from kvark_ros.core.estimation.tare import Tare

# The bits ``step`` sets and tests, as plain ints: Python 3.11 reads an enum member through ``EnumType.__getattr__``,
# ~800 instructions a time (callgrind), where a module global costs a few.
_MOMENTUM_FILTER, _POST, _TARED, _END_EFFECTOR = (int(bits) for bits in (
    Flag.MOMENTUM | Flag.FILTER, Flag.POST, Flag.TARED, Flag.END_EFFECTOR))
_WEAK, _DIVERGED, _SINGULAR = (int(bit) for bit in (Outcome.WEAK, Outcome.DIVERGED, Outcome.SINGULAR))
# ``augmentation_torque``'s code of every torque effect of the catalog: the ``Effect`` member of its name in upper case
EFFECT_CODES = {name: int(Effect[name.upper()]) for name in TORQUE_EFFECTS}


class CompiledStep:
    """The compiled step of one ``Estimator`` around its ``KVARKKernelFilter``: buffers, constants and the calls.

    ``previous`` (p_{k−1}, u_{k−1}) are views of its buffer, which the Estimator keeps as its own; ``configure``
    takes the run-time keys (``Estimator.configure`` calls it). The kernels compile (or load from numba's cache)
    here, on dummy data, so the first sample does not wait; the caller resets the filter afterwards.
    """

    finite = staticmethod(finite_sample)

    def __init__(self, robot: RobotModel, observer: KVARKKernelFilter, tare: Tare, band: np.ndarray | None,
                 scale: IntervalScale | None, config: EstimatorConfig, z: float) -> None:
        """``band``: the static friction band F_s (n,) N·m or None; ``scale``: the interval factors c and floor P_b
        or None; ``z``: the collision test's z."""
        n = self.n = robot.n
        self.robot, self.observer = robot, observer
        self.rows = np.zeros((ROWS, n))
        self.previous = self.rows[Row.P_PREV], self.rows[Row.U_PREV]
        self.params = np.zeros(ESTIMATOR_PARAMS)
        self.no_weak = np.zeros((6, 0))
        self.no_weak.flags.writeable = False
        augmentation = robot.augmentation
        self._augmentation = augmentation if augmentation is not None and augmentation.torque_effects else None
        # augmentation_torque's arguments after q, q̇, τ_m, bound once
        self._aug_arguments = (None if self._augmentation is None
                               else (*augmentation_entries(self._augmentation), self.rows[Row.AUG]))
        self._band, self._scale = band, scale
        self._floored, self._loaded = False, False
        if band is not None:
            self.rows[Row.BAND] = band
        if scale is not None:
            self.rows[Row.SCALE] = scale.scale
        terms, packed = robot.terms, observer.packed
        # The arrays every call passes, bound once: none of them is ever replaced, only written in place.
        self._pinocchio = (terms.gravity, terms.rnea, terms.coriolis)
        self._buffers = (self.rows, tare.offset, self.params, packed.flat, packed.ints, observer.constants,
                         observer.options)
        self.configure(config, z)
        self._compile()

    def configure(self, config: EstimatorConfig, z: float) -> None:
        """Take the run-time keys wrench.*, filter.stiction_velocity, filter.interval_calibration,
        filter.interval_floor and contact.test_covariance, and the collision's z."""
        velocity, wrench = config.filter.stiction_velocity, config.wrench
        self.params[:] = pack(EstimatorParam, {
            EstimatorParam.DAMPING: wrench.damping, EstimatorParam.PRIOR_FORCE: wrench.prior_force,
            EstimatorParam.PRIOR_MOMENT: wrench.prior_moment, EstimatorParam.STICTION_VELOCITY: velocity,
            EstimatorParam.Z: z})
        self._floored = config.filter.interval_floor == "kf"
        self._set_floor()
        scaled = self._scale is not None and config.filter.interval_calibration == "trained"
        self._flags = ((Flag.STICTION if self._band is not None and velocity != 0.0 else 0)
                       | (Flag.SCALED if scaled else 0)
                       | (Flag.TEST_REPORTED if scaled and config.contact.test_covariance == "reported" else 0)
                       | (Flag.END_EFFECTOR if config.wrench.frame != "base" else 0)
                       | (Flag.AUGMENTED if self._augmentation is not None else 0))

    def load(self, loaded: bool) -> None:
        """The floor of the samples to come: P_b while the contact test holds a load, c_b² P_b in free motion
        (docs/method.md §4.13); the row is written only when that changes."""
        if loaded != self._loaded:
            self._loaded = loaded
            self._set_floor()

    def _set_floor(self) -> None:
        """Row.FLOOR: the floor in force, or none (zeros) with filter.interval_floor off."""
        if self._scale is not None:
            self.rows[Row.FLOOR] = self._scale.floor_for(self._loaded) if self._floored else 0.0

    def _compile(self) -> None:
        """One call of each kernel on dummy data (its machine code from numba's cache, or compiled)."""
        zeros = np.zeros(self.n)
        finite_sample(0.0, zeros, zeros, zeros)
        self.prime(zeros, zeros, zeros)
        self.observer.prepare(0.002, zeros, zeros, zeros, zeros)
        outputs = np.empty(self.n), np.empty((self.n, self.n)), np.empty(6), np.empty((6, 6))
        jac = self.robot.compute_terms(zeros, zeros)
        self._run(self._flags | Flag.MOMENTUM | Flag.FILTER | Flag.POST, 0.002, zeros, zeros, jac, np.eye(3), *outputs)
        weak_wrench(jac, zeros, np.eye(self.n), self.params, np.eye(3), False, *outputs[2:], np.empty((6, 6)))
        self.observer.prediction = None

    def _terms(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
        """The sample's pinocchio passes (into ``robot.terms``) and τ_aug; returns J (6, n) in base axes."""
        jac = self.robot.compute_terms(q, qd)
        if self._aug_arguments is not None:
            augmentation_torque(q, qd, tau_m, *self._aug_arguments)
        return jac

    def _run(self, flags: int, dt: float, qd: np.ndarray, tau_m: np.ndarray, jac: np.ndarray, rotation: np.ndarray,
             *outputs: np.ndarray) -> tuple[int, float, float]:
        """``estimate_step`` with this estimator's buffers; ``outputs``: τ̂ (n,), Cov τ̂ (n, n), F (6,), Σ_F (6, 6)."""
        return estimate_step(flags, dt, qd, tau_m, *self._pinocchio, jac, rotation, *self._buffers, *outputs)

    def prime(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        """The first sample after a (re)start: p and u only, kept for the next sample."""
        n = self.n
        self._run(self._flags | Flag.MOMENTUM, 0.0, qd, tau_m, self._terms(q, qd, tau_m), np.eye(3), np.empty(n),
                  np.empty((n, n)), np.empty(6), np.empty((6, 6)))

    def step(self, stamp: float, dt: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, tare: Tare) -> tuple:
        """One sample after the first: (singular, diverged, contact statistic, collision excess, τ̂, Cov τ̂, F, Σ_F,
        R, J, weak directions), the arrays new; ``tare`` averages or is tracked as in ``Tare.apply``. ``singular``:
        J Jᵀ + δ² I is not positive definite (δ = 0 at a singular pose), F and Σ_F are not set."""
        n, observer, terms = self.n, self.observer, self.robot.terms
        jac = self._terms(q, qd, tau_m)
        observer.prepare(dt, qd, self.previous[0], q, terms.gravity.copy() if "g" in observer.needs else None)
        rotation = terms.ee_rotation.copy()
        outputs = np.empty(n), np.empty((n, n)), np.empty(6), np.empty((6, 6))
        flags = self._flags | _POST
        if tare.averaging:      # the averaging takes this sample's untared τ̂ before the wrench (Tare.apply)
            self._run(self._flags | _MOMENTUM_FILTER, dt, qd, tau_m, jac, rotation, *outputs)
            tare.apply(stamp, qd, observer.tau)
        else:
            tare.track(qd)
            flags |= _MOMENTUM_FILTER
        if tare.active:
            flags |= _TARED
        code, statistic, excess = estimate_step(flags, dt, qd, tau_m, *self._pinocchio, jac, rotation, *self._buffers,
                                                *outputs)             # not _run: one Python call less per sample
        weak, diverged = self.no_weak, code & _DIVERGED != 0
        if code & _WEAK:         # σ_min(J) < δ (docs/method.md §1.4.1): the directions and the damping bias
            tau, tau_cov, wrench, wrench_cov = outputs
            directions = np.empty((6, 6))
            count, finite = weak_wrench(jac, tau, tau_cov, self.params, rotation,
                                        self._flags & _END_EFFECTOR != 0, wrench, wrench_cov, directions)
            weak, diverged = directions[:, :count], not finite
        return (code & _SINGULAR != 0, diverged, statistic, excess) + outputs + (rotation, jac, weak)


def augmentation_entries(augmentation: Augmentation) -> tuple[np.ndarray, ...]:
    """``augmentation_torque``'s arguments for ``augmentation.torque_terms()``, one entry per effect and joint in the
    order ``Augmentation.joint_torque`` adds them: codes (``Effect``), joints, params [ε, v_s or k], θ (m, 2)."""
    terms = augmentation.torque_terms()
    return (np.array([EFFECT_CODES[term.name] for term in terms], dtype=np.int64),
            np.array([term.joint for term in terms], dtype=np.int64),
            np.array([(term.epsilon, term.second) for term in terms], dtype=float),
            np.array([term.theta for term in terms], dtype=float))
