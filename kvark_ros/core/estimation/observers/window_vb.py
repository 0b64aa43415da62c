"""Windowed VB on Σ_d for the momentum-state K-VARK filter (``filter.vb_variant: window``).

Why a window. One momentum sample says almost nothing about one step's increment
τ_k − τ_{k−1} (its information is ~h² Σ_d / R ≈ 1e-4 on the Panda), so the lag-one statistic
(``smoothed``) returns the prior and Σ_d never moves. Over L samples the random walk (eq. 32)
gives ``E[(τ_k − τ_{k−L})²] = L Σ_d``, which the data resolve for L of a few tens of samples. The
filter carries S = WINDOW_SNAPSHOTS snapshots z_j of τ_ext (z_j = τ_{k_j}, no dynamics, not
measured) in its state, so the joint posterior of (τ_k, z_j) given y_1:k, cross covariance
included, comes from the ordinary update; the (p, τ) estimate is unchanged by them. A snapshot
taken t_j seconds ago gives the density statistic
``s_j = ((τ̂_k − ẑ_j)² + P_ττ + P_zz − 2 P_τz) / t_j`` (N²·m²/s). The IW posterior (eqs. 36-39,
n = 1 per joint) with prior mean q_0 (training, Σ_d0 = q_0 h) and dof ν_0 (``filter.vb_prior_dof``),
forgetting ρ = 1 − t_s/T per sample (T = ``filter.vb_memory``) applied to the data part only, so that Σ_d
returns to the prior:

    λ_k = ν_0 + 2 + ρ^m (λ_{k−m} − ν_0 − 2) + 1/S          (eq. 37; windows overlap S-fold)
    Υ_k = ν_0 q_0 + ρ^m (Υ_{k−m} − ν_0 q_0) + s_j / S      (eq. 38 with the windowed statistic)
    Σ_d,k = h Υ_k / (λ_k − 2)                               (eq. 39), at most WINDOW_MAX_RATIO Σ_d0

with m = L / S samples between closing windows. ``filter.vb_iterations`` does not apply: the
statistic comes from samples already filtered.

Whose τ̂ (``filter.vb_window_source``). Read from the adaptive filter itself (``estimate``, the default) the statistic
feeds back: a larger Σ_d passes more of the residual model's coloured misfit into τ̂, whose change raises Σ_d further.
On a robot whose misfit at new motions exceeds training's (the population's UR-class arms) one push lifts
q̂ to ~10³ q_0 and the misfit holds it there through free motion. ``prior`` reads a twin filter on the same data held
at Σ_d0 = q_0 h (``twin_*``), its snapshots kept as taken (filtered, not smoothed: under a model at Σ_d0 the smoother
would give most of any change to the random walk's past), with P_zz and Cov(τ, z) the covariance of the two filtered
errors. Nothing feeds back; the twin lags a fast change, so q̂ rises somewhat less when τ_ext moves
(docs/method.md §4.6 has the measured trade).

Here: the component's constants and state; its arithmetic runs in the compiled step
(``compiled.kvark_filter.kvark_step``), its numpy reference is ``ReferenceWindowVB`` in test/core/reference_filter.py.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.estimation.observers.base import Stateful

WINDOW_SNAPSHOTS = 5    # staggered windows, one closing every vb_window / 5 samples
WINDOW_MAX_RATIO = 1e4  # Σ_d never exceeds this multiple of the prior Σ_d0


class WindowVB(Stateful):
    """The snapshots of τ_ext and the IW statistics of the windowed VB, for n joints (module docstring).

    State (arrays (n,) or (n, S)): ``z`` ẑ_j N·m, ``zz`` Var z_j N²·m², ``pz`` and ``tz``
    Cov(p, z_j) N·m²·s and Cov(τ, z_j) N²·m², ``age`` (S,) seconds since snapshot j, ``q`` the
    current density estimate N²·m²/s, ``scale``/``dof`` the forgotten data parts of Υ and λ; with ``twin`` the twin
    filter's ``twin_p`` p̂ N·m·s, ``twin_tau`` τ̂ N·m and P = [[``twin_a``, ``twin_b``], [``twin_b``, ``twin_c``]].
    Per step the filter predicts the snapshots before and updates them after its own (p, τ) update (module docstring).
    """

    STATE = ("z", "zz", "pz", "tz", "age", "count", "q", "scale", "dof", "twin_p", "twin_tau", "twin_a", "twin_b",
             "twin_c")

    def __init__(self, prior_density: np.ndarray, window: int, forgetting: float, prior_dof: float,
                 twin: bool = False) -> None:
        """``prior_density``: q_0 (n,) N²·m²/s; ``window``: L samples; ``forgetting``: ρ; ``prior_dof``: ν_0;
        ``twin``: the snapshots are the twin's at Σ_d0, as taken (``vb_window_source: prior``), else the filter's own,
        smoothed."""
        self.q0 = prior_density
        self.n = len(prior_density)
        self.stride = max(window // WINDOW_SNAPSHOTS, 1)               # m, samples between closing windows
        self.forgetting = forgetting
        self.prior_dof = prior_dof
        self.twin = twin
        self.reset()

    def reset(self) -> None:
        """Forget the snapshots and the statistics: Σ_d back at the prior."""
        self.z: np.ndarray | None = None                               # set from τ̂_0 at the first step
        self.zz = self.pz = self.tz = None
        self.age = np.zeros(WINDOW_SNAPSHOTS)
        self.count = 0
        self.q = self.q0.copy()
        self.scale = np.zeros(self.n)
        self.dof = 0.0
        self.twin_p = self.twin_tau = self.twin_a = self.twin_b = self.twin_c = None   # set at the first step
