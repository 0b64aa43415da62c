"""The compiled kernels (issue 16): the momentum-form K-VARK filter step and ``Estimator.step``.

Why. One ``Estimator.step`` of the default filter cost ~1.04 M instructions, most of them numpy's per-call overhead
on 6- and 7-element arrays. ``kvark_step`` runs the per-sample arithmetic of the K-VARK momentum filter
(docs/method.md §4.2-4.7) and ``estimate_step`` everything else of a step but the pinocchio passes (which stay
Python calls, ``RobotModel.compute_terms``), each as one ``numba.njit`` call on preallocated buffers. The numpy
references (test/core/reference_filter.py, ``Estimator``) are readable: the same equations, and the tests pin
the kernels to them on the committed bags (``test/core/test_compiled_step_matches_reference.py``). The buffers and
calls are in ``observers.kvark_kernel`` (the filter) and ``core.estimation.compiled_step`` (the estimator).

What ``estimate_step`` computes, in the reference's order, and how far the two differ: ``compiled_step``.

Arguments, not globals. Every array numba receives from Python costs ~1 k instructions to unbox, so the state and
the constants come packed (``split_state``, ``split_constants``). And numba's cache (``cache=True``: ``__pycache__``
next to this file, or ``NUMBA_CACHE_DIR``) is keyed on this file's content only: a function inlined from another
module, or another module's constant frozen into the machine code, would stay stale in the cache when only that
module changed. So all compiled code the kernels call lives in this file (the input checks, which call none,
are ``input_kernels``) and takes every number from its arguments, from this
file's own constants or from the layouts this file pins (below; ``test/core/test_compiled_step_matches_reference.py``
checks both). Arrays other than C-contiguous float64 ones (a strided view, float32) compile one more
specialization, once.

Layouts. The packed arrays' entries are declared once, in ``core.estimation.kernel_layouts``; numba compiles a member
as its integer constant (``vec[Vec.TAU]`` costs what ``vec[1]`` does). ``LAYOUTS_DIGEST`` pins that file's content:
numba's cache sees only this file, so a change there must change the digest here (the tests check it).
"""
from __future__ import annotations

import math
from typing import Callable

import numba
import numpy as np

from kvark_ros.core.estimation.kernel_layouts import (CONST_ROWS, PARAMS, VEC_ROWS, Const, Counter, EstimatorParam,
                                                      Flag, Option, Outcome, Param, Row, Vec)

# sha256 of core/estimation/kernel_layouts.py (module docstring): update it with the file,
# so numba recompiles the kernels.
LAYOUTS_DIGEST = "bd6c2c2bebe3a8abc39aa0d302fd5e0cc972fb0b4f532e271f1a41c16a46f28d"

# Samples of evidence from which an accepted jump counts as a step; on fewer its Var τ̂ also spans an impulse (§4.7).
ONSET_EVIDENCE = 2


def jit(function: Callable) -> Callable:
    """``numba.njit`` with numpy's IEEE semantics (inf/nan, no ZeroDivisionError) and numba's on-disk cache.

    Where no cache directory is writable (no ``NUMBA_CACHE_DIR``, a read-only install, no writable home) numba
    refuses ``cache=True`` when decorating; the kernels then compile at every start instead (~13 s)."""
    try:
        return numba.njit(cache=True, error_model="numpy")(function)
    except RuntimeError:                            # numba: "cannot cache function …: no locator available"
        return numba.njit(error_model="numpy")(function)


