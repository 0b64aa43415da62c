"""The K-VARK momentum filter's step, compiled: ``kvark_step`` on its packed state (docs/method.md §4.2-4.7).

The per-sample arithmetic of the filter (``observers.kvark``), as one ``numba.njit`` call on preallocated buffers:
per joint a 2-state Kalman filter on [p; τ_ext] with the KMP's mean correcting the momentum prediction, the EWMA R_k,
the VB on Σ_d (per sample, or over windows with a twin held at the prior) and the contact-onset detector. Its numpy
reference, the same equations in the same order, is test/core/reference_filter.py, pinned to it by
test/core/test_compiled_step_matches_reference.py. The state and constants come packed (``split_state``,
``split_constants``; ``layouts``), their entries named by ``layouts`` (``vec[Vec.TAU]`` compiles as ``vec[1]``).
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.estimation.compiled.jit import jit
from kvark_ros.core.estimation.compiled.layouts import (CONST_ROWS, PARAMS, VEC_ROWS, Const, Counter, Option, Param,
                                                        Vec)

PINS = {"layouts.py": "b567b01b443f6eb37b6883fed944593a9449df4a179e52a7f83d6a575b5beb9f"}

# Samples of evidence from which an accepted jump counts as a step; on fewer its Var τ̂ also spans an impulse (§4.7).
ONSET_EVIDENCE = 2


@jit
def split_state(state: np.ndarray, n: int, snapshots: int,
                onsets: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Views of the packed filter state: vec (VEC_ROWS, n); the window's S = ``snapshots`` snapshots z, zz, pz, tz
    (4, n, S); the onset detector's ep, et, d, c (4, n, M), M = ``onsets``; and [dof, age (S,)] (1 + S,).
    ``split_state.py_func`` gives the same views in Python (``observers.kvark.KernelState``)."""
    end_vec = VEC_ROWS * n
    end_snap = end_vec + 4 * n * snapshots
    end_glr = end_snap + 4 * n * onsets
    return (state[:end_vec].reshape((VEC_ROWS, n)), state[end_vec:end_snap].reshape((4, n, snapshots)),
            state[end_snap:end_glr].reshape((4, n, onsets)), state[end_glr:end_glr + 1 + snapshots])


def state_size(n: int, snapshots: int, onsets: int) -> int:
    """Length of the packed float state of n joints, S snapshots and M onset hypotheses (``split_state``)."""
    return VEC_ROWS * n + 4 * n * (snapshots + onsets) + 1 + snapshots


@jit
def split_constants(constants: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Views of the packed constants: consts (CONST_ROWS, n) and params (PARAMS,)."""
    end_consts = CONST_ROWS * n
    return constants[:end_consts].reshape((CONST_ROWS, n)), constants[end_consts:end_consts + PARAMS]


def constants_size(n: int) -> int:
    """Length of the packed constants of n joints (``split_constants``)."""
    return CONST_ROWS * n + PARAMS


@jit
def kvark_step(dt: float, qd: np.ndarray, p: np.ndarray, u_prev: np.ndarray, state: np.ndarray, ints: np.ndarray,
               constants: np.ndarray, options: np.ndarray) -> None:
    """One sample of the K-VARK momentum filter (``KVARKFilter.step``); updates the packed state in place.

    Inputs: ``dt`` s; ``qd`` (n,) rad/s; ``p``, ``u_prev`` (n,) N·m·s, N·m. ``state``, ``ints``: the packed state
    (``split_state``: p̂, τ̂, P = [[a, b], [b, c]], R_k and w̄_k, the NIS mean, Σ_d, the window's q̂, Υ and snapshots,
    the residual model's μ_*, σ²_* at this sample (read; the caller evaluates the model first), the onset detector's
    sums, the counters, ``Counter``); ``constants``, ``options``: ``split_constants`` (``Const``, ``Param``) and
    ``Option``.
    """
    n = qd.shape[0]
    vec, snap, glr, scal = split_state(state, n, options[Option.SNAPSHOTS], options[Option.ONSETS])
    consts, params = split_constants(constants, n)
    p_hat, tau, a, b, c = vec[Vec.P_HAT], vec[Vec.TAU], vec[Vec.A], vec[Vec.B], vec[Vec.C]
    r_adaptive, r_weight, nis_mean, sigma_d = vec[Vec.R], vec[Vec.R_WEIGHT], vec[Vec.NIS], vec[Vec.SIGMA_D]
    q, scale, vb_dof, vb_scale = vec[Vec.Q], vec[Vec.SCALE], vec[Vec.VB_DOF], vec[Vec.VB_SCALE]
    mean, var = vec[Vec.MEAN], vec[Vec.VAR]
    z, zz, pz, tz = snap[0], snap[1], snap[2], snap[3]
    ep, et, d, info = glr[0], glr[1], glr[2], glr[3]
    age, dof = scal[1:], scal[0]
    count, slot, alarms = ints[Counter.COUNT], ints[Counter.SLOT], ints[Counter.ALARMS]
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
