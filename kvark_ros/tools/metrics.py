"""Error statistics of an observer against ground truth (paper v2 Tables IV-V) and the calibration of its
reported covariance: per joint, over the whole joint vector, and at several nominal levels."""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import ndtri

from kvark_ros.core.contact_events import CONTACT_TORQUE, contact_free, contacts, touching
from kvark_ros.core.estimation.contact import chi2_quantile

Z95 = 1.96                                  # half-width of the 95 % interval in σ (coverage95, as it always was)
ALPHA95 = 0.05                              # 1 − the nominal coverage of that interval (the interval score's α)
LEVELS = (0.5, 0.8, 0.9, 0.95, 0.99)        # nominal coverages of the reliability table


def _rounded(values: np.ndarray | float) -> Any:
    if np.ndim(values) == 0:
        return None if not np.isfinite(values) else round(float(values), 6)
    return [None if not np.isfinite(v) else round(float(v), 6) for v in values]


def static_band(trained: Any) -> np.ndarray | None:
    """The trained model's static friction band F_s (n,) N·m, or None (not identified)."""
    return None if trained is None or trained.stiction is None else trained.stiction.band


def in_motion(qd: np.ndarray, stiction_velocity: float) -> np.ndarray:
    """(T, n) bool: the joint samples whose |q̇| (T, n) rad/s is above ``filter.stiction_velocity`` v_s rad/s, where
    the static friction band σ²_s = F_s²/3 · exp(−(q̇/v_s)²) has fallen below e⁻¹ of its width at rest (docs/method.md
    §4.11)."""
    return np.abs(qd) > stiction_velocity


def observer_metrics(result: Any, truth: Any, stamp: np.ndarray, band: np.ndarray | None = None,
                     moving: np.ndarray | None = None) -> dict[str, Any]:
    """metrics.json's per-observer entry: joint/force/moment RMSE (:func:`wrench_metrics`: force and moment over the
    samples with a known true wrench), |error| statistics, coverage95, µs/step,
    and the contact and collision flags' figures (:func:`contact_metrics`, under ``contact`` and ``collision``);
    ``collision_share`` (share of estimates flagged) and a ``--tare-at`` tare's outcome also without truth.

    Only samples where the observer gave an estimate and the truth is finite count. coverage95 is the
    share of joint samples whose true τ_ext lies within the reported ±1.96 σ (None without a covariance); the
    other covariance figures are :func:`calibration_metrics`' (each None without a covariance). ``band``: the
    model's static friction band F_s (n,) N·m, for the contact delays counted from the band (:func:`contact_metrics`).
    ``moving``: (T, n) bool, the joint samples in motion (|q̇_j| above ``filter.stiction_velocity``), for
    ``coverage95_moving``, coverage95 over those alone: at rest the static friction band makes the interval span any
    torque the joint can hold, so the samples at rest cover by construction (None: not given, or none in motion).
    """
    entry: dict[str, Any] = {"us_per_step": round(result.us_per_step, 2),
                             "estimates": int(result.valid.sum()), "rejected": result.rejected,
                             "collision_share": _rounded(result.collision[result.valid].mean())
                             if result.valid.any() else None}
    if result.tare is not None:
        entry["tare"] = result.tare
    # κ = ∞ (fewer than 6 joints) becomes None: JSON has no infinity.
    entry["wrench"] = {key: None if value is None else _rounded(value) for key, value in result.singularity().items()}
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
        "coverage95": None, "coverage95_moving": None, **dict.fromkeys(CALIBRATION_KEYS),
        "contact": contact_metrics(stamp, result.contact, result.valid, truth.tau_ext, band),
        "collision": contact_metrics(stamp, result.collision, result.valid, truth.tau_ext, band),
    })
    if result.tau_std is not None:
        inside = magnitude <= 1.96 * result.tau_std[rows]
        entry["coverage95"] = _rounded(inside.mean())
        if moving is not None and moving[rows].any():
            entry["coverage95_moving"] = _rounded(inside[moving[rows]].mean())
        entry.update(calibration_metrics(error, result.tau_std[rows],
                                         None if result.mahalanobis is None else result.mahalanobis[rows]))
    if truth.wrench is not None:
        entry.update(wrench_metrics(result.wrench, truth.wrench, rows))
    return entry