@jit
def split_state(state: np.ndarray, n: int, snapshots: int,
                onsets: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Views of the packed filter state: vec (VEC_ROWS, n); the window's S = ``snapshots`` snapshots z, zz, pz, tz
    (4, n, S); the onset detector's ep, et, d, c (4, n, M), M = ``onsets``; and [dof, age (S,)] (1 + S,).
    ``split_state.py_func`` gives the same views in Python (``observers.kvark_kernel.KernelState``)."""
    end_vec = VEC_ROWS * n
    end_snap = end_vec + 4 * n * snapshots
    end_glr = end_snap + 4 * n * onsets
    return (state[:end_vec].reshape((VEC_ROWS, n)), state[end_vec:end_snap].reshape((4, n, snapshots)),
            state[end_snap:end_glr].reshape((4, n, onsets)), state[end_glr:end_glr + 1 + snapshots])


def state_size(n: int, snapshots: int, onsets: int) -> int:
    """Length of the packed float state of n joints, S snapshots and M onset hypotheses (``split_state``)."""
    return VEC_ROWS * n + 4 * n * (snapshots + onsets) + 1 + snapshots


@jit
def split_constants(constants: np.ndarray, n: int,
                    support: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Views of the packed constants: consts (CONST_ROWS, n), params (PARAMS,), the KMP's support velocities
    (n, N) and its transposed weights (n, N, N+1) (``kmp_predict``); N = ``support``."""
    end_consts = CONST_ROWS * n
    end_params = end_consts + PARAMS
    end_support = end_params + n * support
    return (constants[:end_consts].reshape((CONST_ROWS, n)), constants[end_consts:end_params],
            constants[end_params:end_support].reshape((n, support)),
            constants[end_support:end_support + n * support * (support + 1)].reshape((n, support, support + 1)))


@jit
def kmp_predict(qd: np.ndarray, support: np.ndarray, weights_t: np.ndarray, consts: np.ndarray, floor: float,
                mean: np.ndarray, var: np.ndarray) -> None:
    """``KMPResidualModel.predict`` of a q̇-only model, into ``mean`` (n,) N·m and ``var`` (n,) N²·m².

    ``qd`` (n,) rad/s; ``support`` the support velocities s (n, N); ``weights_t`` the model's weights
    transposed, (n, N, N+1): column 0 σ_f² (𝒦 + λ₁Σ)⁻¹μ, columns 1..N σ_f² L⁻ᵀ with L Lᵀ = 𝒦 + λ₂Σ; ``floor``
    the variance floor (``residual.common.VARIANCE_FLOOR``).
    """
    n, n_support = support.shape
    rows = weights_t.shape[2]
    w = np.empty(rows)
    for j in range(n):
        w[:] = 0.0
        nearest = 0.0
        for i in range(n_support):
            e = qd[j] - support[j, i]
            e = np.exp(e * e * consts[Const.NEG_HALF_INV_LS2, j])      # k_*/σ_f², eq. 21
            nearest = max(nearest, e)
            for r in range(rows):                                      # W e, one row per r (vectorises over r)
                w[r] += weights_t[j, i, r] * e
        quad = 0.0
        for r in range(1, rows):
            quad += w[r] * w[r]
        sigma_f2 = consts[Const.SIGMA_F2, j]
        mean[j] = w[0]                                                 # eq. 22
        v = consts[Const.VAR_SCALE, j] * (sigma_f2 - quad)             # eq. 23
        v = max(v, sigma_f2 * (1.0 - nearest * nearest))               # far-field floor (§3.6)
        var[j] = max(v, floor)


@jit
def kvark_step(dt: float, qd: np.ndarray, p: np.ndarray, u_prev: np.ndarray, state: np.ndarray, ints: np.ndarray,
               constants: np.ndarray, options: np.ndarray) -> None:
    """One sample of the K-VARK momentum filter (``KVARKKernelFilter.step``); updates the packed state in place.

    Inputs: ``dt`` s; ``qd`` (n,) rad/s; ``p``, ``u_prev`` (n,) N·m·s, N·m. ``state``, ``ints``: the packed state
    (``split_state``: p̂, τ̂, P = [[a, b], [b, c]], R_k and w̄_k, the NIS mean, Σ_d, the window's q̂, Υ and snapshots,
    the residual model's μ_*, σ²_* (written here when ``options[Option.KMP]``, else read), the onset detector's sums,
    the counters, ``Counter``); ``constants``, ``options``: ``split_constants`` (``Const``, ``Param``) and ``Option``.
    """
    n = qd.shape[0]
    vec, snap, glr, scal = split_state(state, n, options[Option.SNAPSHOTS], options[Option.ONSETS])
    consts, params, support, weights_t = split_constants(constants, n, options[Option.SUPPORT])
    p_hat, tau, a, b, c = vec[Vec.P_HAT], vec[Vec.TAU], vec[Vec.A], vec[Vec.B], vec[Vec.C]
    r_adaptive, r_weight, nis_mean, sigma_d = vec[Vec.R], vec[Vec.R_WEIGHT], vec[Vec.NIS], vec[Vec.SIGMA_D]
    q, scale, vb_dof, vb_scale = vec[Vec.Q], vec[Vec.SCALE], vec[Vec.VB_DOF], vec[Vec.VB_SCALE]
    mean, var = vec[Vec.MEAN], vec[Vec.VAR]
    z, zz, pz, tz = snap[0], snap[1], snap[2], snap[3]
    ep, et, d, info = glr[0], glr[1], glr[2], glr[3]
    age, dof = scal[1:], scal[0]
    count, slot, alarms = ints[Counter.COUNT], ints[Counter.SLOT], ints[Counter.ALARMS]
    if options[Option.KMP]:
        kmp_predict(qd, support, weights_t, consts, params[Param.VARIANCE_FLOOR], mean, var)  # eqs. 21-23
    heteroscedastic, ewma, nis = options[Option.HETEROSCEDASTIC], options[Option.EWMA], options[Option.NIS]
    window, onset, stride = options[Option.WINDOW], options[Option.ONSET], options[Option.STRIDE]
    twin = options[Option.TWIN]
    vb_iw, smoothed = options[Option.VB_IW], options[Option.SMOOTHED]
    passes, forget_vb = options[Option.ITERATIONS] if vb_iw else 1, params[Param.VB_FORGETTING]
    hh = dt * dt
    snapshots = z.shape[1]
    column, closing, full, forget = 0, False, False, params[Param.FORGET]
    if window:
        count += 1
        for i in range(snapshots):
            age[i] = age[i] + dt
        closing = count % stride == 0
        if closing:
            column = (count // stride) % snapshots
            full = count >= stride * snapshots                         # snapshot `column` spans a whole window
            if full:
                dof = forget * dof + 1.0 / snapshots                   # eq. 37
    threshold = params[Param.THRESHOLD]
    gate = False
    dof_pred = scale_pred = 0.0
    for j in range(n):
        tau_pred = tau[j]                                              # eq. 41
        p_pred = p_hat[j] + dt * (u_prev[j] - mean[j] + tau_pred)     # eq. 28 as the momentum model
        residual_var = var[j] if heteroscedastic else consts[Const.RESIDUAL_VAR, j]
        bj, hc = b[j], dt * c[j]                                       # F P Fᵀ, F = [[1, h], [0, 1]]
        a_f = a[j] + dt * (bj + bj + hc) + consts[Const.Q_P, j] * dt + hh * residual_var  # + w_p (eq. 30)
        b_f, c_f = bj + hc, c[j]
        nu = p[j] - p_pred                                             # innovation
        R = r_adaptive[j] if ewma else consts[Const.R, j]
        if window:
            for i in range(snapshots):
                pz[j, i] = pz[j, i] + dt * tz[j, i]                    # Cov(p⁻, z) = (F P)_pz
            sd = q[j] * dt                                             # Σ_d = q̂ h (§4.6)
        elif vb_iw:                                                    # the IW prediction with forgetting (§4.4)
            sd, dof_pred, scale_pred = sigma_d[j], forget_vb * (vb_dof[j] - 2.0) + 2.0, forget_vb * vb_scale[j]
        else:
            sd = consts[Const.Q_TAU, j] * dt                           # Σ_d from training (eq. 32)
            if nis:
                sd = sd * nis_mean[j]                                  # A4: Σ_d = α Σ_d0
        for _ in range(passes):                                        # M VB passes re-read eq. 42 (§4.4)
            q_a = sd * (hh / 3.0)                                      # (K2): q_τ h³/3, q_τ h²/2, q_τ h
            a_m, b_m, c_m = a_f + q_a, b_f + sd * (dt / 2.0), c_f + sd
            s, k1, k2, g, a[j], b[j], c[j] = _update(a_m, b_m, c_m, R)  # (K3), (K5)
            p_hat[j] = p_pred + k1 * nu                                # (K4)
            tau[j] = tau_pred + k2 * nu
            if vb_iw:
                if smoothed:                                           # E[(τ_k − τ_k−1)² | y_1:k], lag-one RTS (§4.5)
                    r = bj + dt * c_f
                    w_hat = (k2 - r / s) * nu
                    increment = w_hat * w_hat + c[j] - c_f - r * r / s + 2.0 * k2 * r
                    increment = 0.0 if increment < 0.0 else increment
                else:
                    e = tau[j] - tau_pred                              # eq. 34
                    increment = e * e + c[j]                           # eq. 38 as written
                vb_dof[j] = dof_pred + 1.0                             # eq. 37
                vb_scale[j] = scale_pred + increment                   # eq. 38
                sd = vb_scale[j] / (vb_dof[j] - 2.0)                   # eqs. 39-40 (n = 1 per joint)
        if vb_iw:
            sigma_d[j] = sd
        if window:                                     # snapshots of τ̂ or of the twin's τ̂, with its gain (§4.6)
            q0 = consts[Const.Q_TAU, j]
            w_k1, w_k2, w_tau, w_b, w_c = k1, k2, tau[j], b[j], c[j]
            if twin:
                w_k1, w_k2 = _twin_step(j, vec, dt, p[j], u_prev[j], consts[Const.Q_P, j] * dt + hh * residual_var,
                                        q0 * dt, R)
                w_tau, w_b, w_c = vec[Vec.TWIN_TAU, j], vec[Vec.TWIN_B, j], vec[Vec.TWIN_C, j]
            for i in range(snapshots):
                pzi = pz[j, i]
                if not twin:                           # the twin's snapshots stay as taken: filtered, not smoothed
                    gain = pzi / s
                    z[j, i] = z[j, i] + gain * nu
                    zz[j, i] = zz[j, i] - pzi * gain
                tz[j, i] = tz[j, i] - w_k2 * pzi
                pz[j, i] = pzi - w_k1 * pzi
            if closing:
                if full:
                    delta = w_tau - z[j, column]
                    stat = (delta * delta + w_c + zz[j, column] - 2.0 * tz[j, column]) / age[column]  # s_j
                    scale[j] = forget * scale[j] + max(stat, 0.0) / snapshots                        # eq. 38
                    prior = params[Param.PRIOR_DOF]
                    q[j] = min((prior * q0 + scale[j]) / (prior + dof), params[Param.MAX_RATIO] * q0)  # eq. 39
                z[j, column], zz[j, column] = w_tau, w_c                   # new snapshot z_j = τ_k
                pz[j, column], tz[j, column] = w_b, w_c
            sigma_d[j] = q[j] * dt
        if onset:                                                      # GLR sums with this sample (§4.7)
            nu_s, r_s = nu / s, R / s
            for i in range(ep.shape[1]):
                rho = ep[j, i]
                d[j, i] += rho * nu_s
                info[j, i] += rho * (rho / s)
                et[j, i] -= k2 * rho                                   # e⁺ = e⁻ − K ρ
                ep[j, i] = rho * r_s                                   # 1 − K_p = R / S
                if d[j, i] * d[j, i] - threshold * info[j, i] > 0.0:
                    gate = True
        if ewma:                                       # eq. 31, eq. 16's correction, weighted by (R/S)² (§4.3)
            rate = params[Param.EWMA_RATE]
            r_weight[j] += rate * (g * g - r_weight[j])                # w̄_k, the weights' own EWMA, w = (R/S)²
            updated = r_adaptive[j] + rate * g * g / r_weight[j] * (nu * nu - a_m - r_adaptive[j])
            r_adaptive[j] = min(max(updated, consts[Const.R_MIN, j]), consts[Const.R, j])
        if nis:                                                        # A4
            updated = nis_mean[j] + params[Param.NIS_RATE] * (nu * nu / s - nis_mean[j])
            nis_mean[j] = min(max(updated, params[Param.NIS_LOW]), params[Param.NIS_HIGH])
    if window and closing:
        age[column] = 0.0
    if onset:
        accepted, steps = _accept_jumps(gate, threshold, slot, p_hat, tau, a, b, c, ep, et, d, info)
        alarms += accepted
        if steps:                                   # a contact seen as a step: Σ_d ≥ q_c h on every joint (§4.7)
            prior = params[Param.PRIOR_DOF]
            for j in range(n):
                q_c = consts[Const.Q_CONTACT, j]
                if window:
                    if q[j] < q_c:
                        q[j] = q_c
                        scale[j] = q_c * (prior + dof) - prior * consts[Const.Q_TAU, j]   # eq. 39 solved for Υ
                    sigma_d[j] = q[j] * dt
                elif vb_iw and sigma_d[j] < q_c * dt:
                    sigma_d[j] = q_c * dt
                    vb_scale[j] = sigma_d[j] * (vb_dof[j] - 2.0)       # eqs. 39-40 solved for Υ
        for j in range(n):
            for i in range(ep.shape[1]):
                ep[j, i] = ep[j, i] + dt * et[j, i]                    # e⁻_k+1 = F e⁺_k
            ep[j, slot], et[j, slot], d[j, slot], info[j, slot] = 0.0, 1.0, 0.0, 0.0   # newest onset
        slot = (slot + 1) % ep.shape[1]
    ints[Counter.COUNT], ints[Counter.SLOT], ints[Counter.ALARMS], scal[0] = count, slot, alarms, dof


@jit
def _twin_step(j: int, vec: np.ndarray, dt: float, p: float, u_prev: float, w_p: float, sd: float,
               R: float) -> tuple[float, float]:
    """Joint j of the window's twin (§4.6): the filter of ``kvark_step`` with Σ_d = ``sd`` = q_τ h fixed, the same
    μ_*, R and w_p = q_p h + h² σ²_r, updated in ``vec``'s TWIN rows; returns its gain k1, k2."""
    tau, b, hc = vec[Vec.TWIN_TAU, j], vec[Vec.TWIN_B, j], dt * vec[Vec.TWIN_C, j]
    p_pred = vec[Vec.TWIN_P, j] + dt * (u_prev - vec[Vec.MEAN, j] + tau)           # eq. 28
    a_m = vec[Vec.TWIN_A, j] + dt * (b + b + hc) + w_p + sd * (dt * dt / 3.0)      # (K2)
    b_m, c_m = b + hc + sd * (dt / 2.0), vec[Vec.TWIN_C, j] + sd
    nu = p - p_pred
    _, k1, k2, _, vec[Vec.TWIN_A, j], vec[Vec.TWIN_B, j], vec[Vec.TWIN_C, j] = _update(a_m, b_m, c_m, R)
    vec[Vec.TWIN_P, j], vec[Vec.TWIN_TAU, j] = p_pred + k1 * nu, tau + k2 * nu     # (K4)
    return k1, k2


@jit
def _update(a_m: float, b_m: float, c_m: float,
            R: float) -> tuple[float, float, float, float, float, float, float]:
    """One joint's 2-state measurement update of P⁻ = [[a_m, b_m], [b_m, c_m]] by the momentum, H = [1, 0]: returns
    S, the gain K = [k1, k2], g = R / S = 1 − k1 and P⁺'s a, b, c in Joseph form ((K3), (K5), docs/method.md §5.5)."""
    s = a_m + R                                                                    # (K3)
    k1, k2, g = a_m / s, b_m / s, R / s
    return (s, k1, k2, g, g * (g * a_m) + k1 * (k1 * R),                           # (K5), Joseph form
            g * (b_m - k2 * a_m) + k1 * (k2 * R), c_m - k2 * (b_m + b_m - k2 * s))


@jit
def _accept_jumps(gate: bool, threshold: float, slot: int, p_hat: np.ndarray, tau: np.ndarray, a: np.ndarray,
                  b: np.ndarray, c: np.ndarray, ep: np.ndarray, et: np.ndarray, d: np.ndarray,
                  info: np.ndarray) -> tuple[int, int]:
    """Accept the jumps whose ℓ_θ = d²/C exceeds the threshold (once any d² > threshold C) and correct the state,
    x̂ += e⁺ Δ̂, P += e⁺ e⁺ᵀ Var Δ̂, P_ττ += (e⁺_τ Δ̂)² on one sample (onset.py); that joint's hypotheses restart.
    Returns the number of joints and of those whose jump was seen on ``ONSET_EVIDENCE`` samples or more (steps)."""
    if not gate:
        return 0, 0
    accepted, steps, onsets = 0, 0, ep.shape[1]
    for j in range(tau.shape[0]):
        best, theta = -np.inf, 0
        for i in range(onsets):
            ratio = d[j, i] * d[j, i] / (info[j, i] + 1e-300)          # ℓ_θ (0 where no data yet)
            if ratio > best:
                best, theta = ratio, i
        if not best > threshold:
            continue
        e_p, e_t, information = ep[j, theta], et[j, theta], info[j, theta]
        size = d[j, theta] / information                               # Δ̂_θ
        one_sample = (slot - 1 - theta) % onsets < ONSET_EVIDENCE     # evidence at slot i: (slot − 1 − i) mod M
        spread = 1.0 / information                                     # Var Δ̂_θ
        doubt = size * size if one_sample else 0.0                     # a step or an impulse: same p, τ apart by Δ̂
        p_hat[j] += e_p * size
        tau[j] += e_t * size
        a[j] += e_p * e_p * spread
        b[j] += e_p * e_t * spread
        c[j] += e_t * e_t * (spread + doubt)
        ep[j, :], et[j, :], d[j, :], info[j, :] = 0.0, 0.0, 0.0, 0.0  # no hypothesis spans the correction
        accepted += 1
        steps += 0 if one_sample else 1
    return accepted, steps


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
def _cholesky(a: np.ndarray, factor: np.ndarray) -> bool:
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
    if not _cholesky(damped, factor):
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
    """F = J⁺ τ̂ and Σ_F = J⁺ diag(variance) J⁺ᵀ (§1.4; P is diagonal, the module docstring), symmetric."""
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
def _wrench(jac: np.ndarray, tau: np.ndarray, variance: np.ndarray, params: np.ndarray, rotation: np.ndarray,
            end_effector: bool, wrench: np.ndarray, wrench_cov: np.ndarray) -> int:
    """F = J⁺ τ̂ and Σ_F = J⁺ diag(variance) J⁺ᵀ (docs/method.md §1.4, v2 eq. 39) in base axes, or in the ee axes
    (``rotation`` R: F_ee = diag(Rᵀ, Rᵀ) F); returns Outcome.WEAK when some σ_i(J) < δ (§1.4.1: ``weak_wrench``
    then follows), Outcome.SINGULAR when J⁺ does not exist, else 0."""
    damping = params[EstimatorParam.DAMPING]
    delta2 = damping * damping
    gram, pinv = _gram(jac), np.empty((6, jac.shape[1]))
    if not _pseudo_inverse(jac, gram, delta2, pinv):
        return Outcome.SINGULAR
    _moments(pinv, tau, variance, wrench, wrench_cov)
    for a in range(6):
        gram[a, a] -= delta2
    weak = damping != 0.0 and not _cholesky(gram, np.empty((6, 6)))   # σ_min(J) ≥ δ ⇔ J Jᵀ − δ² I ≻ 0
    if end_effector:
        _rotate(rotation, wrench, wrench_cov)
    return Outcome.WEAK if weak else 0


@jit
def weak_wrench(jac: np.ndarray, tau: np.ndarray, tau_cov: np.ndarray, params: np.ndarray, rotation: np.ndarray,
                end_effector: bool, wrench: np.ndarray, wrench_cov: np.ndarray,
                directions: np.ndarray) -> tuple[int, bool]:
    """``RobotModel.solve_wrench`` at a pose with weak directions (docs/method.md §1.4.1), after ``estimate_step``.

    From J (6, n), τ̂ and the reported Cov τ̂ (diagonal): F = J⁺ τ̂, Σ_F = J⁺ P J⁺ᵀ + B Σ_prior Bᵀ (symmetrised) with
    B = U_w diag(c) U_wᵀ, c_i = δ²/(σ_i² + δ²) over the left singular vectors u_i with σ_i < δ (σ_i = 0 for the
    6 − n missing) and Σ_prior = diag(f², f², f², m², m², m²); those u_i into ``directions[:, :k]``. All in base
    axes, or in the ee axes as ``_wrench``. Returns (k, whether τ̂, Cov τ̂ and Σ_F are finite).
    """
    n = jac.shape[1]
    damping = params[EstimatorParam.DAMPING]
    delta2 = damping * damping
    variance, pinv = np.empty(n), np.empty((6, n))
    for j in range(n):
        variance[j] = tau_cov[j, j]
    _pseudo_inverse(jac, _gram(jac), delta2, pinv)
    _moments(pinv, tau, variance, wrench, wrench_cov)
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
        _rotate(rotation, wrench, wrench_cov)
        turned = np.empty(6)
        for i in range(k):
            for a in range(6):
                block = 3 * (a // 3)
                turned[a] = (rotation[0, a - block] * directions[block, i] + rotation[1, a - block]
                             * directions[block + 1, i] + rotation[2, a - block] * directions[block + 2, i])
            directions[:, i] = turned
    total = 0.0
    for j in range(n):
        total += tau[j] + variance[j]
    for a in range(6):
        for b in range(6):
            total += wrench_cov[a, b]
    return k, math.isfinite(total)


@jit
def _rotate(rotation: np.ndarray, wrench: np.ndarray, wrench_cov: np.ndarray) -> None:
    """F ← B F and Σ ← B Σ Bᵀ with B = diag(Rᵀ, Rᵀ): base axes to the ee axes (``Estimate.wrench_in``)."""
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


@jit
def estimate_step(flags: int, dt: float, qd: np.ndarray, tau_m: np.ndarray, gravity: np.ndarray, rnea: np.ndarray,
                  coriolis: np.ndarray, jac: np.ndarray, rotation: np.ndarray, rows: np.ndarray, offset: np.ndarray,
                  params: np.ndarray, state: np.ndarray, ints: np.ndarray, constants: np.ndarray,
                  options: np.ndarray, tau: np.ndarray, tau_cov: np.ndarray, wrench: np.ndarray,
                  wrench_cov: np.ndarray) -> tuple[int, float, float]:
    """One ``Estimator.step`` after its input checks and pinocchio passes (module docstring).

    ``flags``: ``Flag`` bits, MOMENTUM (p, u from ``gravity`` g, ``rnea`` = M q̇ + g and ``coriolis`` C, kept in
    ``rows`` for the next sample), FILTER (``kvark_step`` on the packed filter state ``state``, ``ints``,
    ``constants``, ``options``), POST (the rest, into ``tau``, ``tau_cov``, ``wrench``, ``wrench_cov``), and the
    settings TARED (subtract ``offset``), STICTION (widen by the band in ``rows[Row.BAND]``), SCALED (report P scaled
    by ``rows[Row.SCALE]``, at least ``rows[Row.FLOOR]``), END_EFFECTOR (wrench in the axes of ``rotation``),
    AUGMENTED (subtract ``rows[Row.AUG]`` = τ_aug), TEST_REPORTED (the contact test's S is the reported
    covariance, not P + σ²_r). ``jac``: J (6, n) in base axes; ``params``: δ, the wrench prior, v_s, z
    (``EstimatorParam``). Returns (code: ``Outcome`` bits WEAK | DIVERGED | SINGULAR, the contact statistic
    (NaN: S not positive definite), the collision excess (NaN: not finite)); with WEAK or SINGULAR, F and Σ_F are not
    final.
    """
    n = qd.shape[0]
    if flags & Flag.MOMENTUM:
        _momentum(qd, tau_m, gravity, rnea, coriolis, rows, flags & Flag.AUGMENTED != 0)
    if flags & Flag.FILTER:
        kvark_step(dt, qd, rows[Row.P], rows[Row.U_PREV], state, ints, constants, options)
    if flags & Flag.MOMENTUM:
        rows[Row.P_PREV, :] = rows[Row.P]
        rows[Row.U_PREV, :] = rows[Row.U]
    if not flags & Flag.POST:
        return 0, np.nan, np.nan
    vec = split_state(state, n, options[Option.SNAPSHOTS], options[Option.ONSETS])[0]
    filtered, c, residual_var = vec[Vec.TAU], vec[Vec.C], vec[Vec.VAR]
    band, factors, floor = rows[Row.BAND], rows[Row.SCALE], rows[Row.FLOOR]
    velocity, z = params[EstimatorParam.STICTION_VELOCITY], params[EstimatorParam.Z]
    variance = np.empty(n)
    tau_cov[:, :] = 0.0
    statistic, excess, total, definite = 0.0, -np.inf, 0.0, True
    for j in range(n):
        tau[j] = filtered[j] - offset[j] if flags & Flag.TARED else filtered[j]    # τ̂ − offset (§4.10)
        sticking, widened = 0.0, c[j]                                           # P = diag(c) (§4.2)
        if flags & Flag.STICTION:
            ratio = qd[j] / velocity
            sticking = band[j] * band[j] / 3.0 * np.exp(-(ratio * ratio))       # σ²_s = F_s²/3 e^{−(q̇/v_s)²} (§4.11)
            widened += sticking
        variance[j] = widened                                                   # reported Cov τ̂, Σ_F's source
        if flags & Flag.SCALED:
            scaled = c[j] * (factors[j] * factors[j])                           # diag(c) P diag(c) (§4.13)
            if scaled < floor[j]:
                scaled = floor[j]                                               # at least P_b (§4.13)
            variance[j] = scaled + sticking                                     # + σ²_s
        tau_cov[j, j] = variance[j]
        s_jj = widened + residual_var[j]                                        # S = P + diag σ²_r (§7.2)
        s_test = variance[j] if flags & Flag.TEST_REPORTED else s_jj           # or the reported Cov τ̂ (§7.2)
        if s_test > 0.0:
            scaled = tau[j] / math.sqrt(s_test)                                 # L⁻¹ τ̂, L = diag(√S_jj)
            statistic += scaled * scaled                                        # d² = τ̂ᵀ S⁻¹ τ̂ (§7.1)
        else:
            definite = False
        unwidened = s_jj - sticking if flags & Flag.STICTION else s_jj          # the collision keeps σ unwidened
        if unwidened < 0.0:                                                     # max(·, 0); a NaN stays NaN
            unwidened = 0.0
        joint = abs(tau[j]) - z * math.sqrt(unwidened)                          # |τ̂_j| − z σ_j (§4.10)
        if math.isnan(joint) or joint > excess:                                 # a NaN stays: the flag holds
            excess = joint
        total += tau[j] + variance[j]
    code = _wrench(jac, tau, variance, params, rotation, flags & Flag.END_EFFECTOR != 0, wrench, wrench_cov)
    for a in range(6):
        for b in range(6):
            total += wrench_cov[a, b]
    code |= 0 if math.isfinite(total) else Outcome.DIVERGED
    if not (definite and math.isfinite(statistic)):
        statistic = np.nan
    return code, statistic, excess
