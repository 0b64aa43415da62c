"""The momentum-form K-VARK step as one compiled kernel (``filter.kernel: numba``).

Why. One ``Estimator.step`` of the default filter was ~795 k instructions, two thirds of them numpy's
per-call overhead on 7-element arrays (issue 16). Here the per-sample arithmetic of
``KVARKMomentumFilter.step`` (docs/method.md §4.2-4.3, §4.6-4.7) runs in one ``numba.njit`` function that
loops over the joints and updates the filter's state arrays in place. ``KVARKMomentumFilter`` stays the
readable reference: the same equations in the same order of operations, so the two agree to
floating-point rounding (the tests pin that on the committed bags), and the kernel observer keeps the
reference's ``STATE`` (same names, shapes and values), so ``state``/``load_state`` work unchanged.

Covered: the variants ``kf``, ``kmp_kf``, ``kmp_kf_ewma``, ``kmp_kf_nis`` and the VB variants with
``vb_variant: window``, with or without the onset detector. A q̇-only KMP residual model (eqs. 21-23 and
the far-field floor, §3.3, §3.6) is evaluated inside the kernel; any other residual predictor (pose inputs,
the learned baselines, the oracle) is called in Python and its mean and variance passed in. Not covered
(``kernel_problem``): the difference form and the ``paper``/``smoothed`` VB readings; ``make_observer``
refuses them with ``filter.kernel: numba``.

Compilation: ``cache=True`` stores the machine code next to this file (numba keeps it in memory when the
directory is not writable); the observer steps once on dummy data at construction, so the first sample
does not wait for the compiler.
"""
from __future__ import annotations

import numba
import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, ResidualPredictor
from kvark_ros.core.observers.kvark_filter import NIS_SCALE_BOUNDS, VARIANTS
from kvark_ros.core.observers.kvark_momentum import R_FLOOR, KVARKMomentumFilter
from kvark_ros.core.observers.momentum_observers import MomentumNoise
from kvark_ros.core.observers.window_vb import WINDOW_MAX_RATIO, WINDOW_SNAPSHOTS
from kvark_ros.core.residual.common import VARIANCE_FLOOR
from kvark_ros.core.residual.kmp import KMPResidualModel

# Rows of the per-joint constants (consts, (CONST_ROWS, n)).
C_R, C_R_MIN, C_Q_P, C_Q_TAU, C_RESIDUAL_VAR, C_NEG_HALF_INV_LS2, C_SIGMA_F2, C_VAR_SCALE = range(8)
CONST_ROWS = 8
# Entries of the float parameters (params) and of the integer options (options).
P_EWMA_RATE, P_NIS_RATE, P_FORGET, P_PRIOR_DOF, P_THRESHOLD = range(5)
O_HETEROSCEDASTIC, O_EWMA, O_NIS, O_WINDOW, O_ONSET, O_KMP, O_STRIDE = range(7)
_JIT = {"cache": True, "error_model": "numpy"}     # numpy's IEEE semantics (inf/nan, no ZeroDivisionError)


def kernel_problem(variant: str, settings: FilterSettings) -> str | None:
    """Why ``filter.kernel: numba`` cannot run the K-VARK ``variant`` with ``settings``, or None if it can."""
    if settings.measurement != "momentum":
        return ("filter.kernel: numba covers filter.measurement: momentum only; use filter.kernel: numpy for the "
                "difference form")
    if VARIANTS[variant].vb and settings.vb_variant != "window":
        return (f"filter.kernel: numba covers filter.vb_variant: window only, not {settings.vb_variant}; "
                "use filter.kernel: numpy")
    return None


@numba.njit(**_JIT)
def kmp_predict(qd: np.ndarray, support: np.ndarray, weights_t: np.ndarray, consts: np.ndarray,
                mean: np.ndarray, var: np.ndarray) -> None:
    """``KMPResidualModel.predict`` of a q̇-only model, into ``mean`` (n,) N·m and ``var`` (n,) N²·m².

    ``qd`` (n,) rad/s; ``support`` the support velocities s (n, N); ``weights_t`` the model's weights
    transposed, (n, N, N+1): column 0 σ_f² (𝒦 + λ₁Σ)⁻¹μ, columns 1..N σ_f² L⁻ᵀ with L Lᵀ = 𝒦 + λ₂Σ.
    """
    n, n_support = support.shape
    rows = weights_t.shape[2]
    w = np.empty(rows)
    for j in range(n):
        w[:] = 0.0
        nearest = 0.0
        for i in range(n_support):
            e = qd[j] - support[j, i]
            e = np.exp(e * e * consts[C_NEG_HALF_INV_LS2, j])          # k_*/σ_f², eq. 21
            nearest = max(nearest, e)
            for r in range(rows):                                      # W e, one row per r (vectorises over r)
                w[r] += weights_t[j, i, r] * e
        quad = 0.0
        for r in range(1, rows):
            quad += w[r] * w[r]
        sigma_f2 = consts[C_SIGMA_F2, j]
        mean[j] = w[0]                                                 # eq. 22
        v = consts[C_VAR_SCALE, j] * (sigma_f2 - quad)                 # eq. 23
        v = max(v, sigma_f2 * (1.0 - nearest * nearest))               # far-field floor (§3.6)
        var[j] = max(v, VARIANCE_FLOOR)


