"""Error statistics of an observer against ground truth (paper v2 Tables IV-V)."""
from __future__ import annotations

from typing import Any

import numpy as np


def _rounded(values: np.ndarray | float) -> Any:
    if np.ndim(values) == 0:
        return None if not np.isfinite(values) else round(float(values), 6)
    return [None if not np.isfinite(v) else round(float(v), 6) for v in values]


def observer_metrics(result: Any, truth: Any) -> dict[str, Any]:
    """metrics.json's per-observer entry: joint/force/moment RMSE, |error| statistics, coverage95, µs/step.

    Only samples where the observer gave an estimate and the truth is finite count. coverage95 is the
    share of joint samples whose true τ_ext lies within the reported ±1.96 σ (None without a covariance).
    """
    entry: dict[str, Any] = {"us_per_step": round(result.us_per_step, 2),
                             "estimates": int(result.valid.sum()), "rejected": result.rejected}
    if truth is None:
        return entry
    rows = result.valid & np.isfinite(truth.tau_ext).all(axis=1)
    error = result.tau_ext[rows] - truth.tau_ext[rows]
    magnitude = np.abs(error)
    joint_rmse = np.sqrt(np.mean(error ** 2, axis=0))
    entry.update({
        "joint_rmse": _rounded(joint_rmse), "joint_rmse_mean": _rounded(joint_rmse.mean()),
        "mean_abs": _rounded(magnitude.mean()), "p95": _rounded(np.percentile(magnitude, 95)),
        "max": _rounded(magnitude.max()), "temporal_std": _rounded(error.std(axis=0).mean()),
        "coverage95": None,
    })
    if result.tau_std is not None:
        inside = magnitude <= 1.96 * result.tau_std[rows]
        entry["coverage95"] = _rounded(inside.mean())
    if truth.wrench is not None:
        wrench_rows = rows & np.isfinite(truth.wrench).all(axis=1)
        wrench_error = result.wrench[wrench_rows] - truth.wrench[wrench_rows]
        wrench_rmse = np.sqrt(np.mean(wrench_error ** 2, axis=0))
        entry.update({"force_rmse": _rounded(wrench_rmse[:3]), "moment_rmse": _rounded(wrench_rmse[3:]),
                      "force_rmse_mean": _rounded(wrench_rmse[:3].mean()),
                      "moment_rmse_mean": _rounded(wrench_rmse[3:].mean())})
    return entry
