"""Fitting KMP residual models whose joints take a second input besides q̇ (docs/method.md §3.7).

On a real robot the part of the measured torque the rigid-body model misses depends on the pose
(link inertial errors, an unmodelled tool, cable forces), not only on the joint velocity: on the
real Panda recording the held-out residual of the augmented model was 0.41 N·m mean RMSE with
q̇_j alone and 0.30 with (q̇_j, q_j). A joint's input is one of ``INPUT_KINDS``:

* ``qd``    q̇_j alone (paper v1): GMR at N evenly spaced velocities, hyperparameters from the GP
  fit on GMR samples (``hyperparameters_from_gp``);
* ``qd_q``  (q̇_j, q_j) and ``qd_g`` (q̇_j, g_j(q)), g the model's gravity torque: a GMM on
  (q̇_j, z_j, τ_r,j), GMR at N support points placed by k-means on the training inputs (a grid
  would put most of them where the motion never goes), and an SE kernel with one length scale
  per input (ARD) fitted by GP marginal likelihood on a subsample of the data.

All joints share N, so the model stays one batched array per joint.
"""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
from scipy.special import logsumexp
from sklearn.cluster import KMeans
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
from sklearn.mixture import GaussianMixture

from kvark_ros.core.residual.common import check_training_data, single_threaded
from kvark_ros.core.residual.gp import hyperparameters_from_gp
from kvark_ros.core.residual.kmp import (
    GMM_MAX_ITER,
    GMM_REG_COVAR,
    GMR_VARIANCE_FLOOR_ABS,
    GMR_VARIANCE_FLOOR_REL,
    INPUT_KINDS,
    GMRReference,
    KMPHyperparameters,
    KMPResidualModel,
    fit_gmr_reference,
)

GP_SUBSAMPLE = 500            # samples of the ARD GP fit (O(T³) per likelihood evaluation: ~1 s per joint)
GP_SAMPLES_BUDGET = 400       # GMR samples of the q̇-only GP fit, spread over the N support points
# Length-scale bounds of the ARD fit, in standardised input units: below 0.05 no two support points
# see each other (N ≤ 100 over a few standard deviations), above 20 an input is irrelevant.
ARD_LENGTH_BOUNDS = (0.05, 20.0)


def second_inputs(kinds: Sequence[str], q: np.ndarray, g: np.ndarray) -> np.ndarray:
    """z (T, n): q_j for ``qd_q`` joints, g_j for ``qd_g`` joints, 0 for ``qd`` joints."""
    unknown = sorted(set(kinds) - set(INPUT_KINDS))
    if unknown:
        raise ValueError(f"unknown residual inputs {unknown}; known: {list(INPUT_KINDS)}")
    takes_q = np.array([kind == "qd_q" for kind in kinds])
    takes_g = np.array([kind == "qd_g" for kind in kinds])
    return np.where(takes_q, q, np.where(takes_g, g, 0.0))


