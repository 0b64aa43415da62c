"""The Gaussian mixtures of the GMR references (docs/method.md §3.2, §3.7), fitted by scikit-learn's EM.

Fitting only (it imports scikit-learn; loading a model does not). The mixture is scikit-learn's public
``GaussianMixture(covariance_type="full")``.
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


def fit_mixture(data: np.ndarray, n_components: int, seed: int) -> GaussianMixture:
    """EM fit of ``n_components`` full-covariance Gaussians to standardised data (T, d), ``GMM_REG_COVAR`` on the
    diagonal, at most ``GMM_MAX_ITER`` iterations, k-means initialisation seeded by ``seed``."""
    return GaussianMixture(n_components=n_components, covariance_type="full", reg_covar=GMM_REG_COVAR,
                           max_iter=GMM_MAX_ITER, random_state=seed).fit(data)
