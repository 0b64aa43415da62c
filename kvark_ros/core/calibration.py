"""Calibration of K-VARK's reported τ̂ interval on contact-free training data (docs/method.md §4.13).

The filter's covariance P follows from its noise model, and that model is only as right as its
assumptions: on the realistic simulated Panda the drifting friction and offset make the contact-free
τ̂ 1.4-2.4 times its σ, on the real Panda the torque noise that is white at the sample scale but not
within the filter's band makes it 0.2-0.3 times its σ. On contact-free data the true τ_ext is zero, so
τ̂ itself is the error, and the factor c_j that puts ``COVERAGE`` of the training τ̂_j inside ±1.96 c_j σ_j
can be read off the training recordings. The estimator reports c² P (each joint's row and column scaled
by c) plus the static friction band's σ²_s (core.stiction), and so the wrench covariance; the filter, its gain
and the contact and collision tests keep P. c is read for that whole reported interval: near rest the band
already covers part of the misfit, so the factor needed there is smaller (``needed_factor``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

COVERAGE = 0.95               # share of contact-free τ̂ inside ±1.96 c σ
Z95 = 1.959963984540054       # two-sided 95 % quantile of N(0, 1)
WARMUP = 0.5                  # s at the start of every recording left out (the filter starts from τ̂ = 0, P₀)
SCALE_BOUNDS = (0.05, 20.0)   # a factor beyond these says the noise model is broken, not miscalibrated
CALIBRATED_OBSERVER = "kvark"  # the estimator the factors were read for (the observers differ in their P)


@dataclass(frozen=True)
class IntervalScale:
    """c (n,) per joint: reported Cov τ̂ = diag(c) P diag(c) for ``CALIBRATED_OBSERVER``."""

    scale: np.ndarray

    def __post_init__(self) -> None:
        scale = np.array(self.scale, dtype=float)
        if scale.ndim != 1 or not np.all(np.isfinite(scale)) or np.any(scale <= 0.0):
            raise ValueError(f"interval scale must be positive finite numbers, one per joint, got {self.scale}")
        scale.setflags(write=False)
        object.__setattr__(self, "scale", scale)

    def apply(self, covariance: np.ndarray) -> np.ndarray:
        """diag(c) P diag(c) of a (n, n) covariance, N²·m²."""
        return covariance * np.outer(self.scale, self.scale)

    def to_dict(self) -> dict[str, Any]:
        return {"observer": CALIBRATED_OBSERVER, "coverage": COVERAGE, "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "IntervalScale":
        if values.get("observer") != CALIBRATED_OBSERVER:
            raise ValueError(f"interval scale for observer {values.get('observer')!r}, expected {CALIBRATED_OBSERVER}")
        return cls(np.asarray(values["scale"], dtype=float))


def needed_factor(tau_hat: np.ndarray, sigma: np.ndarray, band_variance: np.ndarray) -> np.ndarray:
    """The least c that puts each |τ̂| inside ±1.96 √(c² σ² + σ²_s), all (T, n) (τ̂ in N·m, σ in N·m, σ²_s in
    N²·m²): c_k = √(max((|τ̂_k|/1.96)² − σ²_s,k, 0)) / σ_k. A sample is inside at c exactly when c ≥ c_k, so the
    ``COVERAGE`` quantile of c_k is the factor that covers that share of the samples."""
    return np.sqrt(np.maximum(np.square(tau_hat / Z95) - band_variance, 0.0)) / sigma


def interval_scale(observer: Any, stamps: Sequence[np.ndarray], qd: Sequence[np.ndarray], q: Sequence[np.ndarray],
                   p: Sequence[np.ndarray], u: Sequence[np.ndarray], g: Sequence[np.ndarray],
                   band: Callable[[np.ndarray], np.ndarray] | None = None) -> IntervalScale:
    """c from contact-free recordings: per recording stamps (T,) s, q̇, q (T, n), the model's momentum p (T, n)
    N·m·s, its input u (T, n) N·m and gravity torque g (T, n) N·m (``training.SegmentDynamics``); ``band`` maps
    q̇ (T, n) rad/s to the static friction band's σ²_s (T, n) N²·m² the estimator adds (None: no band).

    ``observer`` (a fresh K-VARK filter built from the trained model) is reset and stepped over every recording as
    the Estimator steps it; c_j is the 95 % quantile of ``needed_factor`` over the samples after ``WARMUP`` (without
    a band q_95(|τ̂_j| / σ_j) / 1.96), clipped to ``SCALE_BOUNDS``.
    """
    needed = []
    for stamp, qd_k, q_k, p_k, u_k, g_k in zip(stamps, qd, q, p, u, g):
        observer.reset()
        kept = np.flatnonzero(stamp - stamp[0] >= WARMUP)
        kept = kept[kept >= 1]
        tau_hat = np.empty((len(stamp), p_k.shape[1]))
        sigma = np.ones_like(tau_hat)
        for k in range(1, len(stamp)):
            tau_hat[k], cov = observer.step(stamp[k] - stamp[k - 1], qd_k[k], p_k[k], p_k[k - 1], u_k[k - 1], q_k[k],
                                            g_k[k])
            sigma[k] = np.sqrt(np.diag(cov))
        widening = np.zeros((len(kept), p_k.shape[1])) if band is None else band(qd_k[kept])
        needed.append(needed_factor(tau_hat[kept], sigma[kept], widening))
    observer.reset()
    samples = np.concatenate(needed)
    if len(samples) < 100 or not np.all(np.isfinite(samples)):
        raise ValueError(f"interval calibration needs at least 100 finite samples after {WARMUP} s, got "
                         f"{len(samples)}")
    return IntervalScale(np.clip(np.quantile(samples, COVERAGE, axis=0), *SCALE_BOUNDS))
