"""Reading K-VARK's interval factors c from contact-free training recordings (docs/method.md §4.13).

On contact-free data the true τ_ext is zero, so τ̂ itself is the error: c_j is the factor that puts ``COVERAGE`` of
the training τ̂_j inside ±1.96 √(c_j² σ_j² + σ²_s,j) (``core.estimation.calibration``, which holds and applies the
factors). The estimator reports at least the floor: P_b, the fixed-Σ_d ``kf``'s steady-state variance
(``variance_floor``), while the contact test holds a load, and c_b² P_b in free motion (``floor_factor``); it can
only widen that interval.
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from kvark_ros.core.estimation.calibration import COVERAGE, IntervalScale

Z95 = 1.959963984540054       # two-sided 95 % quantile of N(0, 1)
WARMUP = 0.5                  # s at the start of every recording left out (the filter starts from τ̂ = 0, P₀)
SCALE_BOUNDS = (0.05, 20.0)   # a factor beyond these says the noise model is broken, not miscalibrated


FLOOR_SECONDS = 2.0           # s of zero input the ``kf`` runs to reach its steady state (40 time constants at ω_b)


def needed_factor(tau_hat: np.ndarray, sigma: np.ndarray, band_variance: np.ndarray) -> np.ndarray:
    """The least c that puts each |τ̂| inside ±1.96 √(c² σ² + σ²_s), all (T, n) (τ̂ in N·m, σ in N·m, σ²_s in
    N²·m²): c_k = √(max((|τ̂_k|/1.96)² − σ²_s,k, 0)) / σ_k. A sample is inside at c exactly when c ≥ c_k, so the
    ``COVERAGE`` quantile of c_k is the factor that covers that share of the samples (the floor P_b is left out: it
    only widens the interval, and c keeps K-VARK's own P, raised at a contact, in what it reports)."""
    return np.sqrt(np.maximum(np.square(tau_hat / Z95) - band_variance, 0.0)) / sigma


def variance_floor(kf: Any, sample_period: float) -> np.ndarray:
    """P_b (n,) N²·m²: the τ_ext variance the fixed-Σ_d filter ``kf`` (a fresh observer built from the trained model)
    reports in steady state at ``sample_period`` s, reached by stepping it ``FLOOR_SECONDS`` on zero input (its
    covariance does not depend on the data). Why a floor (docs/method.md §4.13): under a load carried through poses
    the training never visited, the model misfit is larger than free motion shows; kvark and ``kf`` then make the
    same error, and only ``kf``'s wider steady state (Σ_d sized for a contact at ω_b) covered it on the simulated
    population's URs. K-VARK never reports τ_ext known better than that filter would."""
    kf.reset()
    zeros = np.zeros(kf.n)
    for _ in range(max(int(round(FLOOR_SECONDS / sample_period)), 2)):
        _, cov = kf.step(sample_period, zeros, zeros, zeros, zeros, zeros, zeros)
    kf.reset()
    floor = np.diag(cov).copy()
    if not np.all(np.isfinite(floor)) or np.any(floor < 0.0):
        raise ValueError(f"the kf's steady-state variance is not a finite non-negative number: {floor}")
    return floor


def floor_factor(kf_scale: np.ndarray) -> np.ndarray:
    """c_b = min(c_kf, 1) (n,): the factor of the floor in free motion, from ``kf``'s own factor c_kf
    (``interval_scale`` of a ``kf`` stepped over the same contact-free recordings as kvark's). In free motion the
    floor is ``kf``'s interval as those recordings show it: where 95 % of ``kf``'s contact-free τ̂ falls inside a
    narrower interval than its P says (c_kf < 1: its white-noise R overstates a noise that is weak within the
    filter's band, as on the real Panda's link-side sensors), it narrows to that. It never widens beyond P_b (c_kf > 1
    is ``kf``'s own misfit, which kvark's c already reads), and under a load it is P_b whole (docs/method.md §4.13)."""
    return np.minimum(np.asarray(kf_scale, dtype=float), 1.0)


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
