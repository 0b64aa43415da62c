"""The noise of the momentum model (docs/method.md §5.3, eq. M1), per joint: what training measures and every
momentum-form filter starts from (``MomentumNoise``: R, q_τ, q_p, with their units below).

Estimated from contact-free samples by ``MomentumNoise.from_training`` and stored in the model's YAML; the K-VARK
momentum filter, its kernel and the second paper's Kalman observers (``momentum_observers``) read it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

DEFAULT_BANDWIDTH = 50.0           # ω_b, rad/s: natural frequency of the steady-state KF (torque_density rule)
DEFAULT_MOMENTUM_VARIANCE = 1e-6   # R, (N·m·s)²: σ_p = 1e-3 N·m·s (≈ 1e-3 rad/s velocity noise on ~1 kg·m²)
DEFAULT_MODEL_DENSITY = 1e-6       # q_p, N²·m²·s: ≈ 0.03 N·m white torque noise at 1 kHz
DEFAULT_STEP = 1e-3                # s, only to turn the default R into a density for the default q_τ
VARIANCE_FLOOR = 1e-12             # (N·m·s)², keeps R > 0 on noise-free (synthetic) data
R_FLOOR_FRACTION = 1e-2            # an estimated R never falls below this fraction of var(δ)/6 or its start value
TRAINING_BLOCKS = 8                # batch means for the standard error of q_p in from_training


@dataclass(frozen=True)
class MomentumNoise:
    """Noise of the momentum model (M1), per joint, shape (n,).

    momentum_variance: R, variance of the momentum measurement ``p = M q̇`` per sample, (N·m·s)².
    torque_density: q_τ, spectral density of the τ_ext random walk, N²·m²/s. Contact-free data
        carry no information on how τ_ext moves; ``from_training`` sets q_τ for a chosen filter
        bandwidth instead (see there).
    model_density: q_p, spectral density of white noise on ṗ (torque noise on τ_m and u), N²·m²·s.
        Optional (0 when absent).
    """

    momentum_variance: np.ndarray
    torque_density: np.ndarray
    model_density: np.ndarray | None = None

    def __post_init__(self) -> None:
        R = np.asarray(self.momentum_variance, dtype=float)
        q_tau = np.asarray(self.torque_density, dtype=float)
        q_p = np.zeros_like(R) if self.model_density is None else np.asarray(self.model_density, dtype=float)
        for name, value, strict in (("momentum_variance", R, True), ("torque_density", q_tau, True),
                                    ("model_density", q_p, False)):
            bad = np.any(value <= 0.0) if strict else np.any(value < 0.0)
            if value.ndim != 1 or len(value) == 0 or not np.all(np.isfinite(value)) or bad:
                kind = "positive" if strict else "non-negative"
                raise ValueError(f"momentum noise '{name}' must be a vector of {kind} finite numbers, got {value}")
        if not (len(R) == len(q_tau) == len(q_p)):
            raise ValueError("momentum noise vectors must all have one entry per joint")
        for name, value in (("momentum_variance", R), ("torque_density", q_tau), ("model_density", q_p)):
            value = value.copy()
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def n(self) -> int:
        return len(self.momentum_variance)

    @classmethod
    def default(cls, n: int, bandwidth: float = DEFAULT_BANDWIDTH) -> "MomentumNoise":
        """Plausible values for a torque-controlled arm at 1 kHz (σ_p = 1e-3 N·m·s, ω_b = 50 rad/s)."""
        R = np.full(n, DEFAULT_MOMENTUM_VARIANCE)
        q_p = np.full(n, DEFAULT_MODEL_DENSITY)
        return cls(R, torque_density_for_bandwidth(R, q_p, DEFAULT_STEP, bandwidth), q_p)

    @classmethod
    def from_training(cls, p: np.ndarray, u: np.ndarray, stamp: np.ndarray,
                      bandwidth: float = DEFAULT_BANDWIDTH) -> "MomentumNoise":
        """Estimate R and q_p from contact-free samples; q_τ from them and the bandwidth ω_b.

        The one-step momentum prediction residual ``ε_k = p_k − p_{k−1} − h_k u_{k−1}`` is
        ``h_k d_k + v_k − v_{k−1} + w_k``: a slow disturbance d (friction, model error; τ_ext = 0
        here), the white momentum measurement noise v (variance R) differenced, and white model
        noise w (variance q_p h_k). Most of ε is usually d, so R is *not* a fixed fraction of
        var(ε): the slow part is removed by ``δ_k = ε_k − ρ_k ε_{k−1}``, ρ_k = h_k/h_{k−1} (exact
        for constant d, any time steps), and R, q_p follow from the lag-0 and lag-1 moments of δ,
        which are linear in them with known coefficients (white v: coefficients 1, −(1+ρ_k), ρ_k)::

            E[δ_k²]        = R (1 + (1+ρ_k)² + ρ_k²) + q_p (h_k + ρ_k² h_{k−1})
            E[δ_k δ_{k−1}] = −R (1 + ρ_k + ρ_k (1+ρ_{k−1})) − q_p ρ_k h_{k−1}

        (averaged over k, solved per joint). The split assumes white v and w and a disturbance
        that is smooth on the sample scale: a colored momentum noise (a strongly filtered
        velocity) or sharp Coulomb transitions bias it. q_p h is often orders of magnitude below
        R and then cannot be resolved: q_p is kept only where it exceeds twice its standard error
        (batch means), else set to 0 (its effect on the filter is then negligible anyway). R is
        floored at 1 % of var(δ)/6 (its value if q_p were 0) and at ``VARIANCE_FLOOR``.

        q_τ: with τ_ext = 0 the data cannot show how fast τ_ext moves, so q_τ sets the filter's
        speed: the steady-state continuous KF of (M1) with ``r_c = R h`` has natural frequency
        ``(q_τ/r_c)^{1/4}`` (damping ≥ 1/√2), and ``√(q_τ/q_p)`` when R → 0. Both limits hold for
        ``q_τ = ω_b² (ω_b² R h + q_p)`` (h the median step), which is used.
        """
        p, u, stamp = (np.asarray(a, dtype=float) for a in (p, u, stamp))
        if p.ndim != 2 or u.shape != p.shape or stamp.shape != (len(p),):
            raise ValueError(f"from_training needs p, u of shape (T, n) and stamp (T,), got "
                             f"{p.shape}, {u.shape}, {stamp.shape}")
        if len(p) < 100:
            raise ValueError(f"from_training needs at least 100 samples, got {len(p)}")
        if not (np.isfinite(p).all() and np.isfinite(u).all() and np.isfinite(stamp).all()):
            raise ValueError("from_training needs finite samples")
        h = np.diff(stamp)
        if np.any(h <= 0.0):
            raise ValueError("from_training needs strictly increasing time stamps")
        if not bandwidth > 0.0:
            raise ValueError(f"bandwidth must be positive, got {bandwidth}")
        eps = p[1:] - p[:-1] - h[:, None] * u[:-1]                     # ε_k, k = 1..T−1
        rho = h[1:] / h[:-1]                                           # ρ_k for the δ_k below
        delta = eps[1:] - rho[:, None] * eps[:-1]                      # δ_k, k = 2..T−1
        lag0 = delta * delta
        lag1 = delta[1:] * delta[:-1]
        m0, m1 = lag0.mean(axis=0), lag1.mean(axis=0)
        rho_now, rho_prev = rho[1:], rho[:-1]                          # ρ_k, ρ_{k−1} of each lag-1 pair
        c0r = np.mean(1.0 + (1.0 + rho) ** 2 + rho ** 2)               # coefficients of R and q_p
        c0q = np.mean(h[1:] + rho ** 2 * h[:-1])
        c1r = -np.mean(1.0 + rho_now + rho_now * (1.0 + rho_prev))
        c1q = -np.mean(rho_now * h[1:-1])
        det = c0r * c1q - c0q * c1r
        R = (m0 * c1q - c0q * m1) / det                                # Cramer's rule, per joint
        q_p = (c0r * m1 - c1r * m0) / det
        # q_p is resolved only where q_p h is not lost in R's share: keep it if it exceeds twice
        # its standard error (batch means over TRAINING_BLOCKS contiguous blocks), else 0.
        blocks = TRAINING_BLOCKS
        size = len(lag1) // blocks
        b0 = lag0[: blocks * size].reshape(blocks, size, -1).mean(axis=1)
        b1 = lag1[: blocks * size].reshape(blocks, size, -1).mean(axis=1)
        q_se = np.std((c0r * b1 - c1r * b0) / det, axis=0, ddof=1) / np.sqrt(blocks)
        q_p = np.where(q_p > 2.0 * q_se, q_p, 0.0)
        R = np.maximum(R, np.maximum(R_FLOOR_FRACTION * m0 / c0r, VARIANCE_FLOOR))
        return cls(R, torque_density_for_bandwidth(R, q_p, float(np.median(h)), bandwidth), q_p)

    def with_bandwidth(self, bandwidth: float, step: float) -> "MomentumNoise":
        """The same R and q_p with q_τ set for natural frequency ``bandwidth`` ω_b, rad/s, at step h, s (the rule of
        ``from_training``): how the K-VARK filter's free-motion prior gets its own bandwidth (docs/method.md §4.12)."""
        if not bandwidth > 0.0:
            raise ValueError(f"bandwidth must be positive, got {bandwidth}")
        return MomentumNoise(self.momentum_variance, torque_density_for_bandwidth(
            self.momentum_variance, self.model_density, step, bandwidth), self.model_density)

    def to_dict(self) -> dict[str, list[float]]:
        """Plain lists, for the model's YAML file."""
        return {"momentum_variance": self.momentum_variance.tolist(),
                "torque_density": self.torque_density.tolist(),
                "model_density": self.model_density.tolist()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "MomentumNoise":
        model = values.get("model_density")
        return cls(np.asarray(values["momentum_variance"], dtype=float),
                   np.asarray(values["torque_density"], dtype=float),
                   None if model is None else np.asarray(model, dtype=float))


def torque_density_for_bandwidth(momentum_variance: np.ndarray, model_density: np.ndarray, step: float,
                                 bandwidth: float) -> np.ndarray:
    """``q_τ = ω_b² (ω_b² R h + q_p)``: the KF's natural frequency is about ω_b (``from_training``)."""
    w2 = bandwidth * bandwidth
    return w2 * (w2 * np.asarray(momentum_variance) * step + np.asarray(model_density))
