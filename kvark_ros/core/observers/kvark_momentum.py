"""K-VARK on the momentum state: the paper's filter with the momentum measured, not differenced.

Why. The virtual measurement of eq. 28 differences the momentum, ``ζ_k = p_k − p_{k−1} − …``, so
the white noise v_k of the momentum measurement ``p = M q̇`` enters as ``(v_k − v_{k−1})/t_s``:
variance ``2 R / t_s²`` per sample and correlated between consecutive samples (DESIGN §2). With
the simulated Panda's velocity noise (encoder 2¹⁹ counts, 500 Hz) that is about 3 N·m per sample
on joint 1, twenty times the friction the residual model corrects, and covariance matching then
makes the difference-form filter very slow (see README, Results). Putting p in the state, as
Wahrburg et al. do, gives the same model with white measurement noise:

    p_k = p_{k−1} + t_s (u_{k−1} − μ_*,k + τ_ext,k−1) + w_p,   w_p ~ N(0, t_s² Σ_*,k + q_p t_s)   (eq. 28 as a model)
    τ_ext,k = τ_ext,k−1 + w_d,                                 w_d ~ N(0, Σ_d,k)                   (eq. 32)
    p_meas,k = p_k + v_k,                                      v_k ~ N(0, R_k)

The paper's pieces keep their roles: the KMP mean corrects the momentum prediction (eq. 22), the
KMP variance is the heteroscedastic uncertainty of that prediction (eq. 30's t_s² Σ_*), the
EWMA adapts the empirical noise from innovations (eq. 31 with eq. 16's ``− H P Hᵀ`` correction,
capped at the training value as in v2 Remark 2), and Σ_d follows the VB inverse-Wishart
recursion (eqs. 33-40, with forgetting), one joint at a time (a mean-field over joints, as the
``vbkfmo_q`` baseline). Per joint the filter is a 2-state KF ((K1)-(K5) of
``momentum_observers``), run for all joints at once on arrays.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.observers.base import FilterTuning, ResidualPredictor
from kvark_ros.core.observers.kvark_filter import NIS_SCALE_BOUNDS, VARIANTS
from kvark_ros.core.observers.momentum_observers import KFMomentumObserver, MomentumNoise, joseph_update

R_FLOOR = 1e-2          # adaptive R never falls below this fraction of its training value
WINDOW_SNAPSHOTS = 5    # window VB: staggered windows, one closing every vb_window / 5 samples
WINDOW_MAX_RATIO = 1e4  # window VB: Σ_d never exceeds this multiple of the prior Σ_d0


class KVARKMomentumFilter(KFMomentumObserver):
    """K-VARK (or an ablation, ``variant``) on the state ``[p; τ_ext]`` per joint.

    Tuning: ``noise`` gives R, q_p and the initial τ_ext random-walk density q_τ (the same
    values as the ``kfmo`` baseline); ``tuning.residual_variance`` replaces the KMP variance in
    the variants without heteroscedastic noise (A1).
    """

    uses_residual_model = True

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 config: EstimatorConfig, name: str | None = None) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"unknown K-VARK variant '{variant}'; known: {', '.join(VARIANTS)}")
        if config.vb_variant == "huang":
            raise ValueError("filter.vb_variant huang is implemented for filter.measurement: difference only")
        if tuning.residual_variance is None:
            raise ValueError("the momentum-state K-VARK needs tuning.residual_variance; retrain the model")
        self.variant = VARIANTS[variant]
        self.residual = residual
        self.tuning = tuning
        self.config = config
        super().__init__(residual.n_joints, noise, initial_covariance=config.initial_covariance)
        self.name = name or variant

    def reset(self) -> None:
        super().reset()
        self.R_adaptive = self.R.copy()                                 # R_k, (N·m·s)²
        self.R_min = R_FLOOR * self.R
        self.nis_mean = np.ones(self.n)                                 # A4: running mean NIS per joint
        self.Sigma_d: np.ndarray | None = None                          # VB: Σ_d,k−1 per joint, N²·m²
        self.vb_dof = np.zeros(self.n)                                  # VB: λ_{k−1}
        self.vb_scale = np.zeros(self.n)                                # VB: Υ_{k−1}
        self.win_z: np.ndarray | None = None                            # window VB (_window_update)
        self.win_zz = self.win_pz = self.win_tz = None
        self.win_age = np.zeros(WINDOW_SNAPSHOTS)
        self.win_count = 0
        self.win_q = self.q_tau.copy()
        self.win_scale = np.zeros(self.n)
        self.win_dof = 0.0
        m = max(self.config.onset_window, 2)                            # onset GLR (_onset_step)
        self.glr_ep, self.glr_et = np.zeros((self.n, m)), np.zeros((self.n, m))
        self.glr_d, self.glr_c = np.zeros((self.n, m)), np.zeros((self.n, m))
        self.glr_slot = 0
        self.onset_alarms = 0                                           # joint alarms since reset

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        variant, config = self.variant, self.config
        if self.p_hat is None:
            self.p_hat = p_prev
        mu, var_star = self.residual.predict(qd)                        # eqs. 22-23
        tau_pred = self.tau                                             # eq. 41
        p_pred = self.p_hat + dt * (u_prev - mu + tau_pred)              # eq. 28 as the momentum model
        residual_var = var_star if variant.heteroscedastic else self.tuning.residual_variance
        hh = dt * dt
        b, hc = self.b, dt * self.c                                     # F P Fᵀ, F = [[1, h], [0, 1]]
        a_f = self.a + dt * (b + b + hc) + self.q_p * dt + hh * residual_var   # + w_p (eq. 30's t_s² Σ_*)
        b_f, c_f = b + hc, self.c
        nu = p - p_pred                                                 # innovation
        R = self.R_adaptive if variant.ewma else self.R
        sigma_d = self.q_tau * dt                                       # Σ_d from training (eq. 32)
        if variant.nis:
            sigma_d = sigma_d * self.nis_mean                           # A4: Σ_d = α Σ_d0
        if not variant.vb:
            self._update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, sigma_d, dt)
        elif config.vb_variant == "window":
            self._window_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, dt)
        else:
            self._vb_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, sigma_d, dt)
        if variant.vb and config.onset_threshold > 0.0:                 # part of the Σ_d adaptation
            self._onset_step(nu, R, dt)
        if variant.ewma:
            # eq. 31 with eq. 16's correction: E[ν²] = H P⁻ Hᵀ + R; bounded by the training R (Remark 2)
            a_pred = a_f + self._last_q[0]
            updated = self.R_adaptive + config.ewma_rate * (nu * nu - a_pred - self.R_adaptive)
            self.R_adaptive = np.minimum(np.maximum(updated, self.R_min), self.R)   # np.clip costs 4× more
        if variant.nis:
            nis = nu * nu / self._last_s
            updated = self.nis_mean + config.nis_rate * (nis - self.nis_mean)
            self.nis_mean = np.minimum(np.maximum(updated, NIS_SCALE_BOUNDS[0]), NIS_SCALE_BOUNDS[1])
        return self.tau, np.diag(self.c)

    def _onset_step(self, nu: np.ndarray, R: np.ndarray, h: float) -> None:
        """Contact-onset detector: Willsky-Jones GLR for a jump in τ_ext, with state correction.

        Why. Eq. 32 models τ_ext as a random walk with small steps, and the VB (eqs. 33-40, here
        ``_window_update``) learns a larger Σ_d only from the *estimated* change of τ_ext, which
        after an impact lags the true one by the filter's own time constant (~40 ms on the Panda).
        An impact is better modelled as a jump: τ_ext,k = τ_ext,k−1 + Δ·1[k = θ] + w_d, with
        unknown onset θ and size Δ. The innovation ν (the sequence whose whiteness eqs. 16 and 31
        rely on) then carries the jump's signature: with the filter's own gains, a unit jump
        between update θ−1 and prediction θ leaves the state error e⁻_θ = (0, 1) (p_θ does not yet
        feel it), and for k ≥ θ, with (K1)-(K4) of ``momentum_observers``,

            ρ_k = H e⁻_k = e⁻_p,k,   e⁺_k = e⁻_k − K_k ρ_k,   e⁻_k+1 = F e⁺_k,   ν_k = ρ_k Δ + ν⁰_k

        with ν⁰ white, variance S_k (K3). The generalized likelihood ratio (Willsky & Jones, IEEE
        TAC 1976) maximises over Δ in closed form and over θ in a window of the last M samples
        (``filter.onset_window``):

            d_θ = Σ_k ρ_k ν_k / S_k,   C_θ = Σ_k ρ_k² / S_k,   Δ̂_θ = d_θ / C_θ,   ℓ_θ = d_θ² / C_θ

        ℓ_θ = 2 ln Λ is χ²(1) under "no jump" for a fixed θ. When max_θ ℓ_θ exceeds
        ``filter.onset_threshold`` (0 = off) on a joint, the jump is accepted there and the
        filter is corrected as if it had been modelled from θ on: x̂ += e⁺_k Δ̂ and
        P += e⁺_k e⁺_kᵀ / C_θ (Var Δ̂ = 1/C_θ), then that joint's hypotheses restart. The window
        VB then sees the jump in τ̂ − ẑ_j and raises Σ_d for the transient that follows the impact
        (eq. 38's statistic), and forgets it as before. Per joint, hypotheses live in a ring of M
        slots, one new onset per sample, arrays (n, M): a few vector operations per step.

        The detector belongs to the Σ_d adaptation (a jump is the limit of a large Σ_d for one
        sample), so only the variants with VB use it; the fixed-Q ablations (``kf``, ``kmp_kf*``)
        stay the paper's baselines.
        """
        s = self._last_s
        rho = self.glr_ep
        d, c = self.glr_d, self.glr_c
        d += rho * (nu / s)[:, None]
        c += rho * (rho / s[:, None])
        et = self.glr_et
        et -= self._last_k2[:, None] * rho                              # e⁺ = e⁻ − K ρ, K = [a⁻; b⁻] / S
        ep = rho * (R / s)[:, None]                                     # 1 − K_p = R / S
        margin = d * d
        margin -= self.config.onset_threshold * c                       # ℓ_θ > threshold ⇔ d² > threshold C
        if margin.max() > 0.0:
            ratio = d * d / (c + 1e-300)                                # ℓ_θ (0 where no data yet)
            joints = np.flatnonzero(ratio.max(axis=1) > self.config.onset_threshold)
            self._onset_correct(joints, ratio, ep, et, h)
            ep, et = self.glr_ep, self.glr_et
        ep += h * et                                                    # e⁻_k+1 = F e⁺_k
        self.glr_ep = ep
        j = self.glr_slot                                               # newest onset replaces the oldest
        ep[:, j], et[:, j], d[:, j], c[:, j] = 0.0, 1.0, 0.0, 0.0
        self.glr_slot = (j + 1) % d.shape[1]

    def _onset_correct(self, joints: np.ndarray, ratio: np.ndarray, ep: np.ndarray, et: np.ndarray,
                       h: float) -> None:
        """Apply the accepted jumps of ``_onset_step`` on ``joints``; restart their hypotheses."""
        theta = ratio[joints].argmax(axis=1)
        c = self.glr_c[joints, theta]
        jump = self.glr_d[joints, theta] / c
        e_p, e_t = ep[joints, theta], et[joints, theta]
        self.p_hat = self.p_hat.copy()
        self.tau = self.tau.copy()
        self.p_hat[joints] += e_p * jump
        self.tau[joints] += e_t * jump
        self.a[joints] += e_p * e_p / c
        self.b[joints] += e_p * e_t / c
        self.c[joints] += e_t * e_t / c
        ep[joints], et[joints] = 0.0, 0.0                               # no hypothesis spans the correction
        self.glr_ep, self.glr_et = ep, et
        self.glr_d[joints], self.glr_c[joints] = 0.0, 0.0
        self.onset_alarms += len(joints)

    def _update(self, p_pred, tau_pred, a, b, c, nu, R, sigma_d, h) -> np.ndarray:
        """Add the random walk's Q (K2) for per-step variance Σ_d and update (K3)-(K5); returns τ̂⁺."""
        q = (sigma_d * (h * h / 3.0), sigma_d * (h / 2.0), sigma_d)     # q_τ h³/3, q_τ h²/2, q_τ h
        self._last_q = q
        self.p_hat, self.tau, self.a, self.b, self.c, self._last_s, self._last_k2 = joseph_update(
            p_pred, tau_pred, a + q[0], b + q[1], c + q[2], nu, R)
        return self.tau

    def _vb_update(self, p_pred, tau_pred, a, b, c, nu, R, sigma_d0, h) -> None:
        """VB-IW on Σ_d per joint (eqs. 33-40, state dimension 1 per joint) with forgetting ρ."""
        rho = self.config.vb_forgetting
        if self.Sigma_d is None:                                        # prior at its steady state, mean Σ_d0
            self.vb_dof = np.full(self.n, 2.0 + (1.0 / (1.0 - rho) if rho < 1.0 else 1.0))
            self.Sigma_d = sigma_d0
            self.vb_scale = sigma_d0 * (self.vb_dof - 2.0)
        dof_pred = rho * (self.vb_dof - 2.0) + 2.0                      # λ_{k|k−1}
        scale_pred = rho * self.vb_scale                                # Υ_{k|k−1}
        sigma_d = self.Sigma_d
        previous = (self.a, self.b, self.c)                            # P_{k−1|k−1} per joint
        smoothed = self.config.vb_variant == "smoothed"
        for _ in range(self.config.vb_iterations):
            tau = self._update(p_pred, tau_pred, a, b, c, nu, R, sigma_d, h)   # eqs. 42-45
            e = tau - tau_pred                                          # eq. 34
            if smoothed:
                increment = self._smoothed_increment(previous, nu, h)
            else:
                increment = e * e + self.c                              # eq. 38 as written
            self.vb_dof = dof_pred + 1.0                                # eq. 37
            self.vb_scale = scale_pred + increment                      # eq. 38
            sigma_d = self.vb_scale / (self.vb_dof - 2.0)               # eqs. 39-40 (n = 1 per joint)
        self.Sigma_d = sigma_d

    def _smoothed_increment(self, previous: tuple[np.ndarray, ...], nu: np.ndarray, h: float) -> np.ndarray:
        """``E[(τ_k − τ_{k−1})² | y_1:k]`` per joint from a lag-one Rauch-Tung-Striebel smoother.

        The statistic eq. 38 stands for. As written, ``e² + P_{k|k}`` counts the posterior
        uncertainty of τ_k as if τ_{k−1} were known, so Σ_d can never fall below P_{k|k}. With the
        smoother gain G = P_{k−1} Fᵀ (P⁻)⁻¹ and the optimal gain K = P⁻Hᵀ/s, the smoothed increment
        ŵ = e − (G K ν)_τ, P_{k−1|k} = P_{k−1} − G K s Kᵀ Gᵀ and P_{k,k−1|k} = (I − KH) F P_{k−1}
        reduce, with r = (P_{k−1} Fᵀ)_τp = b_{k−1} + h c_{k−1}, to
        ``(k₂ν − rν/s)² + c_k − c_{k−1} − r²/s + 2 k₂ r`` (checked against the matrix form).
        """
        _, b0, c0 = previous
        r = b0 + h * c0
        s, k2 = self._last_s, self._last_k2
        w_hat = (k2 - r / s) * nu
        return np.maximum(w_hat * w_hat + self.c - c0 - r * r / s + 2.0 * k2 * r, 0.0)

    def _window_update(self, p_pred, tau_pred, a, b, c, nu, R, h) -> None:
        """VB-IW on Σ_d per joint from the smoothed change of τ_ext over a window of L samples.

        Why a window. One momentum sample says almost nothing about one step's increment
        τ_k − τ_{k−1} (its information is ~h² Σ_d / R ≈ 1e-4 on the Panda), so the lag-one
        statistic (``smoothed``) returns the prior and Σ_d never moves. Over L samples the
        random walk (eq. 32) gives ``E[(τ_k − τ_{k−L})²] = L Σ_d``, which the data resolve for
        L of a few tens of samples. The filter carries S = WINDOW_SNAPSHOTS snapshots z_j of τ_ext
        (z_j = τ_{k_j}, no dynamics, not measured) in its state, so the joint posterior of
        (τ_k, z_j) given y_1:k, cross covariance included, comes from the ordinary update; the
        (p, τ) estimate is unchanged by them. A snapshot taken t_j seconds ago gives the density
        statistic ``s_j = ((τ̂_k − ẑ_j)² + P_ττ + P_zz − 2 P_τz) / t_j`` (N²·m²/s). The IW
        posterior (eqs. 36-39, n = 1 per joint) with prior mean q_0 (training, Σ_d0 = q_0 h) and
        dof ν_0 (``filter.vb_prior_dof``), forgetting ρ per sample (``filter.vb_forgetting``)
        applied to the data part only, so that Σ_d returns to the prior:

            λ_k = ν_0 + 2 + ρ^m (λ_{k−m} − ν_0 − 2) + 1/S          (eq. 37; windows overlap S-fold)
            Υ_k = ν_0 q_0 + ρ^m (Υ_{k−m} − ν_0 q_0) + s_j / S      (eq. 38 with the windowed statistic)
            Σ_d,k = h Υ_k / (λ_k − 2)                               (eq. 39), at most WINDOW_MAX_RATIO Σ_d0

        with m = L / S samples between closing windows. ``filter.vb_iterations`` does not apply:
        the statistic comes from samples already filtered.

        State (arrays (n,) or (n, S)): ``win_z`` ẑ_j N·m, ``win_zz`` Var z_j N²·m², ``win_pz`` and
        ``win_tz`` Cov(p, z_j) N·m²·s and Cov(τ, z_j) N²·m², ``win_age`` (S,) seconds since
        snapshot j, ``win_q`` the current density estimate N²·m²/s, ``win_scale``/``win_dof`` the
        forgotten data parts of Υ and λ.
        """
        snapshots = WINDOW_SNAPSHOTS
        stride = max(self.config.vb_window // snapshots, 1)
        q0 = self.q_tau                                                 # prior density, N²·m²/s
        if self.win_z is None:                                          # all snapshots start at τ̂_0
            ones = np.ones((self.n, snapshots))
            self.win_z, self.win_zz = ones * self.tau[:, None], ones * self.c[:, None]
            self.win_pz, self.win_tz = ones * self.b[:, None], ones * self.c[:, None]
            self.win_q = q0.copy()
        pz = self.win_pz + h * self.win_tz                              # Cov(p⁻, z) = (F P)_pz
        tz = self.win_tz
        self._update(p_pred, tau_pred, a, b, c, nu, R, self.win_q * h, h)   # eqs. 42-45 on (p, τ)
        s = self._last_s[:, None]
        gain_z = pz / s                                                 # K for z: Cov(z, p⁻) / S
        self.win_z = self.win_z + gain_z * nu[:, None]
        self.win_zz = self.win_zz - pz * gain_z                         # P_zz − Cov(z, p⁻)² / S
        k1 = (a + self._last_q[0]) / self._last_s
        self.win_tz = tz - self._last_k2[:, None] * pz                  # Cov(x⁺, z) = Cov(x⁻, z) − K Cov(p⁻, z)
        self.win_pz = pz - k1[:, None] * pz
        self.win_age = self.win_age + h
        self.win_count += 1
        if self.win_count % stride == 0:
            j = (self.win_count // stride) % snapshots
            if self.win_count >= stride * snapshots:                    # snapshot j spans a whole window
                delta = self.tau - self.win_z[:, j]
                stat = (delta * delta + self.c + self.win_zz[:, j] - 2.0 * self.win_tz[:, j]) / self.win_age[j]
                forget = self.config.vb_forgetting ** stride
                self.win_scale = forget * self.win_scale + np.maximum(stat, 0.0) / snapshots   # eq. 38
                self.win_dof = forget * self.win_dof + 1.0 / snapshots                         # eq. 37
                dof = self.config.vb_prior_dof
                q = (dof * q0 + self.win_scale) / (dof + self.win_dof)                         # eq. 39
                self.win_q = np.minimum(q, WINDOW_MAX_RATIO * q0)
            self.win_z[:, j], self.win_zz[:, j] = self.tau, self.c      # new snapshot z_j = τ_k
            self.win_pz[:, j], self.win_tz[:, j] = self.b, self.c
            self.win_age[j] = 0.0
        self.Sigma_d = self.win_q * h
