"""The diagnosis's parameter covariance counts the residuals' correlation in time (``gap.fitting``)."""
from __future__ import annotations

import numpy as np

from kvark_ros.gap.fitting import long_run_covariance

RHO = 0.9          # lag-one correlation of the slow series: the gap's misfit is about this smooth at 8 ms
SAMPLES = 20_000


def _scores(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) scores: an AR(1) series with unit innovations (long-run variance 1 / (1 − ρ)² per sample) beside white
    noise (1 per sample)."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((SAMPLES, 2))
    slow = np.empty(SAMPLES)
    slow[0] = noise[0, 0] / np.sqrt(1.0 - RHO ** 2)
    for t in range(1, SAMPLES):
        slow[t] = RHO * slow[t - 1] + noise[t, 0]
    return np.column_stack([slow, noise[:, 1]]), slow


def test_the_long_run_covariance_of_a_slow_series_is_its_sum_not_its_sample_count() -> None:
    """Σ_t Σ_s E[x_t x_s] = T / (1 − ρ)² = 100 T for ρ = 0.9, where Σ x_t² (every sample independent, what the
    least-squares covariance assumes) gives T / (1 − ρ²) = 5.3 T. The Bartlett estimate at Andrews' bandwidth
    (L ≈ 140 here) is within 25 % of the truth: its bias is about −2ρ / ((1 − ρ²) L) = −7 % and its standard error
    √(4L / 3T) = 10 % (seeds 0-4 gave 0.83-1.07 of it). The white column stays at T, the cross term near 0."""
    scores, slow = _scores(seed=0)
    covariance = long_run_covariance(scores)
    assert abs(covariance[0, 0] / (SAMPLES / (1.0 - RHO) ** 2) - 1.0) < 0.25
    assert float(slow @ slow) < 0.1 * covariance[0, 0]
    assert abs(covariance[1, 1] / SAMPLES - 1.0) < 0.25
    assert abs(covariance[0, 1]) < 0.2 * np.sqrt(covariance[0, 0] * covariance[1, 1])
    np.testing.assert_allclose(covariance, covariance.T)
    assert np.all(np.linalg.eigvalsh(covariance) >= 0.0)      # Bartlett weights keep it a covariance