@numba.njit(**_JIT)
def kvark_step(dt: float, qd: np.ndarray, p: np.ndarray, u_prev: np.ndarray, mean: np.ndarray, var: np.ndarray,
               p_hat: np.ndarray, tau: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
               r_adaptive: np.ndarray, nis_mean: np.ndarray, sigma_d: np.ndarray,
               z: np.ndarray, zz: np.ndarray, pz: np.ndarray, tz: np.ndarray, age: np.ndarray, q: np.ndarray,
               scale: np.ndarray, count: int, dof: float,
               ep: np.ndarray, et: np.ndarray, d: np.ndarray, info: np.ndarray, slot: int, alarms: int,
               consts: np.ndarray, params: np.ndarray, options: np.ndarray, support: np.ndarray,
               weights_t: np.ndarray) -> tuple[int, float, int, int]:
    """One sample of ``KVARKMomentumFilter.step``; updates the state arrays in place.

    Inputs: ``dt`` s; ``qd`` (n,) rad/s; ``p``, ``u_prev`` (n,) N·m·s, N·m; ``mean``, ``var`` (n,) the residual
    model's μ_*, σ²_* (written here when ``options[O_KMP]``, else read). State (the reference's attributes):
    p̂, τ̂, P = [[a, b], [b, c]], R_k, the NIS mean, Σ_d (n,); the window's z, zz, pz, tz (n, S), age (S,),
    q, scale (n,), count, dof; the onset detector's ep, et, d, c (n, M), slot, alarms. Returns the new
    (count, dof, slot, alarms).
    """
    n = tau.shape[0]
    if options[O_KMP]:
        kmp_predict(qd, support, weights_t, consts, mean, var)             # eqs. 21-23
    heteroscedastic, ewma, nis = options[O_HETEROSCEDASTIC], options[O_EWMA], options[O_NIS]
    window, onset, stride = options[O_WINDOW], options[O_ONSET], options[O_STRIDE]
    hh = dt * dt
    snapshots = z.shape[1]
    column, closing, full, forget = 0, False, False, params[P_FORGET]
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
    threshold = params[P_THRESHOLD]
    gate = False
    for j in range(n):
        tau_pred = tau[j]                                              # eq. 41
        p_pred = p_hat[j] + dt * (u_prev[j] - mean[j] + tau_pred)     # eq. 28 as the momentum model
        residual_var = var[j] if heteroscedastic else consts[C_RESIDUAL_VAR, j]
        bj, hc = b[j], dt * c[j]                                       # F P Fᵀ, F = [[1, h], [0, 1]]
        a_f = a[j] + dt * (bj + bj + hc) + consts[C_Q_P, j] * dt + hh * residual_var   # + w_p (eq. 30)
        b_f, c_f = bj + hc, c[j]
        nu = p[j] - p_pred                                             # innovation
        R = r_adaptive[j] if ewma else consts[C_R, j]
        if window:
            for i in range(snapshots):
                pz[j, i] = pz[j, i] + dt * tz[j, i]                    # Cov(p⁻, z) = (F P)_pz
            sd = q[j] * dt                                             # Σ_d = q̂ h (§4.6)
        else:
            sd = consts[C_Q_TAU, j] * dt                               # Σ_d from training (eq. 32)
            if nis:
                sd = sd * nis_mean[j]                                  # A4: Σ_d = α Σ_d0
        q_a = sd * (hh / 3.0)                                          # (K2): q_τ h³/3, q_τ h²/2, q_τ h
        a_m, b_m, c_m = a_f + q_a, b_f + sd * (dt / 2.0), c_f + sd
        s = a_m + R                                                    # (K3)
        k1, k2, g = a_m / s, b_m / s, R / s
        a[j] = g * (g * a_m) + k1 * (k1 * R)                           # (K5), Joseph form
        b[j] = g * (b_m - k2 * a_m) + k1 * (k2 * R)
        c[j] = c_m - k2 * (b_m + b_m - k2 * s)
        p_hat[j] = p_pred + k1 * nu                                    # (K4)
        tau[j] = tau_pred + k2 * nu
        if window:                                                     # snapshots: the same gain (§4.6)
            for i in range(snapshots):
                pzi = pz[j, i]
                gain = pzi / s
                z[j, i] = z[j, i] + gain * nu
                zz[j, i] = zz[j, i] - pzi * gain
                tz[j, i] = tz[j, i] - k2 * pzi
                pz[j, i] = pzi - k1 * pzi
            if closing:
                q0 = consts[C_Q_TAU, j]
                if full:
                    delta = tau[j] - z[j, column]
                    stat = (delta * delta + c[j] + zz[j, column] - 2.0 * tz[j, column]) / age[column]  # s_j
                    scale[j] = forget * scale[j] + max(stat, 0.0) / snapshots                        # eq. 38
                    prior = params[P_PRIOR_DOF]
                    q[j] = min((prior * q0 + scale[j]) / (prior + dof), WINDOW_MAX_RATIO * q0)      # eq. 39
                z[j, column], zz[j, column] = tau[j], c[j]                 # new snapshot z_j = τ_k
                pz[j, column], tz[j, column] = b[j], c[j]
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
        if ewma:                                                       # eq. 31 with eq. 16's correction
            updated = r_adaptive[j] + params[P_EWMA_RATE] * (nu * nu - a_m - r_adaptive[j])
            r_adaptive[j] = min(max(updated, consts[C_R_MIN, j]), consts[C_R, j])
        if nis:                                                        # A4
            updated = nis_mean[j] + params[P_NIS_RATE] * (nu * nu / s - nis_mean[j])
            nis_mean[j] = min(max(updated, NIS_SCALE_BOUNDS[0]), NIS_SCALE_BOUNDS[1])
    if window and closing:
        age[column] = 0.0
    if onset:
        alarms += _accept_jumps(gate, threshold, p_hat, tau, a, b, c, ep, et, d, info)
        for j in range(n):
            for i in range(ep.shape[1]):
                ep[j, i] = ep[j, i] + dt * et[j, i]                    # e⁻_k+1 = F e⁺_k
            ep[j, slot], et[j, slot], d[j, slot], info[j, slot] = 0.0, 1.0, 0.0, 0.0   # newest onset
        slot = (slot + 1) % ep.shape[1]
    return count, dof, slot, alarms


