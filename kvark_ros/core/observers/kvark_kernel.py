"""The momentum-form K-VARK filter with its step compiled (``filter.kernel: numba``, the default).

Why. ``KVARKMomentumFilter.step`` cost ~600 k instructions per sample, most of them numpy's per-call overhead on
7-element arrays (issue 16). Here its per-sample arithmetic (docs/method.md §4.2-4.7) runs in one ``numba.njit``
function, ``step_kernel.kvark_step``, that loops over the joints and updates the filter's state in place.
``KVARKMomentumFilter`` stays the readable reference: the same equations in the same order of operations, so the
two agree to floating-point rounding (the tests pin that on the committed bags), and the kernel observer keeps the
reference's ``STATE`` (same names, shapes and values), so ``state``/``load_state`` work unchanged.

Covered: the momentum form in every variant (``kf``, ``kmp_kf``, ``kmp_kf_ewma``, ``kmp_kf_nis``, and the VB
variants in the readings ``window``, ``paper`` and ``smoothed``, with or without the onset detector). A q̇-only
KMP residual model (eqs. 21-23 and the far-field floor, §3.3, §3.6) is evaluated inside the kernel, a KMP with
second inputs (§3.7) by ``model_kernels.kmp_predict_pose`` before it; any other residual predictor (the learned
baselines, the oracle) is called in Python and its mean and variance passed in. The difference form
(``KVARKFilter``, §4.1) has no kernel: ``make_observer`` builds the numpy filter for it whichever
``filter.kernel`` is set.

The kernel (``kvark_step``) lives in ``kvark_ros.core.step_kernel`` with the compiled ``Estimator.step`` that
calls it (numba's cache sees one file). It takes the state as two buffers (``KernelState``: one float64, one
int64) and the constants as one float64 and one int64 array, because every array numba receives from Python costs
about 1 k instructions to unbox (issue 16 measured 30 k of the filter's 100 k on its 30 arguments). The
reference's state attributes (``p_hat``, ``tau``, …, the window's ``z``, …, the detector's ``ep``, …) are views of
those buffers (``_Packed``): the reference's ``reset``, ``state`` and ``load_state`` run unchanged on them.

Compilation: the observer steps once on dummy data at construction (from numba's cache after the first time, see
``step_kernel``), so the first sample does not wait for the compiler.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.model_kernels import kmp_predict_pose
from kvark_ros.core.observers.base import DEFAULT_SAMPLE_PERIOD, FilterTuning, PerSample, ResidualPredictor
from kvark_ros.core.observers.kvark_filter import NIS_SCALE_BOUNDS
from kvark_ros.core.observers.kvark_momentum import R_FLOOR, KVARKMomentumFilter
from kvark_ros.core.observers.momentum_observers import MomentumNoise
from kvark_ros.core.observers.onset import OnsetDetector
from kvark_ros.core.observers.window_vb import WINDOW_MAX_RATIO, WINDOW_SNAPSHOTS, WindowVB
from kvark_ros.core.residual.common import VARIANCE_FLOOR
from kvark_ros.core.residual.kmp import KMPResidualModel
from kvark_ros.core.step_kernel import (C_NEG_HALF_INV_LS2, C_Q_P, C_Q_TAU, C_R, C_R_MIN, C_RESIDUAL_VAR,
                                        C_SIGMA_F2, C_VAR_SCALE, CONST_ROWS, I_ALARMS, I_COUNT, I_SLOT, INTS,
                                        P_EWMA_RATE, P_FORGET, P_MAX_RATIO, P_NIS_HIGH, P_NIS_LOW, P_NIS_RATE,
                                        P_PRIOR_DOF, P_RHO, P_THRESHOLD, P_VARIANCE_FLOOR, PARAMS, V_A, V_B, V_C,
                                        V_MEAN, V_NIS, V_P_HAT, V_Q, V_R, V_SCALE, V_SIGMA_D, V_TAU, V_VAR,
                                        V_VB_DOF, V_VB_SCALE, kvark_step, split_constants, split_state, state_size)


class KernelState:
    """The compiled filter's state: ``flat`` (float64, ``split_state``'s layout) and ``ints`` (int64: count, slot,
    alarms), with ``vec``, ``snap``, ``glr`` and ``scal`` the views ``split_state`` gives the kernel."""

    def __init__(self, n: int, onsets: int) -> None:
        self.flat = np.zeros(state_size(n, WINDOW_SNAPSHOTS, onsets))
        self.ints = np.zeros(INTS, dtype=np.int64)
        self.vec, self.snap, self.glr, self.scal = split_state.py_func(self.flat, n, WINDOW_SNAPSHOTS, onsets)


class _Packed:
    """A state attribute of the reference kept in a ``KernelState`` (the owner's ``packed``).

    Reading gives a view of its part of the buffers, or None until it is first set (the reference's "not yet
    primed"; the flag is the owner's ``_has_<name>``); writing a value copies it in. So the reference's ``reset``,
    ``state`` and ``load_state``, which assign and deep-copy these attributes, work on the packed buffers.
    """

    def __init__(self, part: str, index: int | slice) -> None:
        self.part, self.index = part, index

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
    """A scalar state attribute of the reference (a counter, the window's dof) kept in a ``KernelState``."""

    def __init__(self, part: str, index: int, kind: type) -> None:
        self.part, self.index, self.kind = part, index, kind

    def __get__(self, owner: object, kind: type | None = None) -> object:
        return self if owner is None else self.kind(getattr(owner.packed, self.part)[self.index])

    def __set__(self, owner: object, value: float) -> None:
        getattr(owner.packed, self.part)[self.index] = value


class PackedWindowVB(WindowVB):
    """``WindowVB`` whose state lives in the compiled filter's ``KernelState``."""

    z, zz, pz, tz = (_Packed("snap", i) for i in range(4))
    age = _Packed("scal", slice(1, None))
    q, scale = _Packed("vec", V_Q), _Packed("vec", V_SCALE)
    count, dof = _PackedScalar("ints", I_COUNT, int), _PackedScalar("scal", 0, float)

    def __init__(self, packed: KernelState, *args) -> None:
        self.packed = packed
        super().__init__(*args)


class PackedOnsetDetector(OnsetDetector):
    """``OnsetDetector`` whose state lives in the compiled filter's ``KernelState``."""

    ep, et, d, c = (_Packed("glr", i) for i in range(4))
    slot, alarms = _PackedScalar("ints", I_SLOT, int), _PackedScalar("ints", I_ALARMS, int)

    def __init__(self, packed: KernelState, *args) -> None:
        self.packed = packed
        super().__init__(*args)


class KVARKKernelFilter(KVARKMomentumFilter):
    """``KVARKMomentumFilter`` whose ``step`` is the compiled ``kvark_step`` (module docstring).

    Same constructor, ``STATE``, ``reset``, ``configure`` and results (to rounding) as the reference; the state
    lives in ``packed`` (its attributes are views of it), and ``step`` hands out copies.
    """

    compiled = True     # the Estimator runs its whole step compiled around this filter (core.compiled_step)
    p_hat, tau, a, b, c = (_Packed("vec", row) for row in (V_P_HAT, V_TAU, V_A, V_B, V_C))
    R_adaptive, nis_mean, Sigma_d = _Packed("vec", V_R), _Packed("vec", V_NIS), _Packed("vec", V_SIGMA_D)
    vb_dof, vb_scale = _Packed("vec", V_VB_DOF), _Packed("vec", V_VB_SCALE)

    def __init__(self, variant: str, residual: ResidualPredictor, tuning: FilterTuning, noise: MomentumNoise,
                 settings: FilterSettings, name: str | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD) -> None:
        n = residual.n_joints
        onsets = max(PerSample.of(settings, sample_period).onset_window, 2)   # OnsetDetector's M
        self.packed = KernelState(n, onsets)
        self._has_prediction = False
        super().__init__(variant, residual, tuning, noise, settings, name=name, sample_period=sample_period)
        kmp = self._kmp_inside = isinstance(residual, KMPResidualModel) and not residual.needs
        support = residual._s.shape[1] if kmp else 1
        self.constants = np.zeros(CONST_ROWS * n + PARAMS + n * support * (support + 2))
        consts, self._params, support_points, weights_t = split_constants.py_func(self.constants, n, support)
        consts[C_R], consts[C_R_MIN] = self.R, R_FLOOR * self.R
        consts[C_Q_P], consts[C_Q_TAU] = self.q_p, self.q_tau
        consts[C_RESIDUAL_VAR] = tuning.residual_variance
        if kmp:
            consts[C_NEG_HALF_INV_LS2] = residual._neg_half_inv_ls2[:, 0]
            consts[C_SIGMA_F2], consts[C_VAR_SCALE] = residual._sigma_f2, residual._var_scale
            support_points[:] = residual._s
            weights_t[:] = np.swapaxes(residual._weights, 1, 2)
        self._pose = self._pose_kmp(residual) if isinstance(residual, KMPResidualModel) and residual.needs else None
        self._no_g = np.zeros(n)
        window = self.window
        stride = window.stride if window is not None else 1
        self._params[P_FORGET] = window.forgetting ** stride if window is not None else 1.0
        self._params[P_PRIOR_DOF] = window.prior_dof if window is not None else 1.0
        self._params[P_THRESHOLD] = self.onset.threshold if self.onset is not None else 0.0
        self._params[P_RHO] = self.vb_forgetting
        self._params[P_MAX_RATIO], self._params[P_VARIANCE_FLOOR] = WINDOW_MAX_RATIO, VARIANCE_FLOOR
        self._params[P_NIS_LOW], self._params[P_NIS_HIGH] = NIS_SCALE_BOUNDS
        self._apply_runtime(settings)
        self._vb_iw = self.variant.vb and window is None                # the per-sample readings paper, smoothed
        self.options = np.array([self.variant.heteroscedastic, self.variant.ewma, self.variant.nis,
                                 window is not None, self.onset is not None, kmp, stride, support, onsets,
                                 self._vb_iw, self.vb_smoothed, self.vb_iterations, WINDOW_SNAPSHOTS],
                                dtype=np.int64)                 # in step_kernel's O_* order
        self._compile()

    @staticmethod
    def _pose_kmp(residual: KMPResidualModel) -> tuple[np.ndarray, ...]:
        """``kmp_predict_pose``'s arrays for a KMP with second inputs: rows ``K_*``, s, s₂, Wᵀ, L_K⁻ᵀ, work space."""
        n, n_support = residual._s.shape
        pose = np.array([residual._neg_half_inv_ls2[:, 0], residual._neg_half_inv_ls2_z[:, 0], residual._sigma_f2,
                         residual._var_scale, residual._takes_q, residual._takes_g, residual._two_input], dtype=float)
        floor = (residual._floor_weights if residual._floor_weights is not None
                 else np.zeros((n, n_support, n_support)))
        return (pose, np.ascontiguousarray(residual._s), np.ascontiguousarray(residual._s2),
                np.ascontiguousarray(np.swapaxes(residual._weights, 1, 2)),
                np.ascontiguousarray(np.swapaxes(floor, 1, 2)), np.empty(n_support + 1), np.empty(n_support),
                np.empty(n_support))

    def _make_window(self, *args) -> WindowVB:
        return PackedWindowVB(self.packed, *args)

    def _make_onset(self, *args) -> OnsetDetector:
        return PackedOnsetDetector(self.packed, *args)

    @property
    def prediction(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The residual model's (μ_*, σ²_*) of the last step: views of the packed state (None before a first step)."""
        vec = self.packed.vec
        return (vec[V_MEAN], vec[V_VAR]) if self._has_prediction else None

    @prediction.setter
    def prediction(self, value: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._has_prediction = value is not None
        if value is not None:
            self.packed.vec[V_MEAN], self.packed.vec[V_VAR] = value

    def _apply_runtime(self, settings: FilterSettings) -> None:
        super()._apply_runtime(settings)
        if hasattr(self, "_params"):                                   # the reference sets the rates before us
            self._params[P_EWMA_RATE], self._params[P_NIS_RATE] = self.ewma_rate, self.nis_rate

    def _compile(self) -> None:
        """Compile (or load from the cache) the kernel with one step on dummy data, then start afresh."""
        zeros = np.zeros(self.n)
        self.step(self.sample_period, zeros, zeros, zeros, zeros, zeros, zeros)
        self.reset()
        self._has_prediction = False

    def prepare(self, dt: float, qd: np.ndarray, p_prev: np.ndarray, q: np.ndarray | None = None,
                g: np.ndarray | None = None) -> None:
        """What precedes ``kvark_step`` in Python: the first step after a reset primes the state (p̂ = p_{k−1}, every
        snapshot at τ̂_0 as ``WindowVB.predict``, the per-sample VB's prior at its steady state with mean Σ_d0 = q_τ h
        as ``_vb_update``); a residual model other than a q̇-only KMP is evaluated (one with second inputs compiled)."""
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
                if self.Sigma_d is None:
                    self.Sigma_d = np.zeros(self.n)
            self._has_prediction = self._has_prediction or self._kmp_inside
        if self._pose is not None and q is not None:     # compiled too (zeros for an unused g)
            vec = self.packed.vec
            kmp_predict_pose(qd, q, self._no_g if g is None else g, *self._pose, VARIANCE_FLOOR, vec[V_MEAN],
                             vec[V_VAR])
            self._has_prediction = True
        elif not self._kmp_inside:
            self.prediction = self.residual.predict(qd, q, g) if self.needs else self.residual.predict(qd)

    def step(self, dt: float, qd: np.ndarray, p: np.ndarray, p_prev: np.ndarray,
             u_prev: np.ndarray, q: np.ndarray | None = None,
             g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self.prepare(dt, qd, p_prev, q, g)
        kvark_step(dt, qd, p, u_prev, self.packed.flat, self.packed.ints, self.constants, self.options)
        return self.tau.copy(), np.diag(self.c)
