"""The numpy reference of the momentum-form K-VARK step: a test oracle, not production code.

Production steps the momentum-form filter compiled only: ``KVARKFilter`` (core/estimation/observers/kvark.py)
calls ``compiled.kvark_filter.kvark_step``. This module keeps the same equations as readable numpy, in the same
order of operations, on the production filter's settings, state and components (``KVARKMomentumFilter``,
``WindowVB``, ``OnsetDetector``, hooked in through its ``_make_window``/``_make_onset``):

- ``ReferenceMomentumFilter``: the step, eqs. 22-45 on ``[p; τ_ext]`` per joint (kvark_momentum.py's docstring);
- ``ReferenceWindowVB``: the windowed VB's predict and update (window_vb.py's docstring);
- ``ReferenceOnsetDetector`` and ``Jump``: the Willsky-Jones GLR (onset.py's docstring).

``test_compiled_step_matches_reference.py`` pins the kernel to it (to rounding) on the committed bags, and the
equation tests (``test_kvark_filter.py``) run it beside the kernel. ``reference_estimator`` is a ``ReferenceEstimator``
(reference_estimator.py) whose K-VARK momentum filter is this reference, so that its whole step runs as numpy.
Not collected as tests (no ``test_`` prefix); imported by the tests of test/core (pytest puts their directory on
``sys.path``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvark_ros.core.config import EstimatorConfig, FilterSettings
from kvark_ros.core.estimation.compiled.kvark_filter import ONSET_EVIDENCE
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.estimation.observers import Observer, ResidualPredictor, make_observer
from kvark_ros.core.estimation.observers.kvark import KVARKMomentumFilter
from kvark_ros.core.estimation.observers.momentum_observers import joseph_update
from kvark_ros.core.estimation.observers.onset import OnsetDetector
from kvark_ros.core.estimation.observers.variants import NIS_SCALE_BOUNDS, VARIANTS
from kvark_ros.core.estimation.observers.window_vb import WINDOW_MAX_RATIO, WINDOW_SNAPSHOTS, WindowVB

from reference_estimator import ReferenceEstimator, reference_predict


class ReferenceWindowVB(WindowVB):
    """``WindowVB`` with its numpy arithmetic (window_vb.py's docstring)."""

    def predict(self, h: float, tau: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Predict the snapshot covariances over the step h; returns Σ_d = q h (n,) for (K2).

        ``tau``, ``b``, ``c``: the filter's posterior at k−1 (τ̂ and P_pτ, P_ττ), (n,); all
        snapshots start there at the first step.
        """
        if self.z is None:                                             # all snapshots start at τ̂_0
            ones = np.ones((self.n, WINDOW_SNAPSHOTS))
            self.z, self.zz = ones * tau[:, None], ones * c[:, None]
            self.pz, self.tz = ones * b[:, None], ones * c[:, None]
        self.pz = self.pz + h * self.tz                                # Cov(p⁻, z) = (F P)_pz
        return self.q * h

    def twin_step(self, h: float, p: np.ndarray, u_prev: np.ndarray, mu: np.ndarray, w_p: np.ndarray,
                  sigma_d0: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, ...]:
        """One step of the twin filter held at Σ_d0 (window_vb.py's docstring), (K1)-(K5) as the filter's own with
        w_p = q_p h + h² σ²_r; returns its gain k1, k2."""
        b, hc = self.twin_b, h * self.twin_c
        p_pred = self.twin_p + h * (u_prev - mu + self.twin_tau)               # eq. 28
        a = self.twin_a + h * (b + b + hc) + w_p + sigma_d0 * (h * h / 3.0)     # (K2)
        b, c = b + hc + sigma_d0 * (h / 2.0), self.twin_c + sigma_d0
        nu = p - p_pred
        self.twin_p, self.twin_tau, self.twin_a, self.twin_b, self.twin_c, s, k2 = joseph_update(
            p_pred, self.twin_tau, a, b, c, nu, R)
        return a / s, k2

    def update(self, h: float, nu: np.ndarray, s: np.ndarray, k1: np.ndarray, k2: np.ndarray, tau: np.ndarray,
               b: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Update the snapshots with the filter's gain and close a window every m samples.

        ``nu``: innovation (n,) N·m·s; ``s``: its variance S; ``k1``, ``k2``: the gain K = [k1; k2];
        ``tau``, ``b``, ``c``: the filter's posterior at k. Returns Σ_d = q h (n,), N²·m².
        """
        pz, tz = self.pz, self.tz
        if not self.twin:                                              # the twin's snapshots stay as taken
            gain_z = pz / s[:, None]                                   # K for z: Cov(z, p⁻) / S
            self.z = self.z + gain_z * nu[:, None]
            self.zz = self.zz - pz * gain_z                            # P_zz − Cov(z, p⁻)² / S
        self.tz = tz - k2[:, None] * pz                                # Cov(x⁺, z) = Cov(x⁻, z) − K Cov(p⁻, z)
        self.pz = pz - k1[:, None] * pz
        self.age = self.age + h
        self.count += 1
        stride, snapshots, q0 = self.stride, WINDOW_SNAPSHOTS, self.q0
        if self.count % stride == 0:
            j = (self.count // stride) % snapshots
            if self.count >= stride * snapshots:                       # snapshot j spans a whole window
                delta = tau - self.z[:, j]
                stat = (delta * delta + c + self.zz[:, j] - 2.0 * self.tz[:, j]) / self.age[j]
                forget = self.forgetting ** stride
                self.scale = forget * self.scale + np.maximum(stat, 0.0) / snapshots   # eq. 38
                self.dof = forget * self.dof + 1.0 / snapshots                         # eq. 37
                dof = self.prior_dof
                q = (dof * q0 + self.scale) / (dof + self.dof)                         # eq. 39
                self.q = np.minimum(q, WINDOW_MAX_RATIO * q0)
            self.z[:, j], self.zz[:, j] = tau, c                       # new snapshot z_j = τ_k
            self.pz[:, j], self.tz[:, j] = b, c
            self.age[j] = 0.0
        return self.q * h


@dataclass(frozen=True)
class Jump:
    """Jumps accepted at one step, on ``joints`` (J,): the filter adds ``e_p · size`` to p̂,
    ``e_t · size`` to τ̂, ``e eᵀ · variance`` to each joint's P and ``e_t² · doubt`` to its P_ττ (onset.py's docstring).

    e_p, e_t: e⁺_k of the accepted onset θ (J,); size: Δ̂_θ (J,) N·m; variance: Var Δ̂_θ = 1/C (J,) N²·m²;
    doubt: Δ̂_θ² where the jump was seen on one sample (a step or an impulse, which differ in τ alone), else 0;
    step: seen on ``ONSET_EVIDENCE`` samples or more (J,) bool.
    """

    joints: np.ndarray
    e_p: np.ndarray
    e_t: np.ndarray
    size: np.ndarray
    variance: np.ndarray
    doubt: np.ndarray
    step: np.ndarray


class ReferenceOnsetDetector(OnsetDetector):
    """``OnsetDetector`` with its numpy arithmetic (onset.py's docstring)."""

    def step(self, nu: np.ndarray, R: np.ndarray, s: np.ndarray, k2: np.ndarray, h: float) -> Jump | None:
        """Add one sample's innovation to every hypothesis; the accepted jumps, if any.

        ``nu``: innovation (n,) N·m·s; ``R``: measurement variance (n,); ``s``: S of (K3);
        ``k2``: the τ component of the gain K (n,); ``h``: step, s. The hypotheses of the joints
        in the returned ``Jump`` restart.
        """
        rho = self.ep
        d, c = self.d, self.c
        d += rho * (nu / s)[:, None]
        c += rho * (rho / s[:, None])
        et = self.et
        et -= k2[:, None] * rho                                         # e⁺ = e⁻ − K ρ, K = [a⁻; b⁻] / S
        ep = rho * (R / s)[:, None]                                     # 1 − K_p = R / S
        margin = d * d
        margin -= self.threshold * c                                    # ℓ_θ > threshold ⇔ d² > threshold C
        jump = None
        if margin.max() > 0.0:
            ratio = d * d / (c + 1e-300)                                # ℓ_θ (0 where no data yet)
            joints = np.flatnonzero(ratio.max(axis=1) > self.threshold)
            theta = ratio[joints].argmax(axis=1)
            information = c[joints, theta]
            size = d[joints, theta] / information                       # Δ̂_θ
            one_sample = (self.slot - 1 - theta) % d.shape[1] < ONSET_EVIDENCE   # a step or an impulse
            doubt = np.where(one_sample, size * size, 0.0)
            jump = Jump(joints, ep[joints, theta], et[joints, theta], size, 1.0 / information, doubt, ~one_sample)
            ep[joints], et[joints] = 0.0, 0.0                           # no hypothesis spans the correction
            d[joints], c[joints] = 0.0, 0.0
            self.alarms += len(joints)
        ep += h * et                                                    # e⁻_k+1 = F e⁺_k
        self.ep = ep
        j = self.slot                                                   # newest onset replaces the oldest
        ep[:, j], et[:, j], d[:, j], c[:, j] = 0.0, 1.0, 0.0, 0.0
        self.slot = (j + 1) % d.shape[1]
        return jump


class ReferenceMomentumFilter(KVARKMomentumFilter):
    """``KVARKMomentumFilter`` with the numpy step (observers/kvark.py's docstring): the kernel's oracle."""

    def _make_window(self, prior_density: np.ndarray, window: int, forgetting: float, prior_dof: float,
                     twin: bool) -> WindowVB:
        return ReferenceWindowVB(prior_density, window, forgetting, prior_dof, twin)

    def _make_onset(self, n: int, threshold: float, window: int) -> OnsetDetector:
        return ReferenceOnsetDetector(n, threshold, window)

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        variant = self.variant
        if self.p_hat is None:
            self.p_hat = p_prev
        window = self.window
        if window is not None and window.twin and window.twin_p is None:     # the twin starts as the filter
            window.twin_p, window.twin_tau, window.twin_a, window.twin_b, window.twin_c = (
                self.p_hat, self.tau, self.a, self.b, self.c)
        mu, var_star = reference_predict(self.residual, qd, q, g)     # eqs. 22-23
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
            twin = (p, u_prev, mu, self.q_p * dt + hh * residual_var)
            self._window_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, dt, twin)
        else:
            self._vb_update(p_pred, tau_pred, a_f, b_f, c_f, nu, R, sigma_d, dt)
        if self.onset is not None:                                      # part of the Σ_d adaptation
            jump = self.onset.step(nu, R, self._last_s, self._last_k2, dt)
            if jump is not None:
                self._apply_jump(jump, dt)
        if variant.ewma:
            # eq. 31 with eq. 16's correction: E[ν²] = H P⁻ Hᵀ + R; bounded by the training R (Remark 2).
            # Weighted by w = (R/S)², ν²'s information on R relative to P⁻ = 0 (Var ν² = 2 S²), over w̄_k, the
            # weights' own EWMA: in steady state the rate stays ρ.
            a_pred = a_f + self._last_q[0]
            weight = (self.R_adaptive / self._last_s) ** 2
            self.R_weight = self.R_weight + self.ewma_rate * (weight - self.R_weight)
            updated = self.R_adaptive + self.ewma_rate * weight / self.R_weight * (nu * nu - a_pred - self.R_adaptive)
            self.R_adaptive = np.minimum(np.maximum(updated, self.R_min), self.R)   # np.clip costs 4× more
        if variant.nis:
            nis = nu * nu / self._last_s
            updated = self.nis_mean + self.nis_rate * (nis - self.nis_mean)
            self.nis_mean = np.minimum(np.maximum(updated, NIS_SCALE_BOUNDS[0]), NIS_SCALE_BOUNDS[1])
        return self.tau, np.diag(self.c)

    def _apply_jump(self, jump: Jump, h: float) -> None:
        """Correct the state for the onset detector's accepted jumps: x̂ += e⁺ Δ̂, P += e⁺ e⁺ᵀ Var Δ̂, and
        P_ττ += e⁺_τ² · doubt; then, if any was seen as a step, every joint's Σ_d at least q_c h
        (``_raise_to_contact``)."""
        joints, e_p, e_t, spread = jump.joints, jump.e_p, jump.e_t, jump.variance
        self.p_hat = self.p_hat.copy()
        self.tau = self.tau.copy()
        self.p_hat[joints] += e_p * jump.size
        self.tau[joints] += e_t * jump.size
        self.a[joints] += e_p * e_p * spread
        self.b[joints] += e_p * e_t * spread
        self.c[joints] += e_t * e_t * (spread + jump.doubt)
        if jump.step.any():
            self._raise_to_contact(h)

    def _raise_to_contact(self, h: float) -> None:
        """A contact: every joint's q̂ (window) or Σ_d (per-sample VB) at least q_c (h) (§4.7), the VB's statistics
        set so its posterior (eq. 39, eqs. 39-40) is that value."""
        window = self.window
        if window is not None:
            raised = window.q < self.contact_density
            window.q = np.where(raised, self.contact_density, window.q)
            window.scale = np.where(raised, window.q * (window.prior_dof + window.dof) - window.prior_dof * window.q0,
                                    window.scale)
            self.Sigma_d = window.q * h
        elif self.variant.vb and self.Sigma_d is not None:
            self.Sigma_d = np.maximum(self.Sigma_d, self.contact_density * h)
            self.vb_scale = self.Sigma_d * (self.vb_dof - 2.0)

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

    def _window_update(self, p_pred, tau_pred, a, b, c, nu, R, h, twin) -> None:
        """The windowed VB (``window_vb``) around the update (K2)-(K5) on (p, τ) with its Σ_d; ``twin``: p_k, u_k−1,
        μ_* and w_p for the window's twin."""
        window = self.window
        sigma_d = window.predict(h, self.tau, self.b, self.c)          # the twin starts as the filter (step)
        self._update(p_pred, tau_pred, a, b, c, nu, R, sigma_d, h)     # eqs. 42-45 on (p, τ)
        if window.twin:
            k1, k2 = window.twin_step(h, *twin, self.q_tau * h, R)
            tau, b, c = window.twin_tau, window.twin_b, window.twin_c
        else:
            k1, k2, tau, b, c = (a + self._last_q[0]) / self._last_s, self._last_k2, self.tau, self.b, self.c
        self.Sigma_d = window.update(h, nu, self._last_s, k1, k2, tau, b, c)


def reference_of(observer: KVARKMomentumFilter) -> ReferenceMomentumFilter:
    """The reference built with the arguments ``observer`` (a production momentum-form filter) was built with."""
    variant = next(name for name, value in VARIANTS.items() if value == observer.variant)
    return ReferenceMomentumFilter(variant, observer.residual, observer.tuning, observer.noise, observer.settings,
                                   name=observer.name, sample_period=observer.sample_period,
                                   contact_density=observer.contact_density)


def reference_observer(name: str, trained: TrainedModel, settings: FilterSettings,
                       oracle: ResidualPredictor | None = None) -> Observer:
    """``make_observer``'s observer, with a momentum-form K-VARK filter replaced by its reference."""
    observer = make_observer(name, trained, settings, oracle)
    return reference_of(observer) if isinstance(observer, KVARKMomentumFilter) else observer


def reference_estimator(config: EstimatorConfig, trained: TrainedModel | None = None, observer: str | None = None,
                        urdf: str | None = None, oracle: ResidualPredictor | None = None) -> ReferenceEstimator:
    """``Estimator.from_config``'s estimator as a ``ReferenceEstimator`` (its whole step numpy), with a momentum-form
    K-VARK filter replaced by its reference; other observers as they are."""
    built = Estimator.from_config(config, trained, observer, urdf, oracle)
    filtered = built.observer
    return ReferenceEstimator(config, built.robot, reference_of(filtered) if isinstance(filtered, KVARKMomentumFilter)
                              else filtered, built.trained)
