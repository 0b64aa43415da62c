"""Contact-onset detector of the momentum-state K-VARK filter: Willsky-Jones GLR for a jump in τ_ext.

Why. Eq. 32 models τ_ext as a random walk with small steps, and the VB (eqs. 33-40, here the
windowed VB of ``window_vb``) learns a larger Σ_d only from the *estimated* change of τ_ext, which
after an impact lags the true one by the filter's own time constant (~40 ms on the Panda). An
impact is better modelled as a jump: τ_ext,k = τ_ext,k−1 + Δ·1[k = θ] + w_d, with unknown onset θ
and size Δ. The innovation ν (the sequence whose whiteness eqs. 16 and 31 rely on) then carries
the jump's signature: with the filter's own gains, a unit jump between update θ−1 and prediction
θ leaves the state error e⁻_θ = (0, 1) (p_θ does not yet feel it), and for k ≥ θ, with (K1)-(K4)
of ``momentum_observers``,

    ρ_k = H e⁻_k = e⁻_p,k,   e⁺_k = e⁻_k − K_k ρ_k,   e⁻_k+1 = F e⁺_k,   ν_k = ρ_k Δ + ν⁰_k

with ν⁰ white, variance S_k (K3). The generalized likelihood ratio (Willsky & Jones, IEEE TAC
1976) maximises over Δ in closed form and over θ in a window of the last M samples
(``filter.onset_window_time`` / t_s):

    d_θ = Σ_k ρ_k ν_k / S_k,   C_θ = Σ_k ρ_k² / S_k,   Δ̂_θ = d_θ / C_θ,   ℓ_θ = d_θ² / C_θ

ℓ_θ = 2 ln Λ is χ²(1) under "no jump" for a fixed θ. When max_θ ℓ_θ exceeds
``filter.onset_threshold`` on a joint, the jump is accepted there and the filter is corrected as
if it had been modelled from θ on: x̂ += e⁺_k Δ̂ and P += e⁺_k e⁺_kᵀ Var Δ̂, Var Δ̂ = 1/C_θ, then
that joint's hypotheses restart. An onset seen on one sample only (``compiled.kvark_filter.ONSET_EVIDENCE``) also
adds (e⁺_τ Δ̂)² to Var τ̂ alone: its Δ̂ is that sample's innovation, which an impulse of the same area (an
impact's transient, one outlying torque reading) gives as well as a step. Both explain that sample's
momentum, so p̂'s correction stands; they differ in τ alone (after an impulse the level is back at zero),
and the next samples, weighed by that P, settle which it was. The window VB then sees the jump in
τ̂ − ẑ_j and raises Σ_d for the transient that follows the impact (eq. 38's statistic), and forgets it
as before. Per joint, hypotheses live in a ring of M slots, one new onset per sample, arrays (n, M):
a few vector operations per step.

With ``filter.onset_contact_bandwidth`` ω_c > 0 an onset accepted on more than one sample of evidence also raises
every joint's window density to at least q_c, the random walk of natural frequency ω_c (docs/method.md §4.7): a
contact loads every joint through Jᵀ F, while the detector sees it on the joint whose signature is clearest; the
others' rise is a ramp the VB reads late. A one-sample onset may be no contact at all (an impulse, an outlying
reading), so it raises nothing beyond its own Var τ̂.

The detector belongs to the Σ_d adaptation (a jump is the limit of a large Σ_d for one sample),
so only the variants with VB use it; the fixed-Q ablations (``kf``, ``kmp_kf*``) stay the paper's
baselines.

Here: the detector's constants and state; its arithmetic runs in the compiled step
(``compiled.kvark_filter.kvark_step``), its numpy reference is ``ReferenceOnsetDetector`` in test/core/reference_filter.py.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.estimation.observers.base import Stateful


class OnsetDetector(Stateful):
    """The GLR hypotheses of n joints, M onsets each (module docstring); ``alarms``: joint alarms since reset.

    State (n, M): ``ep``, ``et`` the state error e⁻ (after a step: of the next prediction) of a
    unit jump at each hypothesised onset, ``d`` and ``c`` the sums d_θ and C_θ; ``slot`` the ring
    position of the newest onset.
    """

    STATE = ("ep", "et", "d", "c", "slot", "alarms")

    def __init__(self, n: int, threshold: float, window: int) -> None:
        """``threshold``: on 2 ln Λ, > 0; ``window``: M, onsets kept per joint."""
        self.n = n
        self.threshold = threshold
        self.window = window
        self.reset()

    def reset(self) -> None:
        """Forget all hypotheses and the alarm count."""
        m = max(self.window, 2)
        self.ep, self.et = np.zeros((self.n, m)), np.zeros((self.n, m))
        self.d, self.c = np.zeros((self.n, m)), np.zeros((self.n, m))
        self.slot = 0
        self.alarms = 0