def wrench_metrics(wrench: np.ndarray, truth: np.ndarray, rows: np.ndarray) -> dict[str, Any]:
    """Force/moment RMSE of estimated wrenches (T, 6) over ``rows`` where the true wrench (T, 6) is known (finite:
    ``wrench_truth`` leaves a push the wrist sensor cannot see NaN), and ``wrench_truth_samples``, how many those
    are; the RMSEs are None when there are none (contact not at the sensor)."""
    observed = rows & np.isfinite(truth).all(axis=1)
    entry: dict[str, Any] = {"wrench_truth_samples": int(observed.sum())}
    if not observed.any():
        return {**entry, **dict.fromkeys(("force_rmse", "moment_rmse", "force_rmse_mean", "moment_rmse_mean"))}
    rmse = np.sqrt(np.mean((wrench[observed] - truth[observed]) ** 2, axis=0))
    return {**entry, "force_rmse": _rounded(rmse[:3]), "moment_rmse": _rounded(rmse[3:]),
            "force_rmse_mean": _rounded(rmse[:3].mean()), "moment_rmse_mean": _rounded(rmse[3:].mean())}


CALIBRATION_KEYS = ("coverage95_per_joint", "interval95_per_joint", "interval_score95", "interval_score95_per_joint",
                    "vector_coverage95", "any_joint_miss_share", "any_joint_miss_nominal", "reliability")


def interval_score(lower: np.ndarray, upper: np.ndarray, truth: np.ndarray, alpha: float) -> np.ndarray:
    """The interval score of central (1 − α) prediction intervals [l, u] at the true values x (arrays of one shape,
    N·m): ``(u − l) + (2/α)(l − x)·1{x < l} + (2/α)(x − u)·1{x > u}`` (Gneiting & Raftery 2007, eq. 43, negatively
    oriented: lower is better). A proper score: a forecaster minimises its expectation only by reporting the true
    quantiles, so a narrow interval that misses and a wide one that always covers both pay, where coverage alone
    rewards the wide one."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return (upper - lower) + (2.0 / alpha) * (np.maximum(lower - truth, 0.0) + np.maximum(truth - upper, 0.0))


def mahalanobis_squared(error: np.ndarray, covariance: np.ndarray) -> float:
    """eᵀP⁻¹e of one error (n,) N·m under its reported covariance P (n, n) N²·m²; NaN for a non-finite error or a
    singular P. χ²_n-distributed when P is the error's true covariance."""
    if not np.isfinite(error).all():
        return float("nan")
    try:
        return float(error @ np.linalg.solve(covariance, error))
    except np.linalg.LinAlgError:
        return float("nan")


