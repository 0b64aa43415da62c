"""The Gaussian mixtures of the GMR references (docs/method.md §3.2, §3.7), fitted by scikit-learn's EM.

Fitting only (it imports scikit-learn; loading a model does not). ``FullGaussianMixture`` is sklearn's
``GaussianMixture(covariance_type="full")`` whose E-step evaluates every component's log density with one matrix
product instead of one per component: the same arithmetic, so the same bits (test_training_speed_equivalence.py
checks it), and about a third less time (measured: 0.18-0.22 vs 0.26-0.32 s per fit of 20 components to 6400
three-dimensional samples, one BLAS thread).
"""
from __future__ import annotations

import numpy as np
from sklearn.mixture import GaussianMixture

# reg_covar of the GMM, in standardised units (both coordinates have unit variance). It keeps
# each component's standard deviation above 1 % of the data spread, so a component cannot
# collapse onto one line of quantised velocities (encoder resolution / t_s) or onto q̇ = 0
# samples at standstill, and it costs little: a noise variance of (2 % of the spread)² is
# inflated by only 25 %.
GMM_REG_COVAR = 1e-4
GMM_MAX_ITER = 300


class FullGaussianMixture(GaussianMixture):
    """``GaussianMixture`` with full covariances and the batched E-step of ``_estimate_log_prob``."""

    def _estimate_log_prob(self, X: np.ndarray) -> np.ndarray:
        """log N(x_t; μ_k, Σ_k) (T, K) as sklearn's ``_estimate_log_gaussian_prob``: with the precision Cholesky
        factors P_k (Σ_k⁻¹ = P_k P_kᵀ), y = x P_k − μ_k P_k and −½ (d log 2π + Σᵢ yᵢ²) + log det P_k."""
        precision = self.precisions_cholesky_
        k, d, _ = precision.shape
        y = (X @ precision.transpose(1, 0, 2).reshape(d, k * d)).reshape(len(X), k, d)   # x P_k, all k at once
        y -= np.stack([np.dot(mu, p) for mu, p in zip(self.means_, precision)])
        np.square(y, out=y)
        squared = y[:, :, 0].copy()
        for i in range(1, d):                     # Σᵢ yᵢ² in sklearn's order
            squared += y[:, :, i]
        log_det = np.sum(np.log(precision.reshape(k, -1)[:, :: d + 1]), axis=1)
        return -0.5 * (d * np.log(2 * np.pi) + squared) + log_det


def fit_mixture(data: np.ndarray, n_components: int, seed: int) -> FullGaussianMixture:
    """EM fit of ``n_components`` full-covariance Gaussians to standardised data (T, d), ``GMM_REG_COVAR`` on the
    diagonal, at most ``GMM_MAX_ITER`` iterations, k-means initialisation seeded by ``seed``."""
    return FullGaussianMixture(n_components=n_components, covariance_type="full", reg_covar=GMM_REG_COVAR,
                               max_iter=GMM_MAX_ITER, random_state=seed).fit(data)
