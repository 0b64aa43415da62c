"""The momentum-form K-VARK filter with its step compiled: the one implementation of that step.

Why. The numpy step cost ~600 k instructions per sample, most of them numpy's per-call overhead on 7-element
arrays (issue 16). Here the per-sample arithmetic (docs/method.md §4.2-4.7) runs in one ``numba.njit`` function,
``step_kernel.kvark_step``, that loops over the joints and updates the filter's state in place. The readable numpy
version is a test oracle (``ReferenceMomentumFilter``, test/core/reference_filter.py): the same equations in the same
order of operations, so the two agree to floating-point rounding (the tests pin that on the committed bags). The
settings, ``STATE`` (names, shapes and values), ``reset`` and ``configure`` are ``KVARKMomentumFilter``'s, so
``state``/``load_state`` work unchanged.

Covered: the momentum form in every variant (``kf``, ``kmp_kf``, ``kmp_kf_ewma``, ``kmp_kf_nis``, and the VB
variants in the readings ``window``, ``paper`` and ``smoothed``, with or without the onset detector). A q̇-only
KMP residual model (eqs. 21-23 and the far-field floor, §3.3, §3.6) is evaluated inside the kernel, a KMP with
second inputs (§3.7) by ``model_kernels.kmp_predict_pose`` before it; any other residual predictor (the learned
baselines, the oracle) is called in Python and its mean and variance passed in. The difference form
(``KVARKFilter``, §4.1) has no kernel: ``make_observer`` builds the numpy filter for it.

The kernel (``kvark_step``) lives in ``kvark_ros.core.estimation.step_kernel`` with the compiled ``Estimator.step`` that
calls it (numba's cache sees one file). It takes the state as two buffers (``KernelState``: one float64, one
int64) and the constants as one float64 and one int64 array, because every array numba receives from Python costs
about 1 k instructions to unbox (issue 16 measured 30 k of the filter's 100 k on its 30 arguments). The
state attributes (``p_hat``, ``tau``, …, the window's ``z``, …, the detector's ``ep``, …) are views of those
buffers (``_Packed``): ``KVARKMomentumFilter``'s ``reset``, ``state`` and ``load_state`` run unchanged on them. The
constants are written by name from ``step_kernel``'s layouts: the ``Const`` rows, every ``Param`` entry from this
filter's attribute of its lower-case name or from ``declared_params``, the ``Option`` entries; the residual model's
factors come from ``KMPResidualModel.kernel_arrays``.

Compilation: the observer steps once on dummy data at construction (from numba's cache after the first time, see
``step_kernel``), so the first sample does not wait for the compiler.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.estimation.model_kernels import kmp_predict_pose
from kvark_ros.core.estimation.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, PerSample, ResidualPredictor
from kvark_ros.core.estimation.observers.kvark_filter import NIS_SCALE_BOUNDS
from kvark_ros.core.estimation.observers.kvark_momentum import R_FLOOR, KVARKMomentumFilter
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.observers.onset import OnsetDetector
from kvark_ros.core.estimation.observers.window_vb import WINDOW_MAX_RATIO, WINDOW_SNAPSHOTS, WindowVB
from kvark_ros.core.estimation.residual.common import VARIANCE_FLOOR
from kvark_ros.core.estimation.residual.kmp import KMPResidualModel
from kvark_ros.core.estimation.kernel_layouts import (CONST_ROWS, INTS, PARAMS, Const, Counter, Option, Param, Pose,
                                                      Vec, pack)
from kvark_ros.core.estimation.step_kernel import kvark_step, split_constants, split_state, state_size


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


class KVARKKernelFilter(KVARKMomentumFilter):
    """``KVARKMomentumFilter`` whose ``step`` is the compiled ``kvark_step`` (module docstring).

    ``KVARKMomentumFilter``'s constructor, ``STATE``, ``reset`` and ``configure``; results equal to the numpy
    reference's (test/core/reference_filter.py) to rounding; the state lives in ``packed`` (its attributes are views
    of it), and ``step`` hands out copies.
    """

    compiled = True     # the Estimator runs its whole step compiled around this filter (core.estimation.compiled_step)
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
        kmp = self._kmp_inside = isinstance(residual, KMPResidualModel) and not residual.needs
        support = residual.n_support if kmp else 1
        self.constants = np.zeros(CONST_ROWS * n + PARAMS + n * support * (support + 2))
        consts, self._params, support_points, weights_t = split_constants.py_func(self.constants, n, support)
        consts[Const.R], consts[Const.R_MIN] = self.R, R_FLOOR * self.R
        consts[Const.Q_P], consts[Const.Q_TAU], consts[Const.Q_CONTACT] = self.q_p, self.q_tau, self.contact_density
        consts[Const.RESIDUAL_VAR] = tuning.residual_variance
        if kmp:
            arrays = residual.kernel_arrays()
            consts[Const.NEG_HALF_INV_LS2] = arrays.neg_half_inv_ls2
            consts[Const.SIGMA_F2], consts[Const.VAR_SCALE] = arrays.sigma_f2, arrays.var_scale
            support_points[:] = arrays.support
            weights_t[:] = np.swapaxes(arrays.weights, 1, 2)
        # kmp_predict_pose's arguments after q̇, q, g, bound once (the outputs are views of the packed state)
        self._pose = ((*pose_arguments(residual), VARIANCE_FLOOR, *self.packed.prediction)
                      if isinstance(residual, KMPResidualModel) and residual.needs else None)
        self._no_g = np.zeros(n)
        self._apply_runtime(settings)
        window, variant = self.window, self.variant
        self._vb_iw = variant.vb and window is None                     # the per-sample readings paper, smoothed
        self.options = np.array(pack(Option, {
            Option.HETEROSCEDASTIC: variant.heteroscedastic, Option.EWMA: variant.ewma, Option.NIS: variant.nis,
            Option.WINDOW: window is not None, Option.ONSET: self.onset is not None, Option.KMP: kmp,
            Option.STRIDE: window.stride if window is not None else 1, Option.SUPPORT: support,
            Option.ONSETS: onsets, Option.VB_IW: self._vb_iw, Option.SMOOTHED: self.vb_smoothed,
            Option.ITERATIONS: self.vb_iterations, Option.SNAPSHOTS: WINDOW_SNAPSHOTS,
            Option.TWIN: window is not None and window.twin}), dtype=np.int64)
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
                Param.NIS_HIGH: NIS_SCALE_BOUNDS[1], Param.VARIANCE_FLOOR: VARIANCE_FLOOR}

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
        """Compile (or load from the cache) the kernel with one step on dummy data, then start afresh."""
        zeros = np.zeros(self.n)
        self.step(self.sample_period, zeros, zeros, zeros, zeros, zeros, zeros)
        self.reset()
        self._has_prediction = False

    def prepare(self, dt: float, qd: np.ndarray, p_prev: np.ndarray, q: np.ndarray | None = None,
                g: np.ndarray | None = None) -> None:
        """What precedes ``kvark_step`` in Python: the first step after a reset primes the state (p̂ = p_{k−1}, every
        snapshot at τ̂_0, the window's twin at the filter's state, the per-sample VB's prior at its steady state with
        mean Σ_d0 = q_τ h, as the numpy reference); a residual model other than a q̇-only KMP is evaluated (one with
        second inputs compiled)."""
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
            self._has_prediction = self._has_prediction or self._kmp_inside
        if self._pose is not None and q is not None:     # compiled too (zeros for an unused g)
            kmp_predict_pose(qd, q, self._no_g if g is None else g, *self._pose)
            self._has_prediction = True
        elif not self._kmp_inside:
            self.prediction = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self.prepare(dt, qd, p_prev, q, g)
        kvark_step(dt, qd, p, u_prev, self.packed.flat, self.packed.ints, self.constants, self.options)
        return self.tau.copy(), np.diag(self.c)


def pose_arguments(residual: KMPResidualModel) -> tuple[np.ndarray, ...]:
    """``kmp_predict_pose``'s arrays for a KMP with second inputs: the rows ``Pose`` (len(Pose), n), s, s₂ (n, N),
    Wᵀ (n, N, N+1), L_K⁻ᵀ (n, N, N) and its work space (``KMPResidualModel.kernel_arrays``)."""
    arrays = residual.kernel_arrays()
    n, n_support = arrays.support.shape
    pose = np.array(pack(Pose, {Pose.LS: arrays.neg_half_inv_ls2, Pose.LS_Z: arrays.neg_half_inv_ls2_z,
                                Pose.SIGMA_F2: arrays.sigma_f2, Pose.VAR_SCALE: arrays.var_scale,
                                Pose.TAKES_Q: arrays.takes_q, Pose.TAKES_G: arrays.takes_g,
                                Pose.TWO_INPUT: arrays.two_input}), dtype=float)
    floor = arrays.floor_weights if arrays.floor_weights is not None else np.zeros((n, n_support, n_support))
    return (pose, np.ascontiguousarray(arrays.support), np.ascontiguousarray(arrays.support2),
            np.ascontiguousarray(np.swapaxes(arrays.weights, 1, 2)),
            np.ascontiguousarray(np.swapaxes(floor, 1, 2)), np.empty(n_support + 1), np.empty(n_support),
            np.empty(n_support))
