"""``estimate_step``: everything of ``Estimator.step`` but the input checks and the pinocchio passes, compiled, for
every observer.

One call per sample computes, in this order, what ``flags`` ask for (``Flag``):
- MOMENTUM: τ_aug (``residual.augmentation_torque``, with AUGMENTED), p = rnea(q, 0, q̇) − g = M q̇ (eq. 5) and
  u = Cᵀ q̇ − g + τ_m − τ_aug (eq. 7, §2.1-2.2) from pinocchio's outputs;
- KMP: the KMP residual's μ_*, σ²_* at this sample (``residual.kmp_predict``);
- FILTER: the K-VARK filter step (``kvark_filter.kvark_step``) on (h, q̇_k, p_k, u_{k−1}); SHIFT keeps p_k, u_k;
- POST, the post-step, on what the observer hands over: τ̂, its covariance P (diagonal, full or none) and the
  residual's μ_r, σ²_r, read from the packed filter state (PACKED: the compiled K-VARK filter) or from the buffer's
  rows ESTIMATE, VARIANCE, MEAN, VAR and its full P (any other observer, ``step.CompiledStep``):
  the tare offset (§4.10); the static friction band σ²_s(q̇) on Cov τ̂ (§4.11); the interval factors c of the
  reported Cov τ̂ = diag(c) P diag(c), at least the floor, + diag σ²_s (§4.13; the tests keep P + diag σ²_s); the
  wrench F = J⁺ τ̂ and Σ_F = J⁺ P J⁺ᵀ with the weak directions and their damping bias (the wrench kernels'
  ``solve_wrench``, §1.4-1.4.1); the contact statistic τ̂ᵀ S⁻¹ τ̂ with S = P + diag σ²_s + diag σ²_r (+ diag μ_r²
  for an observer that does not subtract the residual; or the reported covariance with TEST_REPORTED; §7.1-7.2) and
  the collision excess
  max_j(|τ̂_j| − z σ_j), σ_j² = S_jj − σ²_s,j (§4.10).

The numpy reference of the post-step is test/core/reference_estimator.py; the two differ by rounding only (sums run
in another order than BLAS's, ``exp`` is libm's, the Cholesky factors are ours).
"""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.estimation.compiled.jit import jit
from kvark_ros.core.estimation.compiled.kvark_filter import kvark_step, split_state
from kvark_ros.core.estimation.compiled.layouts import (ESTIMATOR_PARAMS, ROWS, EstimatorParam, Flag, Option,
                                                        Outcome, Row, Vec)
from kvark_ros.core.estimation.compiled.residual import augmentation_torque, kmp_predict
from kvark_ros.core.estimation.compiled.wrench import cholesky, solve_wrench

PINS = {"layouts.py": "b567b01b443f6eb37b6883fed944593a9449df4a179e52a7f83d6a575b5beb9f",
        "kvark_filter.py": "64529901f0cc1972d92341f6b5544027e22237b4d1f32dd0926d6a2f24a6ae7b",
        "residual.py": "c31ae5ae6f4c7085292dc0aea07e9d728bbebaac379c6722ba134a197ea9e288",
        "wrench.py": "a4d88c78d93b9eb29276ee68e6a0c511cf5aa3448bdcced3de037c4c86c5de80"}


@jit
def split_buffer(buffer: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                       np.ndarray]:
    """Views of the estimator's packed buffer: rows (ROWS, n) (``Row``), params (ESTIMATOR_PARAMS,)
    (``EstimatorParam``), an observer's full P (n, n), the weak wrench directions (6, 6), then the trained model's
    packed KMP (``residual.pack_kmp``, params[KMP_SIZE] long) and packed augmentation (``residual.pack_augmentation``,
    the rest). ``split_buffer.py_func`` gives the same views in Python (``step.CompiledStep``)."""
    end_rows = ROWS * n
    end_params = end_rows + ESTIMATOR_PARAMS
    end_full = end_params + n * n
    end_directions = end_full + 36
    end_kmp = end_directions + int(buffer[end_rows + EstimatorParam.KMP_SIZE])
    return (buffer[:end_rows].reshape((ROWS, n)), buffer[end_rows:end_params],
            buffer[end_params:end_full].reshape((n, n)), buffer[end_full:end_directions].reshape((6, 6)),
            buffer[end_directions:end_kmp], buffer[end_kmp:])


