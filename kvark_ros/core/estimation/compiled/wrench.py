"""The wrench from τ̂, compiled: F = J⁺ τ̂ and Σ_F = J⁺ P J⁺ᵀ through the damped pseudo-inverse (docs/method.md §1.4),
with the directions the joints cannot sense and the damping bias along them (§1.4.1): ``solve_wrench``.

``RobotModel.solve_wrench`` and the compiled step (``post``) call it. The Cholesky factors are this file's own, so a
pose whose smallest σ equals δ to ~1e-16 could be called regular here and weak by LAPACK.
"""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.estimation.compiled.jit import jit
from kvark_ros.core.estimation.compiled.layouts import EstimatorParam, Outcome

PINS = {"layouts.py": "b567b01b443f6eb37b6883fed944593a9449df4a179e52a7f83d6a575b5beb9f"}


@jit
def cholesky(a: np.ndarray, factor: np.ndarray) -> bool:
    """The lower Cholesky factor of the symmetric (m, m) ``a`` into ``factor``; False if ``a`` is not positive
    definite (a pivot ≤ 0 or NaN), as LAPACK's dpotrf."""
    m = a.shape[0]
    for j in range(m):
        pivot = a[j, j]
        for k in range(j):
            pivot -= factor[j, k] * factor[j, k]
        if not pivot > 0.0:
            return False
        root = math.sqrt(pivot)
        factor[j, j] = root
        for i in range(j + 1, m):
            value = a[i, j]
            for k in range(j):
                value -= factor[i, k] * factor[j, k]
            factor[i, j] = value / root
        for i in range(j):
            factor[i, j] = 0.0
    return True


@jit
def _gram(jac: np.ndarray) -> np.ndarray:
    """J Jᵀ (6, 6) of J (6, n)."""
    gram = np.empty((6, 6))
    for a in range(6):
        for b in range(a + 1):
            value = 0.0
            for k in range(jac.shape[1]):
                value += jac[a, k] * jac[b, k]
            gram[a, b] = gram[b, a] = value
    return gram


@jit
def _pseudo_inverse(jac: np.ndarray, gram: np.ndarray, delta2: float, pinv: np.ndarray) -> bool:
    """J⁺ = (J Jᵀ + δ² I)⁻¹ J (6, n) into ``pinv`` (v2 eq. 39) from ``gram`` = J Jᵀ, through a Cholesky factor;
    False when J Jᵀ + δ² I is not positive definite (δ = 0 at a singular pose)."""
    n = jac.shape[1]
    damped, factor = gram.copy(), np.empty((6, 6))
    for a in range(6):
        damped[a, a] += delta2
    if not cholesky(damped, factor):
        return False
    for k in range(n):                                                 # L Lᵀ X = J, column by column
        for a in range(6):
            value = jac[a, k]
            for b in range(a):
                value -= factor[a, b] * pinv[b, k]
            pinv[a, k] = value / factor[a, a]
        for a in range(5, -1, -1):
            value = pinv[a, k]
            for b in range(a + 1, 6):
                value -= factor[b, a] * pinv[b, k]
            pinv[a, k] = value / factor[a, a]
    return True


@jit
def _moments(pinv: np.ndarray, tau: np.ndarray, variance: np.ndarray, wrench: np.ndarray,
             wrench_cov: np.ndarray) -> None:
    """F = J⁺ τ̂ and Σ_F = J⁺ diag(variance) J⁺ᵀ (§1.4) of a diagonal Cov τ̂, symmetric."""
    n = pinv.shape[1]
    for a in range(6):
        value = 0.0
        for k in range(n):
            value += pinv[a, k] * tau[k]
        wrench[a] = value
        for b in range(a + 1):
            value = 0.0
            for k in range(n):
                value += pinv[a, k] * variance[k] * pinv[b, k]
            wrench_cov[a, b] = wrench_cov[b, a] = value




@jit
def _moments_full(pinv: np.ndarray, tau: np.ndarray, cov: np.ndarray, wrench: np.ndarray,
                  wrench_cov: np.ndarray) -> None:
    """F = J⁺ τ̂ and Σ_F = ½ (A + Aᵀ), A = J⁺ P J⁺ᵀ (§1.4), of a full Cov τ̂ P (n, n)."""
    n = pinv.shape[1]
    work = np.zeros((6, n))
    for a in range(6):
        value = 0.0
        for k in range(n):
            value += pinv[a, k] * tau[k]
        wrench[a] = value
        for k in range(n):                                             # work = J⁺ P
            for m in range(n):
                work[a, m] += pinv[a, k] * cov[k, m]
    for a in range(6):
        for b in range(6):
            value = 0.0
            for m in range(n):
                value += work[a, m] * pinv[b, m]
            wrench_cov[a, b] = value
    for a in range(6):
        for b in range(a):
            wrench_cov[a, b] = wrench_cov[b, a] = 0.5 * (wrench_cov[a, b] + wrench_cov[b, a])


