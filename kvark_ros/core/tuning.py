"""Static filter covariances from contact-free training data (paper v2 §V-D).

On training data τ_ext = 0, so the residual-corrected virtual measurement ``y_k`` (eq. 28 over
t_s) is pure measurement noise plus what the residual model misses:

* ``measurement_variance``: innovation covariance matching, ``R = E[y²]`` per joint (the fixed
  R of the non-heteroscedastic filter, A1);
* ``empirical_variance``: the median squared innovation (v2 Remark 2: Σ_emp starts there and
  never exceeds it);
* ``process_noise_density``: the random-walk density that gives the A1 filter a chosen time
  constant T: a steady-state gain K ≈ t_s/T needs ``q t_s ≈ K² R``, i.e. ``q = R t_s / T²``.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.observers.base import FilterTuning
from kvark_ros.core.residual_model import KMPResidualModel
from kvark_ros.core.robot_model import RobotModel

VARIANCE_FLOOR = 1e-8   # N²·m², keeps R positive on noise-free (synthetic) data


def virtual_measurements(robot: RobotModel, residual: KMPResidualModel | None, stamp: np.ndarray,
                         q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> np.ndarray:
    """``y_k = (p_k − p_{k−1})/t_s − u_{k−1} + μ_*(q̇_k)`` for k ≥ 1, shape (T−1, n), N·m.

    With no residual model the KMP mean term is left out (what the residual-free observers see).
    """
    momentum = np.empty_like(q)
    inputs = np.empty_like(q)
    for k in range(len(stamp)):
        momentum[k], inputs[k] = robot.momentum_terms(q[k], qd[k], tau_m[k])
    y = np.diff(momentum, axis=0) / np.diff(stamp)[:, None] - inputs[:-1]
    if residual is not None:
        y += residual.predict_batch(qd[1:])[0]
    return y


def match_covariances(y: np.ndarray, dt: float, time_constant: float = 0.02) -> FilterTuning:
    """Filter tuning from training virtual measurements ``y`` (T, n) at nominal step ``dt`` s."""
    if y.ndim != 2 or len(y) < 10 or not np.isfinite(y).all():
        raise ValueError("covariance matching needs at least 10 finite virtual measurements per joint")
    if not (dt > 0.0 and time_constant > dt):
        raise ValueError(f"time_constant ({time_constant} s) must exceed the sample step ({dt} s)")
    second_moment = np.maximum(np.mean(y * y, axis=0), VARIANCE_FLOOR)
    median = np.maximum(np.median(y * y, axis=0), VARIANCE_FLOOR)
    return FilterTuning(process_noise_density=second_moment * dt / time_constant ** 2,
                        measurement_variance=second_moment,
                        empirical_variance=median)
