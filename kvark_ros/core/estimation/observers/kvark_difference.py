"""K-VARK in the paper's difference form (docs/method.md §4.1): the disturbance KF on the virtual measurement eq. 28,
every variant of ``variants``, in numpy (``filter.measurement: difference``; the default momentum form is
``kvark.KVARKFilter``). Its P is full (the VB couples the joints), which the estimator's post-step takes as is.

Units. Eq. 28 divided by t_s gives the measurement in torque units,
``y_k = ζ_k / t_s = τ_ext,k + ν_k / t_s``, so ``H = I`` and ``R_k = Σ_ν,k / t_s² = Σ_*,k + Σ_emp,k / t_s²``
(eq. 30). This is the paper's filter exactly, with covariances that do not depend on the rate.

Sign. The paper writes ``ζ = −t_s τ_ext`` (eqs. 28-29, H = −t_s I) for torque acting *from* the
robot; we output torque acting *on* the robot (docs/method.md §1.2). The flip happens in one place:
``_virtual_measurement`` below, where H = +I.
"""
from __future__ import annotations

import functools

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.config_schema import vb_variant_problem
from kvark_ros.core.estimation.linalg import solve_spd
from kvark_ros.core.estimation.observers.base import (DEFAULT_SAMPLE_PERIOD, FilterTuning, Observer, PerSample,
                                                      ResidualPredictor)
from kvark_ros.core.estimation.observers.variants import NIS_SCALE_BOUNDS, VARIANTS


