"""``CompiledStep``: one ``Estimator``'s compiled step, its buffers and its kernel calls, for every observer.

Per accepted sample after the first, the pinocchio passes run from Python (``RobotModel.compute_terms``), then:
- the compiled K-VARK filter (``observers.kvark.KVARKFilter``) runs with the rest in one call of
  ``post.estimate_step`` (τ_aug, p and u, the KMP, the filter step, the post-step), reading the filter's packed
  state;
- any other observer steps in Python between two calls: the first computes p and u, the observer takes them
  (``Observer.step``), and the second runs the post-step on what it returned, copied into the buffer's rows.
The buffers are allocated here once; only the sample's outputs (τ̂, Cov τ̂, F, Σ_F, R, the weak directions) are new
arrays, because an ``Estimate`` is a snapshot its consumers keep (replay, the tests) or publish later (the node's
``/diagnostics``). The numpy reference of the whole step is test/core/reference_estimator.py.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.calibration import IntervalScale
from kvark_ros.core.estimation.compiled.layouts import ROWS, EstimatorParam, Flag, Option, Outcome, Row, pack
from kvark_ros.core.estimation.compiled.post import buffer_size, estimate_step, split_buffer
from kvark_ros.core.estimation.compiled.residual import NO_AUGMENTATION, pack_augmentation
from kvark_ros.core.estimation.observers.base import Observer
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.tare import Tare

# The bits ``step`` sets and tests, as plain ints: Python 3.11 reads an enum member through ``EnumType.__getattr__``,
# ~800 instructions a time (callgrind), where a module global costs a few.
_MOMENTUM, _KMP, _FILTER, _SHIFT, _POST, _TARED, _LOADED, _FULL = (int(bit) for bit in (
    Flag.MOMENTUM, Flag.KMP, Flag.FILTER, Flag.SHIFT, Flag.POST, Flag.TARED, Flag.LOADED, Flag.FULL))
_DIVERGED, _SINGULAR, _UNTESTED = (int(bit) for bit in (Outcome.DIVERGED, Outcome.SINGULAR, Outcome.UNTESTED))
# The K-VARK filter's arrays of ``estimate_step`` for any other observer: never read.
_NO_FILTER = (np.zeros(1), np.zeros(1, dtype=np.int64), np.zeros(1), np.zeros(len(Option), dtype=np.int64))
# The rows a sample writes (the others hold settings and the tare offset).
_TRANSIENT = [Row.P_PREV, Row.U_PREV, Row.P, Row.U, Row.AUG, Row.ESTIMATE, Row.VARIANCE, Row.MEAN, Row.VAR]


class CompiledStep:
    """The compiled step of one ``Estimator`` around its observer (module docstring).

    ``band``: the static friction band F_s (n,) N·m or None; ``scale``: the interval factors c and the floor, for the
    observer they were read for, or None; ``z``: the collision test's z; ``contact_kmp``: the trained KMP
    (``KMPResidualModel``) whose prediction the contact test adds for an observer without a residual model, or None.
    ``tare`` subtracts its offset from this step's buffer (``offset``, which the estimator gives its ``Tare``).
    The kernels compile (or load from numba's cache) here, on dummy data, so the first sample does not wait.
    """

    def __init__(self, robot: RobotModel, observer: Observer, band: np.ndarray | None, scale: IntervalScale | None,
                 config: EstimatorConfig, z: float, contact_kmp: object | None) -> None:
        n = self.n = robot.n
        self.robot, self.observer = robot, observer
        self._fused = bool(getattr(observer, "compiled", False))
        kmp = getattr(observer, "kmp", None) if self._fused else None
        residual = observer.uses_residual_model or contact_kmp is not None
        if not self._fused and not observer.uses_residual_model and contact_kmp is not None:
            kmp = contact_kmp.compiled.packed
        augmentation = robot.augmentation
        augmented = augmentation is not None and bool(augmentation.torque_effects)
        aug = pack_augmentation(augmentation) if augmented else NO_AUGMENTATION
        self._kmp_size = 0 if kmp is None else kmp.size
        # one buffer: its rows, params, a full P, the weak directions, a copy of the KMP and the augmentation
        self.buffer = np.concatenate([np.zeros(buffer_size(n)), np.zeros(0) if kmp is None else kmp, aug])
        self.buffer[ROWS * n + EstimatorParam.KMP_SIZE] = self._kmp_size
        self.rows, self.params, self.full, self.directions, _, _ = split_buffer.py_func(self.buffer, n)
        self.offset = self.rows[Row.OFFSET]
        self.no_weak = np.zeros((6, 0))                   # the weak directions at a regular pose (read-only, shared)
        self.no_weak.flags.writeable = False
        self._band, self._scale = band, scale
        if band is not None:
            self.rows[Row.BAND] = band
        if scale is not None:
            self.rows[Row.SCALE] = scale.scale
        # The flags of every call that never change for this estimator (configure adds the settings').
        self._fixed = ((Flag.AUGMENTED if augmented else 0) | (Flag.KMP if kmp is not None else 0)
                       | (Flag.COVARIANCE if observer.reports_covariance else 0)
                       | (Flag.FULL if observer.reports_covariance and not observer.diagonal_covariance else 0)
                       | (Flag.RESIDUAL if residual else 0)
                       | (Flag.COMPENSATED if observer.uses_residual_model else 0)
                       | (Flag.PACKED if self._fused else 0))
        self._needs_g = "g" in observer.needs
        terms = robot.terms
        filter_arrays = observer.kernel_arguments() if self._fused else _NO_FILTER
        # The arrays every call passes, bound once: none of them is ever replaced, only written in place.
        self._pinocchio = (terms.gravity, terms.rnea, terms.coriolis)
        self._models = (self.buffer,) + tuple(filter_arrays)
        self.configure(config, z)
        self._compile()

    def configure(self, config: EstimatorConfig, z: float) -> None:
        """Take the run-time keys wrench.*, filter.stiction_velocity, filter.interval_calibration,
        filter.interval_floor and contact.test_covariance, and the collision's z."""
        velocity, wrench = config.filter.stiction_velocity, config.wrench
        self.params[:] = pack(EstimatorParam, {
            EstimatorParam.DAMPING: wrench.damping, EstimatorParam.PRIOR_FORCE: wrench.prior_force,
            EstimatorParam.PRIOR_MOMENT: wrench.prior_moment, EstimatorParam.STICTION_VELOCITY: velocity,
            EstimatorParam.Z: z, EstimatorParam.KMP_SIZE: self._kmp_size})
        scale = self._scale
        if scale is not None:           # the floors in force: c_b² P_b in free motion, P_b under a load (§4.13)
            floored = config.filter.interval_floor == "kf"
            self.rows[Row.FLOOR_FREE] = scale.floor_for(False) if floored else 0.0
            self.rows[Row.FLOOR_LOADED] = scale.floor_for(True) if floored else 0.0
        scaled = scale is not None and config.filter.interval_calibration == "trained"
        self._flags = int(self._fixed
                          | (Flag.STICTION if self._band is not None and velocity != 0.0 else 0)
                          | (Flag.SCALED if scaled else 0)
                          | (Flag.TEST_REPORTED if scaled and config.contact.test_covariance == "reported" else 0)
                          | (Flag.END_EFFECTOR if config.wrench.frame != "base" else 0))

    def reset(self) -> None:
        """Forget the previous sample's p and u (a filter restart)."""
        self.rows[Row.P_PREV] = 0.0
        self.rows[Row.U_PREV] = 0.0

    def continue_from(self, other: CompiledStep) -> None:
        """Take over ``other``'s previous sample (p, u): a rebuilt estimator continuing."""
        self.rows[Row.P_PREV] = other.rows[Row.P_PREV]
        self.rows[Row.U_PREV] = other.rows[Row.U_PREV]

    def _compile(self) -> None:
        """One call of the kernel on dummy data (its machine code from numba's cache, or compiled); the caller resets
        the filter afterwards."""
        zeros, n = np.zeros(self.n), self.n
        jac = self.robot.compute_terms(zeros, zeros)
        flags = self._flags | _MOMENTUM | _SHIFT | _POST
        if self._fused:
            self.observer.prepare(0.002, zeros, zeros, zeros, zeros)
            flags |= _FILTER
        estimate_step(flags, 0.002, zeros, zeros, zeros, *self._pinocchio, jac, np.eye(3), *self._models,
                      np.empty(n), np.empty((n, n)), np.empty(6), np.empty((6, 6)))
        self.rows[_TRANSIENT] = 0.0

    def prime(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        """The first sample after a (re)start: p and u only, kept for the next sample."""
        n = self.n
        estimate_step((self._flags & ~_KMP) | _MOMENTUM | _SHIFT, 0.0, q, qd, tau_m, *self._pinocchio,
                      self.robot.compute_terms(q, qd), np.eye(3), *self._models, np.empty(n), np.empty((n, n)),
                      np.empty(6), np.empty((6, 6)))

    def step(self, stamp: float, dt: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, tare: Tare,
             loaded: bool) -> tuple:
        """One sample after the first: (singular, diverged, untested, contact statistic, collision excess, τ̂,
        Cov τ̂ or None, F, Σ_F or None, R, J, weak directions), the arrays new (a tuple: cheap per sample). ``tare``
        averages or is tracked as in ``Tare.apply`` (the kernel subtracts its offset); ``loaded``: the last sample's
        contact flag (the interval floor under a load, §4.13). ``singular``: J Jᵀ + δ² I is not positive definite
        (δ = 0 at a singular pose), F and Σ_F are not set; ``untested``: no S for the contact test."""
        n, observer, terms, rows = self.n, self.observer, self.robot.terms, self.rows
        jac = self.robot.compute_terms(q, qd)
        rotation = terms.ee_rotation.copy()
        outputs = np.empty(n), np.empty((n, n)), np.empty(6), np.empty((6, 6))
        flags = self._flags | (_LOADED if loaded else 0)
        pinocchio, models = self._pinocchio, self._models
        if self._fused:
            observer.prepare(dt, qd, rows[Row.P_PREV], q, terms.gravity.copy() if self._needs_g else None)
            if tare.averaging:      # the averaging takes this sample's untared τ̂ before the post-step (Tare.apply)
                estimate_step(flags | _MOMENTUM | _FILTER | _SHIFT, dt, q, qd, tau_m, *pinocchio, jac, rotation,
                              *models, *outputs)
                tare.apply(stamp, qd, observer.tau)
                flags = (flags & ~_KMP) | _POST
            else:
                tare.track(qd)
                flags |= _MOMENTUM | _FILTER | _SHIFT | _POST
        else:
            estimate_step((flags & ~_KMP) | _MOMENTUM, dt, q, qd, tau_m, *pinocchio, jac, rotation, *models,
                          *outputs)
            tau, cov = observer.step(dt, qd, rows[Row.P], rows[Row.P_PREV], rows[Row.U_PREV], q,
                                     terms.gravity.copy() if self._needs_g else None)
            if tare.averaging:      # the untared τ̂ (the kernel subtracts the offset)
                tare.apply(stamp, qd, tau)
            else:
                tare.track(qd)
            rows[Row.ESTIMATE] = tau
            if cov is not None:
                if flags & _FULL:
                    self.full[:] = cov
                else:
                    rows[Row.VARIANCE] = cov.diagonal()
            if observer.uses_residual_model:
                rows[Row.MEAN], rows[Row.VAR] = observer.prediction
            flags |= _SHIFT | _POST
        if tare.active:
            flags |= _TARED
        code, statistic, excess, k = estimate_step(flags, dt, q, qd, tau_m, *pinocchio, jac, rotation, *models,
                                                   *outputs)
        tau, tau_cov, wrench, wrench_cov = outputs
        if not observer.reports_covariance:
            tau_cov = wrench_cov = None
        return (code & _SINGULAR != 0, code & _DIVERGED != 0, code & _UNTESTED != 0, statistic, excess, tau, tau_cov,
                wrench, wrench_cov, rotation, jac, self.directions[:, :k].copy() if k else self.no_weak)