@jit
def solve_wrench(jac: np.ndarray, tau: np.ndarray, variance: np.ndarray, cov: np.ndarray, full: bool,
                 params: np.ndarray, rotation: np.ndarray, end_effector: bool, wrench: np.ndarray,
                 wrench_cov: np.ndarray, directions: np.ndarray) -> tuple[int, int]:
    """F = J⁺ τ̂, J⁺ = (J Jᵀ + δ² I)⁻¹ J (v2 eq. 39), and Σ_F = J⁺ P J⁺ᵀ (docs/method.md §1.4) from J (6, n) in base
    axes, with P = diag(``variance``) or, when ``full``, ``cov`` (n, n); in base axes, or in the ee axes
    (``end_effector``: F_ee = diag(Rᵀ, Rᵀ) F, ``rotation`` R). One Cholesky of J Jᵀ − δ² I decides whether some
    σ_i(J) < δ; only then J's SVD gives those directions u_i (σ_i = 0 for the 6 − n missing) into
    ``directions[:, :k]`` and Σ_F adds the damping bias B Σ_prior Bᵀ (symmetrised), B = U_w diag(c) U_wᵀ,
    c_i = δ²/(σ_i² + δ²), Σ_prior = diag(f², f², f², m², m², m²) (§1.4.1). Returns (``Outcome`` bits: WEAK, or
    SINGULAR when J Jᵀ + δ² I is not positive definite and nothing is set; k).
    """
    n = jac.shape[1]
    damping = params[EstimatorParam.DAMPING]
    delta2 = damping * damping
    gram, pinv = _gram(jac), np.empty((6, n))
    if not _pseudo_inverse(jac, gram, delta2, pinv):
        return Outcome.SINGULAR, 0
    if full:
        _moments_full(pinv, tau, cov, wrench, wrench_cov)
    else:
        _moments(pinv, tau, variance, wrench, wrench_cov)
    for a in range(6):
        gram[a, a] -= delta2
    if damping == 0.0 or cholesky(gram, np.empty((6, 6))):          # σ_min(J) ≥ δ ⇔ J Jᵀ − δ² I ≻ 0
        if end_effector:
            rotate(rotation, wrench, wrench_cov)
        return 0, 0
    u, sigma, _ = np.linalg.svd(jac)                                   # J = U diag(σ) Vᵀ, U (6, 6)
    bias, shrink, k = np.zeros((6, 6)), np.empty(6), 0
    for i in range(6):
        strength = sigma[i] if i < sigma.shape[0] else 0.0
        if strength < damping:
            shrink[k] = delta2 / (strength * strength + delta2)         # c_i
            directions[:, k] = u[:, i]
            k += 1
    for a in range(6):                                                 # B = U_w diag(c) U_wᵀ
        for b in range(6):
            for i in range(k):
                bias[a, b] += directions[a, i] * shrink[i] * directions[b, i]
    prior = np.empty(6)
    prior[:3], prior[3:] = params[EstimatorParam.PRIOR_FORCE] ** 2, params[EstimatorParam.PRIOR_MOMENT] ** 2
    for a in range(6):                                                 # + B Σ_prior Bᵀ (§1.4.1)
        for b in range(6):
            value = 0.0
            for c in range(6):
                value += bias[a, c] * prior[c] * bias[c, b]
            wrench_cov[a, b] += value
    for a in range(6):
        for b in range(a):
            wrench_cov[a, b] = wrench_cov[b, a] = 0.5 * (wrench_cov[a, b] + wrench_cov[b, a])
    if end_effector:
        rotate(rotation, wrench, wrench_cov)
        turned = np.empty(6)
        for i in range(k):
            for a in range(6):
                block = 3 * (a // 3)
                turned[a] = (rotation[0, a - block] * directions[block, i] + rotation[1, a - block]
                             * directions[block + 1, i] + rotation[2, a - block] * directions[block + 2, i])
            directions[:, i] = turned
    return Outcome.WEAK, k


@jit
def rotate(rotation: np.ndarray, wrench: np.ndarray, wrench_cov: np.ndarray) -> None:
    """F ← B F and Σ ← B Σ Bᵀ with B = diag(Rᵀ, Rᵀ), ``rotation`` R (3, 3): base axes to the ee axes, or with Rᵀ
    back (``Estimate.wrench_in``)."""
    turned, work = np.zeros(6), np.empty((6, 6))
    for a in range(6):
        block = 3 * (a // 3)
        for k in range(3):
            turned[a] += rotation[k, a - block] * wrench[block + k]
    wrench[:] = turned
    for a in range(6):                                                 # work = B Σ
        block = 3 * (a // 3)
        for b in range(6):
            value = 0.0
            for k in range(3):
                value += rotation[k, a - block] * wrench_cov[block + k, b]
            work[a, b] = value
    for a in range(6):                                                 # B Σ Bᵀ, symmetric by construction
        for b in range(a + 1):
            block = 3 * (b // 3)
            value = 0.0
            for k in range(3):
                value += work[a, block + k] * rotation[k, b - block]
            wrench_cov[a, b] = wrench_cov[b, a] = value
