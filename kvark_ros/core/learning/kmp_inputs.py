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

from concurrent.futures import Executor
from typing import Callable, Sequence

import numpy as np
from scipy.special import logsumexp
from sklearn.cluster import KMeans

from kvark_ros.core.estimation.residual.common import check_training_data, single_threaded, submit_joints
from kvark_ros.core.estimation.residual.gmm import fit_mixture
from kvark_ros.core.estimation.residual.gp import gmr_sample_noise, kmp_hyperparameters_of_joint
from kvark_ros.core.estimation.residual.gp_fit import fit_gp
from kvark_ros.core.estimation.residual.kmp import (
    GMR_VARIANCE_FLOOR_ABS,
    GMR_VARIANCE_FLOOR_REL,
    INPUT_KINDS,
    GMRReference,
    KMPHyperparameters,
    KMPResidualModel,
    gmr_1d,
)

GP_SUBSAMPLE = 500            # samples of the ARD GP fit (O(T³) per likelihood evaluation: ~0.15 s per joint)
GP_SAMPLES_BUDGET = 400       # GMR samples of the q̇-only GP fit, spread over the N support points
GP_REFERENCE_COMPONENTS = 10  # GMM components of the reference the q̇-only GP samples (hyperparameters_from_gp's)
# Length-scale bounds of the ARD fit, in standardised input units: below 0.05 no two support points
# see each other (N ≤ 100 over a few standard deviations), above 20 an input is irrelevant.
ARD_LENGTH_BOUNDS = (0.05, 20.0)
ARD_AMPLITUDE_BOUNDS = (1e-4, 1e2)     # σ_f² and σ_n² of the ARD fit, in units of the residual's mean square
ARD_NOISE_BOUNDS = (1e-6, 1e1)
# One joint's fit: its GMR reference s, μ, σ², s2 (N,) and hyperparameters ℓ, ℓ₂, σ_f², λ₁.
JointFit = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float, float, float]


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
    gmm = fit_mixture(np.column_stack((xs, (y - y_mean) / y_std)), n_components, seed)
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
    fitted to a subsample of (x (T, 2), y (T,)) (``fit_gp``, from σ_f² 1, ℓ 1, σ_n² 10⁻² in standardised units).

    λ₁ follows ``hyperparameters_from_gp``: each GMR mean stands for m = T/N samples, so
    λ₁ mean(σ²) = σn²/m. An irrelevant input's length scale sits at the upper bound.
    """
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(x), min(GP_SUBSAMPLE, len(x)), replace=False)
    x_std = x.std(axis=0)
    x_std[x_std == 0.0] = 1.0
    scale = float(np.sqrt(np.mean(y ** 2))) or 1.0
    bounds = np.log([ARD_AMPLITUDE_BOUNDS, ARD_LENGTH_BOUNDS, ARD_LENGTH_BOUNDS, ARD_NOISE_BOUNDS])
    fit = fit_gp(x[rows] / x_std, y[rows] / scale, np.log([1.0, 1.0, 1.0, 1e-2]), bounds, 0, seed)
    length = fit.length_scale * x_std
    noise = fit.noise_var * scale ** 2
    per_support = len(x) / len(sigma2)
    return (float(length[0]), float(length[1]), fit.sigma_f2 * scale ** 2,
            noise / (per_support * float(np.mean(sigma2))))


def fit_joint(kind: str, x: np.ndarray, z: np.ndarray, y: np.ndarray, n_components: int, n_support: int, seed: int,
              joint: int, noise: np.ndarray) -> JointFit:
    """One joint of ``fit_kmp`` with inputs ``kind``, from its q̇ x (T,) rad/s, second input z (T,) and τ_r y (T,) N·m:
    the GMR reference (s, μ, σ², s2 (N,), eq. 18) and the hyperparameters (ℓ, ℓ₂, σ_f², λ₁).

    A ``qd`` joint's GP is fitted on samples μᵢ + σᵢ ε of its own 10-component reference (hyperparameters_from_gp's
    default), as paper v2 §V-B's GMR-GP; ε: noise (N, m), that joint's share of ``gmr_sample_noise``.
    """
    if kind == "qd":
        s = np.linspace(x.min(), x.max(), n_support)
        mu, sigma2 = gmr_1d(x, y, s, n_components, seed)
        gp_mu, gp_sigma2 = gmr_1d(x, y, s, GP_REFERENCE_COMPONENTS, seed)
        length, sigma_f2, lambda1 = kmp_hyperparameters_of_joint(s, gp_mu, gp_sigma2, noise, seed + joint)
        return s, mu, sigma2, np.zeros(n_support), length, 1.0, sigma_f2, lambda1
    x2 = np.column_stack((x, z))
    support, mu, sigma2 = _gmr_2d(x2, y, n_support, n_components, seed)
    length, length2, sigma_f2, lambda1 = _ard_hyperparameters(x2, y, sigma2, seed + joint)
    return support[:, 0], mu, sigma2, support[:, 1], length, length2, sigma_f2, lambda1


@single_threaded
def fit_kmp(qd: np.ndarray, z: np.ndarray, tau_r: np.ndarray, inputs: Sequence[str], n_components: int,
            n_support: int, seed: int = 0, executor: Executor | None = None) -> KMPResidualModel:
    """A KMP residual model with the given inputs per joint, from qd (T, n) rad/s, second inputs z (T, n)
    (``second_inputs``) and tau_r (T, n) N·m; λ₂ is the default N·σ_f² (calibrate it afterwards). Each joint is
    fitted by ``fit_joint``, in ``executor``'s workers when given (``start_kmp_fit``)."""
    return start_kmp_fit(qd, z, tau_r, inputs, n_components, n_support, seed, executor)()


@single_threaded
def start_kmp_fit(qd: np.ndarray, z: np.ndarray, tau_r: np.ndarray, inputs: Sequence[str], n_components: int,
                  n_support: int, seed: int = 0,
                  executor: Executor | None = None) -> Callable[[], KMPResidualModel]:
    """``fit_kmp`` in two steps: the joints' fits start in ``executor``'s workers (two-input joints, the longest,
    first; or run here when it is None) and the returned function waits for them and builds the model, so that
    several models can be fitted at once."""
    inputs = tuple(inputs)
    qd, tau_r = check_training_data(qd, tau_r, n_components, n_support)
    z = np.asarray(z, dtype=np.float64)
    noise = gmr_sample_noise(qd.shape[1], n_support, max(1, GP_SAMPLES_BUDGET // n_support), seed)
    order = sorted(range(len(inputs)), key=lambda j: inputs[j] == "qd")
    pending = submit_joints(fit_joint, [(inputs[j], qd[:, j].copy(), z[:, j].copy(), tau_r[:, j].copy(), n_components,
                                         n_support, seed, j, noise[j]) for j in order], executor)

    def model() -> KMPResidualModel:
        by_joint = dict(zip(order, pending()))
        s, mu, sigma2, s2, length, length2, sigma_f2, lambda1 = (np.array(column) for column in
                                                                zip(*(by_joint[j] for j in range(len(inputs)))))
        hyper = KMPHyperparameters(length_scale=length, sigma_f2=sigma_f2, lambda1=lambda1,
                                   lambda2=n_support * sigma_f2, length_scale2=length2)
        return KMPResidualModel(GMRReference(s=s, mu=mu, sigma2=sigma2, s2=s2), hyper, inputs=inputs)
    return model
