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

This module is the filter: ``KVARKMomentumFilter`` holds its settings, components (``window_vb``, ``onset``),
``reset`` and ``configure``; ``KVARKFilter`` keeps its state packed (``KernelState``) and steps it compiled
(``compiled.kvark_filter.kvark_step``), alone (``step``) or inside the estimator's compiled step (``prepare``,
``kernel_arguments``, ``kmp``: ``compiled.step``). Its readable numpy reference, the same equations in the same order,
is ``ReferenceMomentumFilter`` (test/core/reference_filter.py), pinned to the kernel to rounding on the committed
bags; ``state``/``load_state`` work on the packed state unchanged (its attributes are views of it, ``_Packed``).

Why packed: the numpy step cost ~600 k instructions per sample, most of them numpy's per-call overhead on 7-element
arrays, and every array numba receives from Python costs ~1 k instructions to unbox; the state is two buffers (one
float64, one int64) and the constants two arrays, written by name from ``compiled.layouts``.

Covered: every variant (``kf``, ``kmp_kf``, ``kmp_kf_ewma``, ``kmp_kf_nis``, and the VB readings ``window``,
``paper`` and ``smoothed``, with or without the onset detector). A KMP residual (eqs. 21-23, §3) is evaluated
compiled (``compiled.residual.kmp_predict``), any other residual predictor (the learned baselines, the oracle) in
Python before the kernel. The difference form (§4.1) is ``kvark_difference.KVARKDifferenceFilter``.
"""
from __future__ import annotations

from abc import abstractmethod

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.config_schema import vb_variant_problem
from kvark_ros.core.estimation.compiled.kvark_filter import (constants_size, kvark_step, split_constants, split_state,
                                                             state_size)
from kvark_ros.core.estimation.compiled.layouts import INTS, Const, Counter, Option, Param, Vec, pack
from kvark_ros.core.estimation.compiled.residual import kmp_predict
from kvark_ros.core.estimation.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, PerSample, ResidualPredictor
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.observers.momentum_observers import KFMomentumObserver
from kvark_ros.core.estimation.observers.onset import OnsetDetector
from kvark_ros.core.estimation.observers.variants import NIS_SCALE_BOUNDS, VARIANTS
from kvark_ros.core.estimation.observers.window_vb import WINDOW_MAX_RATIO, WINDOW_SNAPSHOTS, WindowVB
from kvark_ros.core.estimation.residual.kmp import KMPResidualModel


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

    ``step`` is abstract: the one implementation is the compiled ``KVARKFilter`` (below,
    ``compiled.kvark_filter.kvark_step``), which ``make_observer`` builds for the momentum form. Its readable numpy
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
        """One sample (``Observer.step``): compiled in ``KVARKFilter`` (class docstring)."""


class KernelState:
    """The compiled filter's state: ``flat`` (float64, ``split_state``'s layout) and ``ints`` (int64, ``Counter``),
    with ``vec``, ``snap``, ``glr`` and ``scal`` the views ``split_state`` gives the kernel and ``prediction`` the
    rows μ_*, σ²_* of ``vec``."""

    def __init__(self, n: int, onsets: int) -> None:
        self.flat = np.zeros(state_size(n, WINDOW_SNAPSHOTS, onsets))
        self.ints = np.zeros(INTS, dtype=np.int64)
        self.vec, self.snap, self.glr, self.scal = split_state.py_func(self.flat, n, WINDOW_SNAPSHOTS, onsets)
        self.prediction = self.vec[Vec.MEAN], self.vec[Vec.VAR]


class _Packed:
    """A state attribute of ``KVARKMomentumFilter`` kept in a ``KernelState`` (the owner's ``packed``).

    Reading gives a view of its part of the buffers, or None until it is first set (the base class's "not yet
    primed"; the flag is the owner's ``_has_<name>``); writing a value copies it in. So the base class's ``reset``,
    ``state`` and ``load_state``, which assign and deep-copy these attributes, work on the packed buffers.
    """

    def __init__(self, part: str, index: int | slice) -> None:
        self.part, self.index = part, index if isinstance(index, slice) else int(index)    # numpy's fastest index

    def __set_name__(self, owner: type, name: str) -> None:
        self.flag = f"_has_{name}"

    def __get__(self, owner: object, kind: type | None = None) -> np.ndarray | None:
        if owner is None:
            return self
        return getattr(owner.packed, self.part)[self.index] if owner.__dict__.get(self.flag, False) else None

    def __set__(self, owner: object, value: np.ndarray | None) -> None:
        owner.__dict__[self.flag] = value is not None
        if value is not None:
            getattr(owner.packed, self.part)[self.index] = value


class _PackedScalar:
    """A scalar state attribute of the base classes (a counter, the window's dof) kept in a ``KernelState``."""

    def __init__(self, part: str, index: int, kind: type) -> None:
        self.part, self.index, self.kind = part, int(index), kind

    def __get__(self, owner: object, kind: type | None = None) -> object:
        return self if owner is None else self.kind(getattr(owner.packed, self.part)[self.index])

    def __set__(self, owner: object, value: float) -> None:
        getattr(owner.packed, self.part)[self.index] = value


class PackedWindowVB(WindowVB):
    """``WindowVB`` whose state lives in the compiled filter's ``KernelState``."""

    z, zz, pz, tz = (_Packed("snap", i) for i in range(4))
    age = _Packed("scal", slice(1, None))
    q, scale = _Packed("vec", Vec.Q), _Packed("vec", Vec.SCALE)
    count, dof = _PackedScalar("ints", Counter.COUNT, int), _PackedScalar("scal", 0, float)
    twin_p, twin_tau, twin_a, twin_b, twin_c = (_Packed("vec", row) for row in (Vec.TWIN_P, Vec.TWIN_TAU, Vec.TWIN_A,
                                                                              Vec.TWIN_B, Vec.TWIN_C))

    def __init__(self, packed: KernelState, *args) -> None:
        self.packed = packed
        super().__init__(*args)


class PackedOnsetDetector(OnsetDetector):
    """``OnsetDetector`` whose state lives in the compiled filter's ``KernelState``."""

    ep, et, d, c = (_Packed("glr", i) for i in range(4))
    slot, alarms = _PackedScalar("ints", Counter.SLOT, int), _PackedScalar("ints", Counter.ALARMS, int)

    def __init__(self, packed: KernelState, *args) -> None:
        self.packed = packed
        super().__init__(*args)


class KVARKFilter(KVARKMomentumFilter):
    """``KVARKMomentumFilter`` with its state packed and its step compiled (module docstring).

    ``KVARKMomentumFilter``'s constructor, ``STATE``, ``reset`` and ``configure``; results equal to the numpy
    reference's (test/core/reference_filter.py) to rounding; the state lives in ``packed`` (its attributes are views
    of it), and ``step`` hands out copies. ``kmp``: the packed KMP of the residual model (``compiled.residual``), or
    None for another residual predictor, which ``prepare`` evaluates in Python.
    """

    compiled = True     # the Estimator runs this filter inside its compiled step (core.estimation.compiled.step)
    p_hat, tau, a, b, c = (_Packed("vec", row) for row in (Vec.P_HAT, Vec.TAU, Vec.A, Vec.B, Vec.C))
    R_adaptive, R_weight = _Packed("vec", Vec.R), _Packed("vec", Vec.R_WEIGHT)
    nis_mean, Sigma_d = _Packed("vec", Vec.NIS), _Packed("vec", Vec.SIGMA_D)
    vb_dof, vb_scale = _Packed("vec", Vec.VB_DOF), _Packed("vec", Vec.VB_SCALE)

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD, contact_density: np.ndarray | None = None) -> None:
        n = residual.n_joints
        onsets = max(PerSample.of(settings, sample_period).onset_window, 2)   # OnsetDetector's M
        self.packed = KernelState(n, onsets)
        self._has_prediction = False
        super().__init__(variant, residual, tuning, noise, settings, name=name, sample_period=sample_period,
                         contact_density=contact_density)
        self.kmp = residual.compiled.packed if isinstance(residual, KMPResidualModel) else None
        self.constants = np.zeros(constants_size(n))
        consts, self._params = split_constants.py_func(self.constants, n)
        consts[Const.R], consts[Const.R_MIN] = self.R, R_FLOOR * self.R
        consts[Const.Q_P], consts[Const.Q_TAU], consts[Const.Q_CONTACT] = self.q_p, self.q_tau, self.contact_density
        consts[Const.RESIDUAL_VAR] = tuning.residual_variance
        self._zeros = np.zeros(n)
        self._apply_runtime(settings)
        window, variant = self.window, self.variant
        self._vb_iw = variant.vb and window is None                     # the per-sample readings paper, smoothed
        self.options = np.array(pack(Option, {
            Option.HETEROSCEDASTIC: variant.heteroscedastic, Option.EWMA: variant.ewma, Option.NIS: variant.nis,
            Option.WINDOW: window is not None, Option.ONSET: self.onset is not None,
            Option.STRIDE: window.stride if window is not None else 1, Option.ONSETS: onsets,
            Option.VB_IW: self._vb_iw, Option.SMOOTHED: self.vb_smoothed, Option.ITERATIONS: self.vb_iterations,
            Option.SNAPSHOTS: WINDOW_SNAPSHOTS, Option.TWIN: window is not None and window.twin}), dtype=np.int64)
        self._compile()

    def declared_params(self) -> dict[Param, float]:
        """The ``Param`` entries that are not this filter's attribute of their lower-case name (as ``ewma_rate``,
        ``nis_rate``, ``vb_forgetting`` are): the window's and the onset detector's (neutral values without them)
        and other modules' constants."""
        window, onset = self.window, self.onset
        return {Param.FORGET: window.forgetting ** window.stride if window is not None else 1.0,
                Param.PRIOR_DOF: window.prior_dof if window is not None else 1.0,
                Param.THRESHOLD: onset.threshold if onset is not None else 0.0,
                Param.MAX_RATIO: WINDOW_MAX_RATIO, Param.NIS_LOW: NIS_SCALE_BOUNDS[0],
                Param.NIS_HIGH: NIS_SCALE_BOUNDS[1]}

    def kernel_arguments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``kvark_step``'s packed state (float, int), constants and options: arrays written in place, never
        replaced, so the estimator's compiled step binds them once."""
        return self.packed.flat, self.packed.ints, self.constants, self.options

    def _make_window(self, *args) -> WindowVB:
        return PackedWindowVB(self.packed, *args)

    def _make_onset(self, *args) -> OnsetDetector:
        return PackedOnsetDetector(self.packed, *args)

    @property
    def prediction(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The residual model's (μ_*, σ²_*) of the last step: views of the packed state (None before a first step)."""
        return self.packed.prediction if self._has_prediction else None

    @prediction.setter
    def prediction(self, value: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._has_prediction = value is not None
        if value is not None:
            mean, var = self.packed.prediction
            mean[:], var[:] = value

    def _apply_runtime(self, settings: FilterSettings) -> None:
        """The base class's, then every ``Param`` entry: ``declared_params``, else this filter's attribute of the
        entry's lower-case name."""
        super()._apply_runtime(settings)
        if hasattr(self, "_params"):                                   # the base class sets the rates before us
            declared = self.declared_params()
            self._params[:] = [declared[member] if member in declared else getattr(self, member.name.lower())
                               for member in Param]

    def _compile(self) -> None:
        """Compile (or load from the cache) the kernels with one step on dummy data, then start afresh."""
        zeros = np.zeros(self.n)
        self.step(self.sample_period, zeros, zeros, zeros, zeros, zeros, zeros)
        self.reset()
        self._has_prediction = False

    def prepare(self, dt: float, qd: np.ndarray, p_prev: np.ndarray, q: np.ndarray | None = None,
                g: np.ndarray | None = None) -> None:
        """What precedes ``kvark_step`` in Python: the first step after a reset primes the state (p̂ = p_{k−1}, every
        snapshot at τ̂_0, the window's twin at the filter's state, the per-sample VB's prior at its steady state with
        mean Σ_d0 = q_τ h, as the numpy reference); a residual model other than the KMP is evaluated."""
        if self._vb_iw and not self._has_Sigma_d:
            rho = self.vb_forgetting
            self.vb_dof = np.full(self.n, 2.0 + (1.0 / (1.0 - rho) if rho < 1.0 else 1.0))
            sigma_d0 = self.q_tau * dt
            self.Sigma_d = sigma_d0
            self.vb_scale = sigma_d0 * (self.vb_dof - 2.0)
        if not self._has_p_hat:
            self.p_hat = p_prev
            window = self.window
            if window is not None:
                if window.z is None:
                    window.z, window.zz = self.tau[:, None], self.c[:, None]     # broadcast over the snapshots
                    window.pz, window.tz = self.b[:, None], self.c[:, None]
                if window.twin and window.twin_p is None:                       # the twin starts as the filter
                    window.twin_p, window.twin_tau = self.p_hat, self.tau
                    window.twin_a, window.twin_b, window.twin_c = self.a, self.b, self.c
                if self.Sigma_d is None:
                    self.Sigma_d = np.zeros(self.n)
        if self.kmp is not None:                        # evaluated compiled, before the filter step
            self._has_prediction = True
        else:
            self.prediction = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self.prepare(dt, qd, p_prev, q, g)
        if self.kmp is not None:                                       # eqs. 21-23
            zeros = self._zeros
            kmp_predict(qd, zeros if q is None else q, zeros if g is None else g, self.kmp, *self.packed.prediction)
        kvark_step(dt, qd, p, u_prev, self.packed.flat, self.packed.ints, self.constants, self.options)
        return self.tau.copy(), np.diag(self.c)