def kalman_update(x_pred: np.ndarray, P_pred: np.ndarray, r: np.ndarray,
                  R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measurement update with H = I and diagonal R (n,).

    Returns the posterior ``x`` (n,), ``P`` (n, n) in Joseph form, and the gain ``K`` (n, n).
    """
    n = len(r)
    S = P_pred.copy()
    S.flat[:: n + 1] += R                                               # S = H P Hᵀ + R
    K = solve_spd(S, P_pred).T                                          # eq. 43: K = P Hᵀ S⁻¹ (P, S symmetric)
    x = x_pred + K @ r                                                  # eq. 44
    I_K = _identity(n) - K
    P = I_K @ P_pred @ I_K.T + (K * R) @ K.T                            # eq. 45, Joseph form
    return x, 0.5 * (P + P.T), K


@functools.lru_cache(maxsize=8)
def _identity(n: int) -> np.ndarray:
    eye = np.eye(n)
    eye.setflags(write=False)
    return eye


class KVARKDifferenceFilter(Observer):
    """Disturbance KF with KMP residual correction; ``variant`` selects K-VARK or an ablation.

    State ``x = τ_ext`` (n,) N·m, random walk (eq. 32); covariance ``P`` (n, n) N²·m².
    ``residual`` is the KMP model for K-VARK and the ablations, another learned model for the
    baselines that share this filter, or the plant's true friction for the oracle.
    ``settings`` (``filter.*``): ``initial_covariance``, the VB keys and the adaptation rates.
    """

    uses_residual_model = True
    diagonal_covariance = False     # the VB's Σ_d couples the joints
    STATE = Observer.STATE + ("prediction", "x", "P", "empirical", "nis_mean", "Sigma_d", "vb_dof", "vb_scale")

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD) -> None:
        super().__init__(residual.n_joints, settings)
        self.sample_period = sample_period                             # t_s the config's times convert at
        if variant not in VARIANTS:
            raise ValueError(f"unknown K-VARK variant '{variant}'; known: {', '.join(VARIANTS)}")
        if VARIANTS[variant].vb and (problem := vb_variant_problem(settings.vb_variant, "difference")):
            raise ValueError(problem)
        if len(tuning.process_noise_density) != self.n:
            raise ValueError(f"filter tuning has {len(tuning.process_noise_density)} joints, "
                             f"the residual model {self.n}")
        self.name = name or variant
        self.variant = VARIANTS[variant]
        self.residual = residual
        self.needs = frozenset(getattr(residual, "needs", ()))
        self.tuning = tuning
        self.initial_covariance = settings.initial_covariance          # P_0 = value · I, N²·m²
        self.vb_paper = settings.vb_variant == "paper"                 # else huang
        self.vb_iterations = settings.vb_iterations                    # M
        self.vb_forgetting = PerSample.of(settings, sample_period).vb_forgetting   # ρ
        self.huang_tau = settings.huang_tau                            # τ of the huang prior
        self._apply_runtime(settings)
        self.reset()

    def _apply_runtime(self, settings: FilterSettings) -> None:
        per_sample = PerSample.of(settings, self.sample_period)
        self.ewma_rate = per_sample.ewma_rate                          # eq. 31
        self.nis_rate = per_sample.nis_rate                            # A4

    def reset(self) -> None:
        n = self.n
        self.x = np.zeros(n)                                           # Algorithm 1, line 12
        self.P = self.initial_covariance * np.eye(n)
        self.empirical = self.tuning.empirical_variance.copy()         # Σ_emp / t_s², N²·m²
        self.nis_mean = float(n)                                       # A4: running mean NIS
        self.Sigma_d: np.ndarray | None = None                         # VB: Σ_d,k−1, set on first step
        self.vb_dof = 0.0                                              # VB: λ_{k−1}
        self.vb_scale = np.zeros((n, n))                               # VB: Υ_{k−1}

    def _virtual_measurement(self, dt: float, mu: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
                             u_prev: np.ndarray) -> np.ndarray:
        """Eq. 28 over t_s, our sign: y = (p_k − p_{k−1})/t_s − u_{k−1} + μ_* = τ_ext + noise."""
        return (p - p_prev) / dt - u_prev + mu

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        variant = self.variant
        mu, var_star = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)  # 22-23
        self.prediction = mu, var_star
        y = self._virtual_measurement(dt, mu, p, p_prev, u_prev)
        if variant.heteroscedastic:
            R = var_star + self.empirical                              # eq. 30 / t_s²
        else:
            R = self.tuning.measurement_variance
        x_pred = self.x                                                # eq. 41 (random walk)
        r = y - x_pred                                                 # innovation, Algorithm 1 line 20
        if variant.ewma:
            # eq. 31, bounded by the training median (v2 Remark 2)
            self.empirical = np.minimum(self.empirical + self.ewma_rate * (r * r - self.empirical),
                                        self.tuning.empirical_variance)
        process = self.tuning.process_noise_density * dt              # Σ_d = diag(q) t_s
        if variant.vb:
            self.x, self.P = (self._vb_paper(dt, x_pred, r, R, process) if self.vb_paper
                              else self._vb_huang(x_pred, r, R, process))
            return self.x, self.P
        if variant.nis:
            process = process * self.nis_mean / self.n                 # A4: Σ_d = α Σ_d0, α from NIS
        P_pred = self.P.copy()
        P_pred.flat[:: self.n + 1] += process                          # eq. 42
        self.x, self.P, K = kalman_update(x_pred, P_pred, r, R)
        if variant.nis:
            # normalised innovation squared rᵀ S⁻¹ r, with S⁻¹ = P_pred⁻¹ K from eq. 43
            nis = float(r @ solve_spd(P_pred, K @ r))
            self.nis_mean += self.nis_rate * (nis - self.nis_mean)
            self.nis_mean = float(np.clip(self.nis_mean, self.n * NIS_SCALE_BOUNDS[0],
                                          self.n * NIS_SCALE_BOUNDS[1]))
        return self.x, self.P

    def _vb_paper(self, dt: float, x_pred: np.ndarray, r: np.ndarray, R: np.ndarray,
                  process: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """VB-IW on Σ_d as the paper writes it (eqs. 33-45), with Särkkä-Nummenmaa forgetting.

        Forgetting prediction (docs/method.md §4.4): ``λ_{k|k−1} = ρ(λ_{k−1} − n − 1) + n + 1``,
        ``Υ_{k|k−1} = ρ Υ_{k−1}``; the prior starts at its steady state ``λ − n − 1 = 1/(1 − ρ)``
        with mean ``Σ_d0`` from training. Each of the M iterations re-reads eq. 42 with the latest
        Σ_d, otherwise the iterations would repeat one computation.
        """
        n, rho = self.n, self.vb_forgetting
        if self.Sigma_d is None:
            self.vb_dof = n + 1 + 1.0 / (1.0 - rho) if rho < 1.0 else n + 2.0
            self.Sigma_d = np.diag(process)
            self.vb_scale = self.Sigma_d * (self.vb_dof - n - 1)
        dof_pred = rho * (self.vb_dof - n - 1) + n + 1
        scale_pred = rho * self.vb_scale
        Sigma_d = self.Sigma_d
        x, P = x_pred, self.P
        for _ in range(self.vb_iterations):
            P_pred = self.P + Sigma_d                                   # eq. 42
            x, P, _ = kalman_update(x_pred, P_pred, r, R)               # eqs. 43-45
            e = x - x_pred                                              # eq. 34
            self.vb_dof = dof_pred + 1.0                                # eq. 37
            self.vb_scale = scale_pred + e[:, None] * e + P             # eq. 38
            Sigma_d = self.vb_scale / (self.vb_dof - n - 1)             # eqs. 39-40
        self.Sigma_d = Sigma_d
        return x, P

    def _vb_huang(self, x_pred: np.ndarray, r: np.ndarray, R: np.ndarray,
                  process: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reading of eq. 35 after Huang et al. (IEEE TAC 2018): inverse-Wishart on P_{k|k−1}.

        Prior ``IW(t = n + τ + 1, T = τ (P_{k−1} + Σ_d0))``; each iteration sets
        ``T = T_prior + P + e eᵀ``, ``t = t_prior + 1`` and uses ``E[P_{k|k−1}⁻¹]⁻¹ = T / t``.
        """
        n, tau = self.n, self.huang_tau
        P_nominal = self.P.copy()
        P_nominal.flat[:: n + 1] += process                             # eq. 42 with the trained Σ_d0
        scale_prior = tau * P_nominal
        dof = n + tau + 2.0
        x, P = x_pred, P_nominal
        for _ in range(self.vb_iterations):
            e = x - x_pred
            P_tilde = (scale_prior + P + e[:, None] * e) / dof          # eq. 35: E[P_{k|k−1}⁻¹]⁻¹
            x, P, _ = kalman_update(x_pred, P_tilde, r, R)              # eqs. 43-45
        self.Sigma_d = P_tilde - self.P
        return x, P