@numba.njit(**_JIT)
def _accept_jumps(gate: bool, threshold: float, p_hat: np.ndarray, tau: np.ndarray, a: np.ndarray, b: np.ndarray,
                  c: np.ndarray, ep: np.ndarray, et: np.ndarray, d: np.ndarray, info: np.ndarray) -> int:
    """Accept the jumps whose ℓ_θ = d²/C exceeds the threshold (once any d² > threshold C) and correct the
    state, x̂ += e⁺ Δ̂, P += e⁺ e⁺ᵀ / C_θ; that joint's hypotheses restart. Returns the number of joints."""
    if not gate:
        return 0
    accepted = 0
    for j in range(tau.shape[0]):
        best, theta = -np.inf, 0
        for i in range(ep.shape[1]):
            ratio = d[j, i] * d[j, i] / (info[j, i] + 1e-300)          # ℓ_θ (0 where no data yet)
            if ratio > best:
                best, theta = ratio, i
        if not best > threshold:
            continue
        e_p, e_t, information = ep[j, theta], et[j, theta], info[j, theta]
        size = d[j, theta] / information                               # Δ̂_θ
        p_hat[j] += e_p * size
        tau[j] += e_t * size
        a[j] += e_p * e_p / information
        b[j] += e_p * e_t / information
        c[j] += e_t * e_t / information
        ep[j, :], et[j, :], d[j, :], info[j, :] = 0.0, 0.0, 0.0, 0.0  # no hypothesis spans the correction
        accepted += 1
    return accepted


