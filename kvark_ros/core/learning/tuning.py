"""Static filter covariances from contact-free training data (paper v2 §V-D).

On training data τ_ext = 0, so the residual-corrected virtual measurement ``y_k`` (eq. 28 over
t_s) is measurement noise plus what the residual model misses, which varies slowly with the
motion. Covariance matching, per joint:

* ``measurement_variance`` R: the white part of y, the variance of y about its 50 ms moving
  average (the fixed R of A1);
* ``process_noise_density`` q: scaled so that the A1 filter's mean normalised innovation
  squared on the training data equals its expectation (1 per joint): the random walk absorbs
  just the slow residual-model error;
* ``empirical_variance``: the median squared innovation of that filter (v2 Remark 2: Σ_emp
  starts there and never exceeds it).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d

from kvark_ros.core.estimation.observers.base import FilterTuning

VARIANCE_FLOOR = 1e-8          # N²·m², keeps R positive on noise-free (synthetic) data
WHITE_WINDOW = 0.05            # s, moving average that separates white noise from slow error
TIME_CONSTANTS = np.geomspace(5.0, 0.002, 40)   # s, candidate A1 time constants (q = R t_s / T²)


def virtual_measurements(momentum: np.ndarray, inputs: np.ndarray, stamp: np.ndarray,
                         residual_mean: np.ndarray | None) -> np.ndarray:
    """``y_k = (p_k − p_{k−1})/t_s − u_{k−1} + μ_*(q̇_k)`` for k ≥ 1, shape (T−1, n), N·m.

    ``momentum`` p (T, n) N·m·s and ``inputs`` u (T, n) N·m are the robot model's momentum terms
    along the samples (eqs. 5, 7; ``RobotModel.momentum_terms``), ``stamp`` (T,) s, and
    ``residual_mean`` (T, n) the residual model's mean along the samples (``None``: left out).
    """
    y = np.diff(momentum, axis=0) / np.diff(stamp)[:, None] - inputs[:-1]
    if residual_mean is not None:
        y += residual_mean[1:]
    return y


def _scalar_filters(segments: Sequence[np.ndarray], R: np.ndarray, q_step: np.ndarray) -> tuple[np.ndarray, list]:
    """Run per-joint A1 filters for every candidate (G, n) process variance; mean NIS (G, n), innovations."""
    nis_sum = np.zeros_like(q_step)
    count = 0
    innovations = []
    for y in segments:
        x = np.zeros_like(q_step)
        P = np.broadcast_to(R, q_step.shape).copy()
        r_all = np.empty((len(y),) + q_step.shape)
        for k, y_k in enumerate(y):
            P_pred = P + q_step                       # eq. 42
            S = P_pred + R
            r = y_k - x                               # innovation
            K = P_pred / S                            # eq. 43
            x = x + K * r                             # eq. 44
            P = (1.0 - K) ** 2 * P_pred + K * K * R   # eq. 45, Joseph form (scalar)
            nis_sum += r * r / S
            r_all[k] = r
        count += len(y)
        innovations.append(r_all)
    return nis_sum / count, innovations


def match_covariances(segments: Sequence[np.ndarray], dt: float) -> FilterTuning:
    """Filter tuning from training virtual measurements, one (T_i, n) array per recording."""
    segments = [np.asarray(y, dtype=float) for y in segments]
    if not segments or any(y.ndim != 2 or len(y) < 50 or not np.isfinite(y).all() for y in segments):
        raise ValueError("covariance matching needs recordings of at least 50 finite virtual measurements")
    window = max(3, int(round(WHITE_WINDOW / dt)))
    white = np.concatenate([y - uniform_filter1d(y, window, axis=0, mode="nearest") for y in segments])
    R = np.maximum(np.mean(white ** 2, axis=0) * window / (window - 1), VARIANCE_FLOOR)
    q_step = R[None, :] * (dt / TIME_CONSTANTS[:, None]) ** 2      # (G, n) per-step variance
    nis, innovations = _scalar_filters(segments, R, q_step)
    best = np.argmin(np.abs(np.log(nis)), axis=0)                   # mean NIS closest to 1 per joint
    joints = np.arange(len(R))
    squared = np.concatenate([r[:, best, joints] ** 2 for r in innovations])
    return FilterTuning(process_noise_density=q_step[best, joints] / dt,
                        measurement_variance=R,
                        empirical_variance=np.maximum(np.median(squared, axis=0), VARIANCE_FLOOR))
