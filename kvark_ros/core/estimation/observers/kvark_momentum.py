"""K-VARK on the momentum state: the paper's filter with the momentum measured, not differenced.

Why. The virtual measurement of eq. 28 differences the momentum, ``ζ_k = p_k − p_{k−1} − …``, so
the white noise v_k of the momentum measurement ``p = M q̇`` enters as ``(v_k − v_{k−1})/t_s``:
variance ``2 R / t_s²`` per sample and correlated between consecutive samples (docs/method.md §4.1). With
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
``vbkfmo_q`` baseline): as written, from a lag-one smoother, or over windows (``window_vb``, the
default), helped at impacts by a contact-onset detector (``onset``). Per joint the filter is a
2-state KF ((K1)-(K5) of ``momentum_observers``), run for all joints at once on arrays.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.config_schema import vb_variant_problem
from kvark_ros.core.estimation.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, PerSample, ResidualPredictor
from kvark_ros.core.estimation.observers.kvark_filter import NIS_SCALE_BOUNDS, VARIANTS
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.observers.momentum_observers import KFMomentumObserver, joseph_update
from kvark_ros.core.estimation.observers.onset import Jump, OnsetDetector
from kvark_ros.core.estimation.observers.window_vb import WindowVB

R_FLOOR = 1e-2          # adaptive R never falls below this fraction of its training value


class KVARKMomentumFilter(KFMomentumObserver):
    """K-VARK (or an ablation, ``variant``) on the state ``[p; τ_ext]`` per joint.

    Tuning: ``noise`` gives R, q_p and the initial τ_ext random-walk density q_τ (the same
    values as the ``kfmo`` baseline); ``tuning.residual_variance`` replaces the KMP variance in
    the variants without heteroscedastic noise (A1). ``settings`` (``filter.*``): P_0, the VB
    keys, the onset detector's and the adaptation rates. With VB, ``window`` (``vb_variant:
    window``) and ``onset`` (``onset_threshold`` > 0) are the windowed VB and the contact-onset
    detector; ``None`` when not used.
    """

    uses_residual_model = True
    # R_min is reassigned by reset but derives from the model's R: a constant, not state.
    STATE = KFMomentumObserver.STATE + ("prediction", "R_adaptive", "nis_mean", "Sigma_d", "vb_dof", "vb_scale",
                                        "window", "onset")

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"unknown K-VARK variant '{variant}'; known: {', '.join(VARIANTS)}")
        if problem := vb_variant_problem(settings.vb_variant, "momentum"):
            raise ValueError(problem)
        if tuning.residual_variance is None:
            raise ValueError("the momentum-state K-VARK needs tuning.residual_variance; retrain the model")
        self.variant = VARIANTS[variant]
        self.residual = residual
        self.needs = frozenset(getattr(residual, "needs", ()))
        self.tuning = tuning
        self.vb_smoothed = settings.vb_variant == "smoothed"          # else paper (window: self.window)
        self.vb_iterations = settings.vb_iterations                    # M
        self.sample_period = sample_period                             # t_s the config's times convert at
        per_sample = PerSample.of(settings, sample_period)
        self.vb_forgetting = per_sample.vb_forgetting                  # ρ
        vb = self.variant.vb
        self.window = (self._make_window(noise.torque_density, per_sample.vb_window, per_sample.vb_forgetting,
                                         settings.vb_prior_dof) if vb and settings.vb_variant == "window" else None)
        self.onset = (self._make_onset(residual.n_joints, settings.onset_threshold, per_sample.onset_window)
                      if vb and settings.onset_threshold > 0.0 else None)
        self._apply_runtime(settings)
        super().__init__(residual.n_joints, noise, initial_covariance=settings.initial_covariance, settings=settings)
        self.name = name or variant

    def _make_window(self, prior_density: np.ndarray, window: int, forgetting: float, prior_dof: float) -> WindowVB:
        """The windowed VB component (``WindowVB``'s arguments); the compiled subclass keeps its state packed."""
        return WindowVB(prior_density, window, forgetting, prior_dof)

    def _make_onset(self, n: int, threshold: float, window: int) -> OnsetDetector:
        """The onset detector (``OnsetDetector``'s arguments); the compiled subclass keeps its state packed."""
        return OnsetDetector(n, threshold, window)

    def _apply_runtime(self, settings: FilterSettings) -> None:
        per_sample = PerSample.of(settings, self.sample_period)
        self.ewma_rate = per_sample.ewma_rate                          # eq. 31
        self.nis_rate = per_sample.nis_rate                            # A4

    def reset(self) -> None:
        super().reset()
        self.R_adaptive = self.R.copy()                                 # R_k, (N·m·s)²
        self.R_min = R_FLOOR * self.R
        self.nis_mean = np.ones(self.n)                                 # A4: running mean NIS per joint
        self.Sigma_d: np.ndarray | None = None                          # VB: Σ_d,k−1 per joint, N²·m²
        self.vb_dof = np.zeros(self.n)                                  # VB: λ_{k−1}
        self.vb_scale = np.zeros(self.n)                                # VB: Υ_{k−1}
        if self.window is not None:
            self.window.reset()
        if self.onset is not None:
            self.onset.reset()

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        variant = self.variant
        if self.p_hat is None:
            self.p_hat = p_prev
        mu, var_star = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)  # 22-23
        self.prediction = mu, var_star
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
        elif self.window is not None:
            self._window_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, dt)
        else:
            self._vb_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, sigma_d, dt)
        if self.onset is not None:                                      # part of the Σ_d adaptation
            jump = self.onset.step(nu, R, self._last_s, self._last_k2, dt)
            if jump is not None:
                self._apply_jump(jump)
        if variant.ewma:
            # eq. 31 with eq. 16's correction: E[ν²] = H P⁻ Hᵀ + R; bounded by the training R (Remark 2)
            a_pred = a_f + self._last_q[0]
            updated = self.R_adaptive + self.ewma_rate * (nu * nu - a_pred - self.R_adaptive)
            self.R_adaptive = np.minimum(np.maximum(updated, self.R_min), self.R)   # np.clip costs 4× more
        if variant.nis:
            nis = nu * nu / self._last_s
            updated = self.nis_mean + self.nis_rate * (nis - self.nis_mean)
            self.nis_mean = np.minimum(np.maximum(updated, NIS_SCALE_BOUNDS[0]), NIS_SCALE_BOUNDS[1])
        return self.tau, np.diag(self.c)

    def _apply_jump(self, jump: Jump) -> None:
        """Correct the state for the onset detector's accepted jumps: x̂ += e⁺ Δ̂, P += e⁺ e⁺ᵀ / C_θ."""
        joints, e_p, e_t, c = jump.joints, jump.e_p, jump.e_t, jump.information
        self.p_hat = self.p_hat.copy()
        self.tau = self.tau.copy()
        self.p_hat[joints] += e_p * jump.size
        self.tau[joints] += e_t * jump.size
        self.a[joints] += e_p * e_p / c
        self.b[joints] += e_p * e_t / c
        self.c[joints] += e_t * e_t / c

    def _update(self, p_pred, tau_pred, a, b, c, nu, R, sigma_d, h) -> np.ndarray:
        """Add the random walk's Q (K2) for per-step variance Σ_d and update (K3)-(K5); returns τ̂⁺."""
        q = (sigma_d * (h * h / 3.0), sigma_d * (h / 2.0), sigma_d)     # q_τ h³/3, q_τ h²/2, q_τ h
        self._last_q = q
        self.p_hat, self.tau, self.a, self.b, self.c, self._last_s, self._last_k2 = joseph_update(
            p_pred, tau_pred, a + q[0], b + q[1], c + q[2], nu, R)
        return self.tau

    def _vb_update(self, p_pred, tau_pred, a, b, c, nu, R, sigma_d0, h) -> None:
        """VB-IW on Σ_d per joint (eqs. 33-40, state dimension 1 per joint) with forgetting ρ."""
        rho = self.vb_forgetting
        if self.Sigma_d is None:                                        # prior at its steady state, mean Σ_d0
            self.vb_dof = np.full(self.n, 2.0 + (1.0 / (1.0 - rho) if rho < 1.0 else 1.0))
            self.Sigma_d = sigma_d0
            self.vb_scale = sigma_d0 * (self.vb_dof - 2.0)
        dof_pred = rho * (self.vb_dof - 2.0) + 2.0                      # λ_{k|k−1}
        scale_pred = rho * self.vb_scale                                # Υ_{k|k−1}
        sigma_d = self.Sigma_d
        previous = (self.a, self.b, self.c)                            # P_{k−1|k−1} per joint
        smoothed = self.vb_smoothed
        for _ in range(self.vb_iterations):
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
        """The windowed VB (``window_vb``) around the update (K2)-(K5) on (p, τ) with its Σ_d."""
        sigma_d = self.window.predict(h, self.tau, self.b, self.c)
        self._update(p_pred, tau_pred, a, b, c, nu, R, sigma_d, h)     # eqs. 42-45 on (p, τ)
        k1 = (a + self._last_q[0]) / self._last_s
        self.Sigma_d = self.window.update(h, nu, self._last_s, k1, self._last_k2, self.tau, self.b, self.c)