def _gmr_2d(x: np.ndarray, y: np.ndarray, n_support: int, n_components: int,
            seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GMM on (x (T, 2), y (T,)) standardised, conditioned at k-means support points (eq. 18).

    Returns support points (N, 2), GMR means (N,) and variances (N,) in physical units.
    """
    x_mean, x_std = x.mean(axis=0), x.std(axis=0)
    x_std[x_std == 0.0] = 1.0
    y_mean, y_std = y.mean(), y.std() or 1.0
    xs = (x - x_mean) / x_std
    support = KMeans(n_support, n_init=3, random_state=seed).fit(xs).cluster_centers_
    gmm = GaussianMixture(n_components=n_components, covariance_type="full", reg_covar=GMM_REG_COVAR,
                          max_iter=GMM_MAX_ITER, random_state=seed).fit(np.column_stack((xs, (y - y_mean) / y_std)))
    log_h = np.empty((n_support, n_components))
    cond_mean = np.empty((n_support, n_components))
    cond_var = np.empty(n_components)
    for k in range(n_components):
        c = gmm.covariances_[k]
        c_xx_inv = np.linalg.inv(c[:2, :2])
        diff = support - gmm.means_[k, :2]
        log_h[:, k] = (np.log(gmm.weights_[k]) - 0.5 * np.linalg.slogdet(2.0 * np.pi * c[:2, :2])[1]
                       - 0.5 * np.einsum("ij,jk,ik->i", diff, c_xx_inv, diff))
        cond_mean[:, k] = gmm.means_[k, 2] + diff @ c_xx_inv @ c[:2, 2]      # E[y | x] of component k
        cond_var[k] = c[2, 2] - c[2, :2] @ c_xx_inv @ c[:2, 2]
    h = np.exp(log_h - logsumexp(log_h, axis=1, keepdims=True))
    mean = np.sum(h * cond_mean, axis=1)
    var = np.sum(h * (cond_var + (cond_mean - mean[:, None]) ** 2), axis=1)
    floor = max(GMR_VARIANCE_FLOOR_REL * y.var(), GMR_VARIANCE_FLOOR_ABS)
    return support * x_std + x_mean, y_mean + y_std * mean, np.maximum(y_std ** 2 * var, floor)


def _ard_hyperparameters(x: np.ndarray, y: np.ndarray, sigma2: np.ndarray, seed: int) -> tuple[float, ...]:
    """(length_scale, length_scale2, sigma_f2, lambda1) of a two-input joint from a zero-mean ARD SE GP
    fitted to a subsample of (x (T, 2), y (T,)).

    λ₁ follows ``hyperparameters_from_gp``: each GMR mean stands for m = T/N samples, so
    λ₁ mean(σ²) = σn²/m.
    """
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(x), min(GP_SUBSAMPLE, len(x)), replace=False)
    x_std = x.std(axis=0)
    x_std[x_std == 0.0] = 1.0
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    kernel = (ConstantKernel(1.0, (1e-4, 1e2)) * RBF(np.ones(2), ARD_LENGTH_BOUNDS)
              + WhiteKernel(1e-2, (1e-6, 1e1)))
    gpr = GaussianProcessRegressor(kernel=kernel, alpha=1e-10, n_restarts_optimizer=0, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)   # an irrelevant input sits at the upper bound
        gpr.fit(x[rows] / x_std, y[rows] / scale)
    fitted = gpr.kernel_
    length = np.asarray(fitted.k1.k2.length_scale) * x_std
    noise = float(fitted.k2.noise_level) * scale ** 2
    per_support = len(x) / len(sigma2)
    return (float(length[0]), float(length[1]), float(fitted.k1.k1.constant_value) * scale ** 2,
            noise / (per_support * float(np.mean(sigma2))))


@single_threaded
def fit_kmp(qd: np.ndarray, z: np.ndarray, tau_r: np.ndarray, inputs: Sequence[str], n_components: int,
            n_support: int, seed: int = 0) -> KMPResidualModel:
    """A KMP residual model with the given inputs per joint, from qd (T, n) rad/s, second inputs z (T, n)
    (``second_inputs``) and tau_r (T, n) N·m; λ₂ is the default N·σ_f² (calibrate it afterwards)."""
    inputs = tuple(inputs)
    qd, tau_r = check_training_data(qd, tau_r, n_components, n_support)
    n = qd.shape[1]
    if "qd" in inputs:
        reference = fit_gmr_reference(qd, tau_r, n_components=n_components, n_support=n_support, seed=seed)
        # The GP of the q̇-only joints is fitted on its own 10-component reference (hyperparameters_from_gp's
        # default), as paper v2 §V-B's GMR-GP.
        hyper = hyperparameters_from_gp(qd, tau_r, n_support, seed,
                                        samples_per_support=max(1, GP_SAMPLES_BUDGET // n_support))
        if all(kind == "qd" for kind in inputs):
            return KMPResidualModel(reference, hyper, inputs=inputs)
        s, mu, sigma2, s2 = (np.array(a) for a in (reference.s, reference.mu, reference.sigma2, reference.s2))
        ls, ls2, sf2, lam1 = (np.array(a) for a in (hyper.length_scale, hyper.length_scale2, hyper.sigma_f2,
                                                     hyper.lambda1))
    else:
        s, mu, sigma2, s2 = (np.zeros((n, n_support)) for _ in range(4))
        ls, ls2, sf2, lam1 = (np.ones(n) for _ in range(4))
    for j, kind in enumerate(inputs):
        if kind == "qd":
            continue
        x = np.column_stack((qd[:, j], z[:, j]))
        support, mu[j], sigma2[j] = _gmr_2d(x, tau_r[:, j], n_support, n_components, seed)
        s[j], s2[j] = support[:, 0], support[:, 1]
        ls[j], ls2[j], sf2[j], lam1[j] = _ard_hyperparameters(x, tau_r[:, j], sigma2[j], seed + j)
    hyper = KMPHyperparameters(length_scale=ls, sigma_f2=sf2, lambda1=lam1, lambda2=n_support * sf2,
                               length_scale2=ls2)
    return KMPResidualModel(GMRReference(s=s, mu=mu, sigma2=sigma2, s2=s2), hyper, inputs=inputs)