def mahalanobis_rows(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``mahalanobis_squared`` of many errors (T, n) under their covariances (T, n, n) in one batched solve, (T,)."""
    out = np.full(len(errors), np.nan)
    rows = np.flatnonzero(np.isfinite(errors).all(axis=1) & np.isfinite(covariances).all(axis=(1, 2)))
    try:
        solved = np.linalg.solve(covariances[rows], errors[rows][..., None])[..., 0]
        out[rows] = np.einsum("ti,ti->t", errors[rows], solved)
    except np.linalg.LinAlgError:       # a singular P among them: one at a time, NaN for those
        out[rows] = [mahalanobis_squared(e, c) for e, c in zip(errors[rows], covariances[rows])]
    return out


def calibration_metrics(error: np.ndarray, std: np.ndarray, mahalanobis: np.ndarray | None) -> dict[str, Any]:
    """How honest the reported uncertainty is, from errors e = τ̂ − τ_true (T, n) N·m, their reported σ (T, n) and
    eᵀP⁻¹e (T,) under the full covariance (None: not kept, the vector figures are None).

    ``coverage95_per_joint``: per joint, the share of samples with |e| ≤ 1.96 σ; ``interval95_per_joint``: the mean
    half-width 1.96 σ (N·m) of that interval, what a coverage costs (wider is safer and less useful).
    ``interval_score95`` (and ``_per_joint``): the mean :func:`interval_score` of τ̂ ± 1.96 σ at α = 0.05, N·m: width
    and misses in one figure (lower is better).
    ``vector_coverage95``: the share of samples with eᵀP⁻¹e ≤ χ²_n(0.95), the 95 % ellipsoid of the whole vector
    (correlations count). A miss on any of n joints is far likelier than 5 %: ``any_joint_miss_share`` against
    ``any_joint_miss_nominal`` = 1 − 0.95ⁿ (its value for independent, calibrated joints). ``reliability``: at each
    ``LEVELS`` nominal coverage, the observed per-joint-sample coverage of ±z σ (z the two-sided normal quantile) and
    of the χ²_n ellipsoid.
    """
    n = error.shape[1]
    inside = np.abs(error) <= Z95 * std
    score = interval_score(error - Z95 * std, error + Z95 * std, np.zeros_like(error), ALPHA95)   # τ̂ − τ against 0
    finite = mahalanobis[np.isfinite(mahalanobis)] if mahalanobis is not None else np.zeros(0)
    z = ndtri(0.5 + 0.5 * np.array(LEVELS))
    joint = [float(np.mean(np.abs(error) <= level_z * std)) for level_z in z]
    vector = [float(np.mean(finite <= chi2_quantile(level, n))) for level in LEVELS] if len(finite) else None
    return {"coverage95_per_joint": _rounded(inside.mean(axis=0)),
            "interval95_per_joint": _rounded(Z95 * std.mean(axis=0)),
            "interval_score95": _rounded(float(score.mean())),
            "interval_score95_per_joint": _rounded(score.mean(axis=0)),
            "vector_coverage95": _rounded(float(np.mean(finite <= chi2_quantile(0.95, n)))) if len(finite) else None,
            "any_joint_miss_share": _rounded(float((~inside).any(axis=1).mean())),
            "any_joint_miss_nominal": _rounded(1.0 - 0.95 ** n),
            "reliability": {"nominal": list(LEVELS), "joint": _rounded(np.array(joint)),
                            "vector": None if vector is None else _rounded(np.array(vector))}}


def contact_metrics(stamp: np.ndarray, flag: np.ndarray, valid: np.ndarray, truth_tau: np.ndarray,
                    band: np.ndarray | None = None) -> dict[str, Any]:
    """metrics.json's contact figures of one observer's flag against the true external torque.

    Touching, contact-free samples and contacts as ``core.contact_events`` defines them. ``false_contact_share``: the
    share of contact-free samples that are flagged. Each contact is detected when the flag rises before it ends;
    ``detection_delay`` (s) is from its onset to the first flagged sample (with its mean and median),
    ``missed_onsets`` counts the others. None where the run has no such samples or onsets.

    ``band`` (n,) N·m, the static friction band F_s (docs/method.md §4.11): a joint at rest holds any torque within
    ±F_s, so a push is visible only once it exceeds that. ``detection_delay_from_band`` (s) is counted from the
    first sample of each detected contact where some joint's true |τ_ext| exceeds max(F_s, CONTACT_TORQUE) (0 when
    the flag rose earlier); ``within_band_onsets`` counts the contacts that never exceed it, ``missed_beyond_band``
    those that do and are never flagged.
    """
    rows = valid & np.isfinite(truth_tau).all(axis=1)
    stamp, flag, touch = stamp[rows], flag[rows], touching(truth_tau[rows])
    free = contact_free(stamp, touch)
    beyond = None if band is None else (np.abs(truth_tau[rows]) > np.maximum(band, CONTACT_TORQUE)).any(axis=1)
    delays, band_delays = [], []
    missed = within_band = missed_beyond = 0
    for onset, end in contacts(stamp, touch):
        flagged = np.flatnonzero(flag[onset:end])
        if len(flagged):
            delays.append(float(stamp[onset + flagged[0]] - stamp[onset]))
        else:
            missed += 1
        if beyond is not None:
            visible = np.flatnonzero(beyond[onset:end])
            if not len(visible):
                within_band += 1
            elif len(flagged):
                band_delays.append(max(float(stamp[onset + flagged[0]] - stamp[onset + visible[0]]), 0.0))
            else:
                missed_beyond += 1
    band_figures = {} if band is None else {
        "detection_delay_from_band": _rounded(np.array(band_delays)) if band_delays else None,
        "within_band_onsets": within_band, "missed_beyond_band": missed_beyond}
    return {**band_figures, "false_contact_share": _rounded(flag[free].mean()) if free.any() else None,
            "contact_free_samples": int(free.sum()),
            "onsets": len(delays) + missed, "missed_onsets": missed,
            "detection_delay": _rounded(np.array(delays)) if delays else None,
            "detection_delay_mean": _rounded(float(np.mean(delays))) if delays else None,
            "detection_delay_median": _rounded(float(np.median(delays))) if delays else None}