def buffer_size(n: int) -> int:
    """Length of the estimator's packed buffer of n joints before its KMP and augmentation (``split_buffer``)."""
    return ROWS * n + ESTIMATOR_PARAMS + n * n + 36


@jit
def _momentum(qd: np.ndarray, tau_m: np.ndarray, gravity: np.ndarray, rnea: np.ndarray, coriolis: np.ndarray,
              rows: np.ndarray, augmented: bool) -> None:
    """p and u of one sample into rows Row.P, Row.U (docs/method.md §2.1)."""
    n = qd.shape[0]
    for j in range(n):
        rows[Row.P, j] = rnea[j] - gravity[j]                          # eq. 5: rnea(q, 0, q̇) − g = M q̇
        ctq = 0.0
        for i in range(n):
            ctq += coriolis[i, j] * qd[i]                              # (Cᵀ q̇)_j
        rows[Row.U, j] = ctq - gravity[j] + tau_m[j]                   # eq. 7
        if augmented:
            rows[Row.U, j] -= rows[Row.AUG, j]                         # τ_m − τ_aug (§2.2)


@jit
def _statistic(tau: np.ndarray, s: np.ndarray) -> float:
    """τ̂ᵀ S⁻¹ τ̂ = ‖L⁻¹ τ̂‖², L Lᵀ = S (n, n) (§7.1); NaN when S is not positive definite."""
    n = tau.shape[0]
    factor, solved = np.empty((n, n)), np.empty(n)
    if not cholesky(s, factor):
        return np.nan
    total = 0.0
    for j in range(n):
        value = tau[j]
        for k in range(j):
            value -= factor[j, k] * solved[k]
        solved[j] = value / factor[j, j]
        total += solved[j] * solved[j]
    return total


@jit
def _post_full(flags: int, qd: np.ndarray, tau: np.ndarray, cov: np.ndarray, mean: np.ndarray, var: np.ndarray,
               rows: np.ndarray, params: np.ndarray, tau_cov: np.ndarray) -> tuple[float, float, float]:
    """The post-step's Cov τ̂ and tests for an observer with a full P ``cov`` (n, n) (FULL; module docstring): the
    reported Cov τ̂ into ``tau_cov``; returns (contact statistic, collision excess, sum of Cov τ̂)."""
    n = tau.shape[0]
    band, factors = rows[Row.BAND], rows[Row.SCALE]
    floor = rows[Row.FLOOR_LOADED] if flags & Flag.LOADED else rows[Row.FLOOR_FREE]
    velocity, z = params[EstimatorParam.STICTION_VELOCITY], params[EstimatorParam.Z]
    sticking, s = np.zeros(n), np.empty((n, n))
    for i in range(n):
        if flags & Flag.STICTION:
            ratio = qd[i] / velocity
            sticking[i] = band[i] * band[i] / 3.0 * np.exp(-(ratio * ratio))  # σ²_s (§4.11)
        for j in range(n):
            s[i, j] = cov[i, j]                                                 # the tests' P + diag σ²_s
            tau_cov[i, j] = cov[i, j] * (factors[i] * factors[j]) if flags & Flag.SCALED else cov[i, j]
    total = 0.0
    for j in range(n):
        s[j, j] += sticking[j]
        if flags & Flag.SCALED:
            if tau_cov[j, j] < floor[j]:
                tau_cov[j, j] = floor[j]                                        # diag(c) P diag(c) ≥ floor (§4.13)
            tau_cov[j, j] += sticking[j]
        else:
            tau_cov[j, j] = s[j, j]
        if flags & Flag.RESIDUAL:                                               # + diag σ²_r (+ μ_r²) (§7)
            s[j, j] += var[j] if flags & Flag.COMPENSATED else var[j] + mean[j] * mean[j]
        for k in range(n):
            total += tau_cov[j, k]
    tested = tau_cov if flags & Flag.TEST_REPORTED else s
    excess = -np.inf
    for j in range(n):
        unwidened = s[j, j] - sticking[j]                                       # the collision keeps σ unwidened
        if unwidened < 0.0:                                                     # max(·, 0); a NaN stays NaN
            unwidened = 0.0
        joint = abs(tau[j]) - z * math.sqrt(unwidened)                          # |τ̂_j| − z σ_j (§4.10)
        if math.isnan(joint) or joint > excess:
            excess = joint
    return _statistic(tau, tested), excess, total