class KVARKKernelFilter(KVARKMomentumFilter):
    """``KVARKMomentumFilter`` whose ``step`` is the compiled ``kvark_step`` (module docstring).

    Same constructor, ``STATE``, ``reset``, ``configure`` and results (to rounding) as the reference; the
    state arrays are updated in place, and ``step`` hands out copies.
    """

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD) -> None:
        if problem := kernel_problem(variant, settings):
            raise ValueError(problem)
        super().__init__(variant, residual, tuning, noise, settings, name=name, sample_period=sample_period)
        n = self.n
        kmp = self._kmp_inside = isinstance(residual, KMPResidualModel) and not residual.needs
        self._consts = np.zeros((CONST_ROWS, n))
        self._consts[C_R], self._consts[C_R_MIN] = self.R, R_FLOOR * self.R
        self._consts[C_Q_P], self._consts[C_Q_TAU] = self.q_p, self.q_tau
        self._consts[C_RESIDUAL_VAR] = tuning.residual_variance
        if kmp:
            self._consts[C_NEG_HALF_INV_LS2] = residual._neg_half_inv_ls2[:, 0]
            self._consts[C_SIGMA_F2], self._consts[C_VAR_SCALE] = residual._sigma_f2, residual._var_scale
            self._support = np.ascontiguousarray(residual._s, dtype=float)
            self._weights_t = np.ascontiguousarray(np.swapaxes(residual._weights, 1, 2), dtype=float)
        else:
            self._support, self._weights_t = np.zeros((n, 1)), np.zeros((n, 1, 2))
        window = self.window
        stride = window.stride if window is not None else 1
        self._params = np.zeros(5)
        self._params[P_FORGET] = window.forgetting ** stride if window is not None else 1.0
        self._params[P_PRIOR_DOF] = window.prior_dof if window is not None else 1.0
        self._params[P_THRESHOLD] = self.onset.threshold if self.onset is not None else 0.0
        self._apply_runtime(settings)
        self._options = np.array([self.variant.heteroscedastic, self.variant.ewma, self.variant.nis,
                                  window is not None, self.onset is not None, kmp, stride], dtype=np.int64)
        # Stand-ins for an absent window (z, zz, pz, tz, age, q, scale, Σ_d) or detector (ep, et, d, c): the kernel
        # takes arrays either way and leaves them alone.
        self._no_window = (np.zeros((n, WINDOW_SNAPSHOTS)),) * 4 + (np.zeros(WINDOW_SNAPSHOTS),) + (np.zeros(n),) * 3
        self._no_onset = (np.zeros((n, 2)),) * 4
        self._compile()

    def _apply_runtime(self, settings: FilterSettings) -> None:
        super()._apply_runtime(settings)
        if hasattr(self, "_params"):                                   # the reference sets the rates before us
            self._params[P_EWMA_RATE], self._params[P_NIS_RATE] = self.ewma_rate, self.nis_rate

    def _compile(self) -> None:
        """Compile (or load from the cache) the kernel with one step on dummy data, then start afresh."""
        zeros = np.zeros(self.n)
        self.step(self.sample_period, zeros, zeros, zeros, zeros, zeros, zeros)
        self.reset()

    def _prime(self, p_prev: np.ndarray) -> None:
        """The first step after a reset: p̂ = p_{k−1}, every snapshot at τ̂_0 (``WindowVB.predict``)."""
        self.p_hat = np.array(p_prev, dtype=float)
        window = self.window
        if window is not None:
            if window.z is None:
                ones = np.ones((self.n, WINDOW_SNAPSHOTS))
                window.z, window.zz = ones * self.tau[:, None], ones * self.c[:, None]
                window.pz, window.tz = ones * self.b[:, None], ones * self.c[:, None]
            if self.Sigma_d is None:
                self.Sigma_d = np.zeros(self.n)

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if self.p_hat is None:
            self._prime(p_prev)
        if self._kmp_inside:
            mean, var = np.empty(self.n), np.empty(self.n)              # filled by the kernel
            self.prediction = mean, var
        else:
            self.prediction = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)
            mean, var = (np.ascontiguousarray(value, dtype=float) for value in self.prediction)
        window, onset = self.window, self.onset
        if window is not None:                                         # Σ_d is state with the window only
            z, zz, pz, tz, age, density, scale, sigma_d = (window.z, window.zz, window.pz, window.tz, window.age,
                                                           window.q, window.scale, self.Sigma_d)
            count, dof = window.count, window.dof
        else:
            (z, zz, pz, tz, age, density, scale, sigma_d), count, dof = self._no_window, 0, 0.0
        ep, et, d, info, slot, alarms = ((onset.ep, onset.et, onset.d, onset.c, onset.slot, onset.alarms)
                                         if onset is not None else self._no_onset + (0, 0))
        count, dof, slot, alarms = kvark_step(
            dt, qd, p, u_prev, mean, var, self.p_hat, self.tau, self.a, self.b, self.c, self.R_adaptive,
            self.nis_mean, sigma_d, z, zz, pz, tz, age, density, scale, count, dof, ep, et, d, info, slot, alarms,
            self._consts, self._params, self._options, self._support, self._weights_t)
        if window is not None:
            window.count, window.dof = count, dof
        if onset is not None:
            onset.slot, onset.alarms = slot, alarms
        return self.tau.copy(), np.diag(self.c)
