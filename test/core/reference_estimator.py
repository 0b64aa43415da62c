"""The numpy reference of ``Estimator.step``'s post-step: a test oracle, not production code.

Production runs every observer's post-step compiled (``core/estimation/compiled/post.py``). This module keeps the same
equations as readable numpy (docs/method.md §1.4, §4.10-4.13, §7): the tare offset, the static friction band σ²_s,
the interval factors and floor, the wrench through the damped pseudo-inverse with the weak directions and their
damping bias, the contact test's S and statistic, the collision excess. ``ReferenceEstimator`` steps an observer
(the numpy K-VARK filter of reference_filter.py, or any other observer as it is) and does the rest here, so the
kernel's whole step can be pinned to it (test_compiled_step_matches_reference.py). Not collected as tests (no
``test_`` prefix); imported by the tests of test/core.
"""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.calibration import IntervalScale
from kvark_ros.core.estimation.estimator import Estimate, Estimator, Status
from kvark_ros.core.estimation.residual.kmp import KMPResidualModel
from kvark_ros.core.estimation.robot_model import RobotModel, WrenchSolution


def reference_predict(residual, qd: np.ndarray, q: np.ndarray | None = None,
                      g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A residual model's (mean, variance) (n,) at one sample, a KMP's by its numpy batch form
    (``KMPResidualModel.predict_batch``; its ``predict`` is the compiled kernel under test)."""
    if isinstance(residual, KMPResidualModel):
        mean, var = residual.predict_batch(qd[None], None if q is None else q[None], None if g is None else g[None])
        return mean[0], var[0]
    return residual.predict(qd, q, g) if getattr(residual, "needs", None) else residual.predict(qd)


def contact_covariance(tau_cov: np.ndarray | None, residual_mean: np.ndarray, residual_var: np.ndarray,
                       residual_compensated: bool) -> np.ndarray:
    """S of the contact test (core/estimation/contact.py): (n, n) from P (or None) and the residual model at q̇:
    P + diag σ²_r, or (P or 0) + diag(μ_r² + σ²_r) for an observer that does not subtract the residual."""
    extra = residual_var if residual_compensated else residual_var + residual_mean * residual_mean
    n = len(extra)
    covariance = np.zeros((n, n)) if tau_cov is None else np.array(tau_cov, dtype=float)
    covariance.flat[:: n + 1] += extra
    return covariance


def chi_square_statistic(tau: np.ndarray, covariance: np.ndarray) -> float | None:
    """``τᵀ S⁻¹ τ`` through a Cholesky factor (docs/method.md §7.1); ``None`` if S is not finite positive definite."""
    try:
        factor = np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        return None
    z = np.linalg.solve(factor, tau)
    value = float(z @ z)
    return value if math.isfinite(value) else None


def collision_excess(tau: np.ndarray, covariance: np.ndarray | None, z: float) -> float:
    """``max_j(|τ̂_j| − z σ_j)``, σ_j² = S_jj (0 without S; a NaN variance gives NaN) (docs/method.md §4.10)."""
    if covariance is None:
        return float(np.abs(tau).max())
    return float((np.abs(tau) - z * np.sqrt(np.maximum(np.diagonal(covariance), 0.0))).max())


def scaled_covariance(scale: IntervalScale, covariance: np.ndarray, floored: bool = True,
                      loaded: bool = False) -> np.ndarray:
    """diag(c) P diag(c), its diagonal raised to at least the floor in force with ``floored`` (docs/method.md §4.13)."""
    scaled = covariance * np.outer(scale.scale, scale.scale)
    if floored:
        diagonal = scaled.flat[:: len(scale.scale) + 1]
        scaled.flat[:: len(scale.scale) + 1] = np.maximum(diagonal, scale.floor_for(loaded))
    return scaled


def rotate_wrench(rotation: np.ndarray, wrench: np.ndarray, cov: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """A wrench (6,) or wrench directions (6, k), and a covariance, in other axes: F' = B F, Σ' = B Σ Bᵀ,
    B = diag(R, R)."""
    turned = np.concatenate((rotation @ wrench[:3], rotation @ wrench[3:]))
    if cov is None:
        return turned, None
    block = np.kron(np.eye(2), rotation)
    turned_cov = block @ cov @ block.T
    return turned, 0.5 * (turned_cov + turned_cov.T)


def solve_wrench(robot: RobotModel, q: np.ndarray, tau_ext: np.ndarray, tau_cov: np.ndarray | None, damping: float,
                 frame: str = "base", prior: tuple[float, float] | None = None) -> WrenchSolution:
    """``RobotModel.solve_wrench`` in numpy (docs/method.md §1.4-1.4.1): F = (J Jᵀ + δ² I)⁻¹ J τ, Σ_F = J⁺ P J⁺ᵀ, the
    left singular vectors with σ_i < δ and, with ``prior``, the damping bias B Σ_prior Bᵀ along them."""
    jac = robot.jacobian(q, frame)
    gram = jac @ jac.T
    delta2 = damping * damping
    pinv = np.linalg.solve(gram + delta2 * np.eye(6), jac)
    wrench = pinv @ tau_ext
    u, sigma, _ = np.linalg.svd(jac)
    sigma = np.concatenate((sigma, np.zeros(6 - sigma.size)))
    weak_mask = sigma < damping
    weak, strength = u[:, weak_mask], sigma[weak_mask]
    if tau_cov is None:
        return WrenchSolution(wrench, None, weak, jac)
    wrench_cov = pinv @ tau_cov @ pinv.T
    if prior is not None and weak.shape[1]:
        shrink = delta2 / (strength * strength + delta2)
        bias = (weak * shrink) @ weak.T
        wrench_cov += (bias * np.repeat(np.square(prior), 3)) @ bias
    return WrenchSolution(wrench, 0.5 * (wrench_cov + wrench_cov.T), weak, jac)


class ReferenceEstimator(Estimator):
    """``Estimator`` whose step after the input checks is numpy: p and u by ``RobotModel.momentum_terms``, the
    observer's step, then the post-step above (module docstring). Its input checks, counts, statuses and state
    transfer are the Estimator's own."""

    def reset(self) -> None:
        super().reset()
        self._p_prev = self._u_prev = None

    def continue_from(self, other: Estimator) -> None:
        super().continue_from(other)
        self._p_prev, self._u_prev = other._p_prev, other._u_prev

    def _prime(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        self._p_prev, self._u_prev = self.robot.momentum_terms(q, qd, tau_m)

    def step(self, stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> Estimate | None:
        dt = self._accept(stamp, q, qd, tau_m)
        return None if dt is None else self.numpy_step(stamp, dt, q, qd, tau_m)

    def numpy_step(self, stamp: float, dt: float, q: np.ndarray, qd: np.ndarray,
                   tau_m: np.ndarray) -> Estimate | None:
        """The numpy step of one accepted sample after the first."""
        n = self.robot.n
        p, u = self.robot.momentum_terms(q, qd, tau_m)
        p_prev, u_prev = self._p_prev, self._u_prev
        self._p_prev, self._u_prev = p, u
        needs = self.observer.needs | frozenset(getattr(self._contact_kmp, "needs", ()))
        g = self.robot.gravity(q) if "g" in needs else None
        tau_ext, tau_cov = self.observer.step(dt, qd, p, p_prev, u_prev, q, g)
        tau_ext = self.tare.apply(stamp, qd, tau_ext)
        trained = self.trained
        sticking = None
        if trained is not None and trained.stiction is not None and self.config.filter.stiction_velocity != 0.0:
            sticking = trained.stiction.variance(qd, self.config.filter.stiction_velocity)
        widened = reported = tau_cov
        scaled = False
        if tau_cov is not None:
            if sticking is not None:
                widened = tau_cov.copy()
                widened.flat[:: n + 1] += sticking                        # Cov τ̂ + diag σ²_s(q̇) (§4.11)
            reported = widened
            scale = self._reference_scale
            if scale is not None and self.config.filter.interval_calibration == "trained":
                reported = scaled_covariance(scale, tau_cov, self.config.filter.interval_floor == "kf",
                                             self.contact.flag)           # (§4.13)
                if sticking is not None:
                    reported.flat[:: n + 1] += sticking
                scaled = True
        settings = self.config.wrench
        solution = solve_wrench(self.robot, q, tau_ext, reported, settings.damping, "base",
                                (settings.prior_force, settings.prior_moment))
        wrench, wrench_cov, weak = solution.wrench, solution.cov, solution.weak
        rotation = self.robot.terms.ee_rotation.copy()
        if settings.frame != "base":
            wrench, wrench_cov = rotate_wrench(rotation.T, wrench, wrench_cov)
            if weak.shape[1]:
                weak = rotate_wrench(rotation.T, weak)[0]
        total = tau_ext.sum() + (0.0 if tau_cov is None else reported.sum() + wrench_cov.sum())
        if not np.isfinite(total):
            self.reset()
            self._reject(Status.DIVERGED_RESET)
            return None
        self.status = Status.OK
        self.counts[Status.OK] += 1
        covariance = self._test_covariance(q, qd, g, widened, sticking)
        tested = reported if scaled and self.config.contact.test_covariance == "reported" else covariance
        contact = (self.contact.flag if tested is None
                   else self.contact.decide(stamp, chi_square_statistic(tau_ext, tested)))
        if sticking is not None and covariance is not None:
            covariance = covariance.copy()
            covariance.flat[:: n + 1] -= sticking                         # the collision keeps σ unwidened
        collision = self.collision.decide(collision_excess(tau_ext, covariance, self.collision.z))
        if weak.shape[1]:
            self.unobservable_samples += 1
        return Estimate(stamp, tau_ext, reported, wrench, wrench_cov, contact, collision, settings.frame, rotation,
                        solution.jacobian, weak)

    @property
    def _contact_kmp(self):
        trained = self.trained
        return None if self.observer.uses_residual_model or trained is None else trained.residual

    @property
    def _reference_scale(self) -> IntervalScale | None:
        trained = self.trained
        return trained.interval_scale if trained is not None and self.observer.name == "kvark" else None

    def _test_covariance(self, q: np.ndarray, qd: np.ndarray, g: np.ndarray | None, tau_cov: np.ndarray | None,
                         sticking: np.ndarray | None) -> np.ndarray | None:
        """S of the contact and collision tests (core/estimation/contact.py), ``tau_cov`` already widened."""
        if self.observer.uses_residual_model:
            mean, variance = self.observer.prediction
        elif self._contact_kmp is not None:
            mean, variance = reference_predict(self._contact_kmp, qd, q, g)
        else:
            return tau_cov
        if tau_cov is None and sticking is not None:
            variance = variance + sticking
        return contact_covariance(tau_cov, mean, variance, self.observer.uses_residual_model)


__all__ = ["ReferenceEstimator", "reference_predict", "chi_square_statistic", "collision_excess", "contact_covariance", "rotate_wrench",
           "scaled_covariance", "solve_wrench"]