@jit
def estimate_step(flags: int, dt: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, gravity: np.ndarray,
                  rnea: np.ndarray, coriolis: np.ndarray, jac: np.ndarray, rotation: np.ndarray, buffer: np.ndarray,
                  state: np.ndarray, ints: np.ndarray, constants: np.ndarray, options: np.ndarray, tau: np.ndarray,
                  tau_cov: np.ndarray, wrench: np.ndarray, wrench_cov: np.ndarray) -> tuple[int, float, float, int]:
    """One ``Estimator.step`` after its input checks and pinocchio passes (module docstring).

    ``flags``: ``Flag`` bits. ``q`` (n,) rad, ``qd`` (n,) rad/s, ``tau_m`` (n,) N·m: the sample; ``gravity`` g,
    ``rnea`` = M q̇ + g, ``coriolis`` C, ``jac`` J (6, n) in base axes, ``rotation`` R (3, 3) of the ee axes:
    pinocchio's
    outputs. ``buffer``: the estimator's (``split_buffer``: rows, params δ, wrench prior, v_s, z, an observer's full P,
    the weak directions, the packed KMP for KMP and the packed augmentation for AUGMENTED); ``state``, ``ints``, ``constants``, ``options``: the K-VARK filter's
    (``kvark_filter``) for FILTER and PACKED. Outputs of POST: τ̂ (n,), Cov τ̂ (n, n), F (6,), Σ_F (6, 6).
    Returns
    (code: ``Outcome`` bits WEAK | DIVERGED | SINGULAR | UNTESTED, the contact statistic (NaN: S not positive
    definite), the collision excess (NaN: not finite), the number k of weak directions, in the buffer's first k
    columns); with SINGULAR, F and Σ_F are not set.
    """
    n = qd.shape[0]
    rows, params, full, directions, kmp, aug = split_buffer(buffer, n)
    if flags & Flag.PACKED:
        vec = split_state(state, n, options[Option.SNAPSHOTS], options[Option.ONSETS])[0]
        estimate, variance_in, mean, var = vec[Vec.TAU], vec[Vec.C], vec[Vec.MEAN], vec[Vec.VAR]
    else:
        estimate, variance_in, mean, var = rows[Row.ESTIMATE], rows[Row.VARIANCE], rows[Row.MEAN], rows[Row.VAR]
    if flags & Flag.MOMENTUM:
        if flags & Flag.AUGMENTED:
            augmentation_torque(q, qd, tau_m, aug, rows[Row.AUG])
        _momentum(qd, tau_m, gravity, rnea, coriolis, rows, flags & Flag.AUGMENTED != 0)
    if flags & Flag.KMP:
        kmp_predict(qd, q, gravity, kmp, mean, var)                             # eqs. 21-23
    if flags & Flag.FILTER:
        kvark_step(dt, qd, rows[Row.P], rows[Row.U_PREV], state, ints, constants, options)
    if flags & Flag.SHIFT:
        rows[Row.P_PREV, :] = rows[Row.P]
        rows[Row.U_PREV, :] = rows[Row.U]
    if not flags & Flag.POST:
        return 0, np.nan, np.nan, 0
    offset, band, factors = rows[Row.OFFSET], rows[Row.BAND], rows[Row.SCALE]
    floor = rows[Row.FLOOR_LOADED] if flags & Flag.LOADED else rows[Row.FLOOR_FREE]
    velocity, z = params[EstimatorParam.STICTION_VELOCITY], params[EstimatorParam.Z]
    covariance, residual = flags & Flag.COVARIANCE != 0, flags & Flag.RESIDUAL != 0
    variance = np.zeros(n)
    tau_cov[:, :] = 0.0
    statistic, excess, total, definite = 0.0, -np.inf, 0.0, True
    for j in range(n):
        tau[j] = estimate[j] - offset[j] if flags & Flag.TARED else estimate[j]  # τ̂ − offset (§4.10)
    if flags & Flag.FULL:
        statistic, excess, total = _post_full(flags, qd, tau, full, mean, var, rows, params, tau_cov)
        for j in range(n):
            total += tau[j]
    else:
        for j in range(n):
            sticking, widened = 0.0, variance_in[j] if covariance else 0.0      # P = diag (§4.2)
            if flags & Flag.STICTION:
                ratio = qd[j] / velocity
                sticking = band[j] * band[j] / 3.0 * np.exp(-(ratio * ratio))   # σ²_s = F_s²/3 e^{−(q̇/v_s)²} (§4.11)
            if covariance:
                if flags & Flag.STICTION:
                    widened += sticking
                variance[j] = widened                                           # reported Cov τ̂, Σ_F's source
                if flags & Flag.SCALED:
                    scaled = variance_in[j] * (factors[j] * factors[j])         # diag(c) P diag(c) (§4.13)
                    if scaled < floor[j]:
                        scaled = floor[j]                                       # at least the floor (§4.13)
                    variance[j] = scaled + sticking                             # + σ²_s
                tau_cov[j, j] = variance[j]
                total += tau[j] + variance[j]
            else:
                total += tau[j]
            if residual:                                                        # S = P + diag σ²_r (§7.2)
                extra = var[j] + sticking if not covariance else var[j]         # no P: σ²_s joins σ²_r
                s_jj = widened + (extra if flags & Flag.COMPENSATED else extra + mean[j] * mean[j])
            elif covariance:
                s_jj = widened
            else:
                s_jj = sticking                                                 # no S: σ = 0 for the collision
            s_test = variance[j] if flags & Flag.TEST_REPORTED else s_jj       # or the reported Cov τ̂ (§7.2)
            if s_test > 0.0:
                scaled = tau[j] / math.sqrt(s_test)                             # L⁻¹ τ̂, L = diag(√S_jj)
                statistic += scaled * scaled                                    # d² = τ̂ᵀ S⁻¹ τ̂ (§7.1)
            else:
                definite = False
            unwidened = s_jj - sticking if flags & Flag.STICTION else s_jj      # the collision keeps σ unwidened
            if unwidened < 0.0:                                                 # max(·, 0); a NaN stays NaN
                unwidened = 0.0
            joint = abs(tau[j]) - z * math.sqrt(unwidened)                      # |τ̂_j| − z σ_j (§4.10)
            if math.isnan(joint) or joint > excess:                             # a NaN stays: the flag holds
                excess = joint
        if not (definite and math.isfinite(statistic)):
            statistic = np.nan
    code, k = solve_wrench(jac, tau, variance, tau_cov, flags & Flag.FULL != 0, params, rotation,
                           flags & Flag.END_EFFECTOR != 0, wrench, wrench_cov, directions)
    if covariance:
        for a in range(6):
            for b in range(6):
                total += wrench_cov[a, b]
    code |= 0 if math.isfinite(total) else Outcome.DIVERGED
    if not (covariance or residual):
        code |= Outcome.UNTESTED
    return code, statistic, excess, k
