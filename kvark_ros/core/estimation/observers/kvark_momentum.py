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
each innovation weighted by (R/S)², its information on R, so that a sample after a jump, whose
P⁻ dwarfs R, cannot pull R to its floor; capped at the training value as in v2 Remark 2), and
Σ_d follows the VB inverse-Wishart recursion (eqs. 33-40, with forgetting), one joint at a time
(a mean-field over joints, as the ``vbkfmo_q`` baseline): as written, from a lag-one smoother, or
over windows (``window_vb``, the default), helped at impacts by a contact-onset detector
(``onset``). Per joint the filter is a 2-state KF ((K1)-(K5) of ``momentum_observers``), run for
all joints at once on arrays.

The step runs compiled only (``kvark_kernel.KVARKKernelFilter``, ``step_kernel.kvark_step``); this module holds what
the filter is built from: its settings, state, components, ``reset`` and ``configure``.
"""
from __future__ import annotations

from abc import abstractmethod

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.config_schema import vb_variant_problem
from kvark_ros.core.estimation.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, PerSample, ResidualPredictor
from kvark_ros.core.estimation.observers.kvark_filter import VARIANTS
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.observers.momentum_observers import KFMomentumObserver
from kvark_ros.core.estimation.observers.onset import OnsetDetector
from kvark_ros.core.estimation.observers.window_vb import WindowVB

R_FLOOR = 1e-2          # adaptive R never falls below this fraction of its training value


class KVARKMomentumFilter(KFMomentumObserver):
    """K-VARK (or an ablation, ``variant``) on the state ``[p; τ_ext]`` per joint.

    Tuning: ``noise`` gives R, q_p and the initial τ_ext random-walk density q_τ (the same
    values as the ``kfmo`` baseline); ``tuning.residual_variance`` replaces the KMP variance in
    the variants without heteroscedastic noise (A1). ``settings`` (``filter.*``): P_0, the VB
    keys, the onset detector's and the adaptation rates. With VB, ``window`` (``vb_variant:
    window``) and ``onset`` (``onset_threshold`` > 0) are the windowed VB and the contact-onset
    detector; ``None`` when not used. ``contact_density`` q_c (n,) N²·m²/s: an accepted onset
    raises every joint's q_τ to at least q_c (``filter.onset_contact_bandwidth``, §4.7; None: 0, no raise).

    ``step`` is abstract: the one implementation is the compiled ``KVARKKernelFilter`` (``observers.kvark_kernel``,
    ``step_kernel.kvark_step``), which ``make_observer`` builds for the momentum form. Its readable numpy
    reference, the same equations in the same order, is ``ReferenceMomentumFilter`` in
    test/core/reference_filter.py, pinned to the kernel by test/core/test_compiled_step_matches_reference.py.
    """

    uses_residual_model = True
    # R_min is reassigned by reset but derives from the model's R: a constant, not state.
    STATE = KFMomentumObserver.STATE + ("prediction", "R_adaptive", "R_weight", "nis_mean", "Sigma_d", "vb_dof",
                                        "vb_scale", "window", "onset")

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD, contact_density: np.ndarray | None = None) -> None:
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
                                         settings.vb_prior_dof, settings.vb_window_source == "prior")
                       if vb and settings.vb_variant == "window" else None)
        self.onset = (self._make_onset(residual.n_joints, settings.onset_threshold, per_sample.onset_window)
                      if vb and settings.onset_threshold > 0.0 else None)
        # q_c, N²·m²/s: the least q_τ after an accepted onset, on every joint (§4.7); 0 (no raise) by default
        self.contact_density = (np.zeros(residual.n_joints) if contact_density is None
                                else np.asarray(contact_density, dtype=float))
        self._apply_runtime(settings)
        super().__init__(residual.n_joints, noise, initial_covariance=settings.initial_covariance, settings=settings)
        self.name = name or variant

    def _make_window(self, prior_density: np.ndarray, window: int, forgetting: float, prior_dof: float,
                     twin: bool) -> WindowVB:
        """The windowed VB's state (``WindowVB``'s arguments): packed in the compiled subclass, stepped in numpy by the
        test reference."""
        return WindowVB(prior_density, window, forgetting, prior_dof, twin)

    def _make_onset(self, n: int, threshold: float, window: int) -> OnsetDetector:
        """The onset detector's state (``OnsetDetector``'s arguments): packed in the compiled subclass, stepped in numpy
        by the test reference."""
        return OnsetDetector(n, threshold, window)

    def _apply_runtime(self, settings: FilterSettings) -> None:
        per_sample = PerSample.of(settings, self.sample_period)
        self.ewma_rate = per_sample.ewma_rate                          # eq. 31
        self.nis_rate = per_sample.nis_rate                            # A4

    def reset(self) -> None:
        super().reset()
        self.R_adaptive = self.R.copy()                                 # R_k, (N·m·s)²
        self.R_weight = np.ones(self.n)                                 # w̄_k, the EWMA's mean weight (§4.3)
        self.R_min = R_FLOOR * self.R
        self.nis_mean = np.ones(self.n)                                 # A4: running mean NIS per joint
        self.Sigma_d: np.ndarray | None = None                          # VB: Σ_d,k−1 per joint, N²·m²
        self.vb_dof = np.zeros(self.n)                                  # VB: λ_{k−1}
        self.vb_scale = np.zeros(self.n)                                # VB: Υ_{k−1}
        if self.window is not None:
            self.window.reset()
        if self.onset is not None:
            self.onset.reset()

    @abstractmethod
    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One sample (``Observer.step``): compiled in ``KVARKKernelFilter`` (class docstring)."""
