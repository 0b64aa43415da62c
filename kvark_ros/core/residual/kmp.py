"""Residual-torque model of K-VARK: GMM -> GMR reference -> KMP mean and variance.

Per joint j the model maps the joint velocity q̇_j (rad/s) to the residual torque
τ_r,j = τ_m,j − τ_EL,j (N·m), the part of the measured torque the rigid-body model does not
explain (mostly friction). Following paper v1, §III-D and §IV-B:

1. a Gaussian mixture (EM, full covariances) is fitted to the points (q̇_j, τ_r,j);
2. Gaussian mixture regression (GMR) conditions it at N support velocities s_i, giving the
   reference {s_i, μ_i, σ²_i} (eq. 18, with one output dimension: Σ = diag(σ²_i));
3. kernelised movement primitives (KMP) turn the reference into a predictive mean (eq. 22)
   and a heteroscedastic predictive variance (eq. 23) at any query velocity.

All joints are handled at once with arrays of shape (n, N); the per-joint factorisations are
computed once at construction so that a query (500 Hz, inside the filter loop) costs one kernel
evaluation and one small batched matrix-vector product.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.linalg
from scipy.special import logsumexp
from sklearn.mixture import GaussianMixture

from kvark_ros.core.residual.common import BATCH_CHUNK, VARIANCE_FLOOR, check_batch, check_training_data
from kvark_ros.core.residual.files import (
    FORMAT_VERSION,
    ResidualModelError,
    check_listed_values,
    freeze_positive_vectors,
    frozen_float_array,
    read_arrays,
    read_model_header,
    save_model_pair,
)

__all__ = [
    "GMRReference",
    "KMPHyperparameters",
    "KMPResidualModel",
    "default_hyperparameters",
    "fit_gmr_reference",
]

STEM = "kmp"
NPZ_NAME = f"{STEM}.npz"
YAML_NAME = f"{STEM}.yaml"

# reg_covar of the GMM, in standardised units (both coordinates have unit variance). It keeps
# each component's standard deviation above 1 % of the data spread, so a component cannot
# collapse onto one line of quantised velocities (encoder resolution / t_s) or onto q̇ = 0
# samples at standstill, and it costs little: a noise variance of (2 % of the spread)² is
# inflated by only 25 %.
GMM_REG_COVAR = 1e-4
GMM_MAX_ITER = 300
# Floor of the GMR variances relative to the variance of the joint's residual torque, with an
# absolute floor for a constant residual, so that Σ in eqs. 22-23 stays positive definite.
GMR_VARIANCE_FLOOR_REL = 1e-6
GMR_VARIANCE_FLOOR_ABS = 1e-12

_REFERENCE_KEYS = ("s", "mu", "sigma2")
_HYPER_KEYS = ("length_scale", "sigma_f2", "lambda1", "lambda2")


@dataclass(frozen=True)
class KMPHyperparameters:
    """Per-joint KMP hyperparameters, arrays of shape (n,), all strictly positive.

    Stored as read-only float64 copies so that a model built from them cannot drift out of
    sync with its precomputed factors.
    """

    length_scale: np.ndarray  # rad/s
    sigma_f2: np.ndarray  # kernel amplitude, N²·m²
    lambda1: np.ndarray  # mean regularisation (eq. 22)
    lambda2: np.ndarray  # variance regularisation (eq. 23)

    def __post_init__(self) -> None:
        freeze_positive_vectors(self, _HYPER_KEYS)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.length_scale.shape[0]


@dataclass(frozen=True)
class GMRReference:
    """GMR reference per joint: support inputs s (n, N) rad/s, means mu (n, N) N·m,
    variances sigma2 (n, N) N²·m².

    This is the probabilistic reference {s_i, μ_i, Σ_i} of eq. 18; sigma2 must be strictly
    positive so that Σ = diag(sigma2) is positive definite. Arrays are stored as read-only
    float64 copies.
    """

    s: np.ndarray
    mu: np.ndarray
    sigma2: np.ndarray

    def __post_init__(self) -> None:
        for key in _REFERENCE_KEYS:
            object.__setattr__(self, key, frozen_float_array(key, getattr(self, key), ndim=2))
        shapes = {getattr(self, key).shape for key in _REFERENCE_KEYS}
        if len(shapes) != 1:
            raise ResidualModelError(f"reference arrays differ in shape: {shapes}")
        if self.s.shape[1] < 1:
            raise ResidualModelError("reference has no support points")
        if np.any(self.sigma2 <= 0.0):
            raise ResidualModelError("sigma2 must be strictly positive")


def default_hyperparameters(n: int, n_support: int = 30) -> KMPHyperparameters:
    """Reasonable KMP hyperparameters for joint-friction residuals of a torque-controlled arm.

    - length_scale 0.1 rad/s: the Coulomb/Stribeck transition of arm friction is a few
      hundredths of a rad/s wide (e.g. Gaz et al. 2019: 1/φ2 = 0.06-0.2 rad/s on the Panda),
      so a longer scale blurs the step at q̇ = 0. The support spacing
      (max q̇ − min q̇)/(N − 1) must not exceed it: at spacing 1.4 × length_scale the
      variance already swings by a factor of 3 between support points (at ≤ 1 ×, by < 15 %).
      With N = 30 that holds for a velocity range up to 2.9 rad/s; for a wider range (the
      Panda reaches ±2.6 rad/s) raise N to ≥ range/length_scale + 1.
    - sigma_f2 1 N²·m²: prior spread of the residual, the size of arm joint friction.
    - lambda1 1: treat each GMR mean as an observation with the GMR (data) variance, which
      smooths noise without flattening the friction curve.
    - lambda2 = N·sigma_f2: the variance far from the data, N·sigma_f2/lambda2 (eq. 23), is then
      1 N²·m² (1 N·m standard deviation, "friction-sized and unknown"), while near the data it
      follows the GMR variance.

    n: number of joints; n_support: N, the number of GMR support points the model will use.
    """
    if n < 1 or n_support < 1:
        raise ValueError(f"n and n_support must be positive, got n={n}, n_support={n_support}")
    sigma_f2 = 1.0
    return KMPHyperparameters(
        length_scale=np.full(n, 0.1),
        sigma_f2=np.full(n, sigma_f2),
        lambda1=np.full(n, 1.0),
        lambda2=np.full(n, n_support * sigma_f2),
    )


def _gmr_1d(x: np.ndarray, y: np.ndarray, s: np.ndarray, n_components: int,
            seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Fit a GMM to (x, y) (T,) and condition it at inputs s (N,); return mean, variance (N,).

    The data are standardised before EM (velocity and torque scales differ by orders of
    magnitude) and the result is mapped back to physical units.
    """
    x_mean, x_std = x.mean(), x.std()
    y_mean, y_std = y.mean(), y.std()
    if y_std == 0.0:
        y_std = 1.0
    data = np.column_stack(((x - x_mean) / x_std, (y - y_mean) / y_std))
    gmm = GaussianMixture(n_components=n_components, covariance_type="full",
                          reg_covar=GMM_REG_COVAR, max_iter=GMM_MAX_ITER,
                          random_state=seed).fit(data)
    m_x, m_y = gmm.means_[:, 0], gmm.means_[:, 1]
    cov = gmm.covariances_
    c_xx, c_xy, c_yy = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    xs = ((s - x_mean) / x_std)[:, None]  # (N, 1)
    # Responsibilities h_k(s) ∝ π_k N(s; m_x,k, c_xx,k), normalised in log space (N, K).
    log_h = (np.log(gmm.weights_) - 0.5 * np.log(2.0 * np.pi * c_xx)
             - 0.5 * (xs - m_x) ** 2 / c_xx)
    h = np.exp(log_h - logsumexp(log_h, axis=1, keepdims=True))
    # Per-component conditional mean and variance of y given x.
    cond_mean = m_y + c_xy / c_xx * (xs - m_x)  # (N, K)
    cond_var = c_yy - c_xy ** 2 / c_xx  # (K,)
    mean = np.sum(h * cond_mean, axis=1)
    var = np.sum(h * (cond_var + (cond_mean - mean[:, None]) ** 2), axis=1)
    mean_phys = y_mean + y_std * mean
    var_phys = y_std ** 2 * var
    floor = max(GMR_VARIANCE_FLOOR_REL * y.var(), GMR_VARIANCE_FLOOR_ABS)
    return mean_phys, np.maximum(var_phys, floor)


def fit_gmr_reference(qd: np.ndarray, tau_r: np.ndarray, n_components: int = 10,
                      n_support: int = 30, seed: int = 0) -> GMRReference:
    """qd, tau_r: (T, n). Fits one GMM per joint and conditions it at n_support points (GMR).

    qd in rad/s, tau_r in N·m. Support points are n_support evenly spaced velocities over the
    observed range of each joint. Raises ValueError for non-finite data, mismatched shapes,
    fewer than 5 * n_components samples, or a joint whose velocity is constant.
    """
    qd, tau_r = check_training_data(qd, tau_r, n_components, n_support)
    n_joints = qd.shape[1]
    s = np.linspace(qd.min(axis=0), qd.max(axis=0), n_support, axis=1)  # (n, N)
    mu = np.empty_like(s)
    sigma2 = np.empty_like(s)
    for j in range(n_joints):
        mu[j], sigma2[j] = _gmr_1d(qd[:, j], tau_r[:, j], s[j], n_components, seed)
    return GMRReference(s=s, mu=mu, sigma2=sigma2)


class KMPResidualModel:
    """Vectorised across joints; all factors precomputed at construction so predict() is
    one kernel evaluation and two small products per joint (it runs at 500 Hz in a filter loop).

    Kernel (eq. 21): k(s, s') = sigma_f2 · exp(−(s − s')² / (2 length_scale²)); the paper's
    `l` plays the role of length_scale². With K_j the Gram matrix of joint j (eq. 19) and
    Σ_j = diag(sigma2_j) (eq. 18):
        mean     μ_*  = k_*ᵀ (K + λ1 Σ)⁻¹ μ                              (eq. 22)
        variance Σ_*  = (N/λ2) (k_** − k_*ᵀ (K + λ2 Σ)⁻¹ k_*), k_** = sigma_f2  (eq. 23)
    Far from the support points the mean tends to 0 and the variance to N·sigma_f2/λ2. Near
    them the variance grows with the GMR variance (heteroscedastic) but is not equal to it:
    N/λ2 scales it, so the filter's covariance matching, not this model, fixes its absolute
    level.

    Attributes: reference (GMRReference), hyper (KMPHyperparameters), metadata (dict, written
    to and read from kmp.yaml).
    """

    def __init__(self, reference: GMRReference, hyper: KMPHyperparameters,
                 metadata: Mapping[str, Any] | None = None) -> None:
        if reference.s.shape[0] != hyper.n_joints:
            raise ResidualModelError(
                f"reference has {reference.s.shape[0]} joints, hyperparameters have "
                f"{hyper.n_joints}")
        self.reference = reference
        self.hyper = hyper
        self.metadata: dict[str, Any] = dict(metadata or {})
        n, n_sup = reference.s.shape
        self._s = reference.s
        # Exponent factor of eq. 21, (n, 1); the paper's `l` plays the role of length_scale².
        self._neg_half_inv_ls2 = (-0.5 / hyper.length_scale ** 2)[:, None]
        self._sigma_f2 = hyper.sigma_f2
        self._var_scale = n_sup / hyper.lambda2  # N / λ2 of eq. 23, (n,)
        # Rows 0 of _weights: sigma_f2 · (K + λ1 Σ)⁻¹ μ; rows 1..N: sigma_f2 · L⁻¹ with
        # L Lᵀ = K + λ2 Σ. sigma_f2 is folded in so that a query only needs the unscaled
        # kernel e = k_*/sigma_f2: mean = w0·e (eq. 22), k_*ᵀ(K+λ2Σ)⁻¹k_* = ‖W e‖²
        # with W the rows 1..N (eq. 23).
        self._weights = np.empty((n, n_sup + 1, n_sup))
        eye = np.eye(n_sup)
        for j in range(n):
            gram = self._kernel(j, reference.s[j][:, None], reference.s[j][None, :])  # eq. 19
            try:
                mean_factor = scipy.linalg.cho_factor(
                    gram + hyper.lambda1[j] * np.diag(reference.sigma2[j]))
                chol = scipy.linalg.cholesky(
                    gram + hyper.lambda2[j] * np.diag(reference.sigma2[j]), lower=True)
            except np.linalg.LinAlgError as exc:
                raise ResidualModelError(
                    f"joint {j}: K + λΣ is not numerically positive definite ({exc}); "
                    "increase sigma2 or lambda, or use fewer support points") from exc
            alpha = scipy.linalg.cho_solve(mean_factor, reference.mu[j])
            chol_inv = scipy.linalg.solve_triangular(chol, eye, lower=True)
            self._weights[j, 0] = hyper.sigma_f2[j] * alpha
            self._weights[j, 1:] = hyper.sigma_f2[j] * chol_inv
        self._weights.setflags(write=False)

    def _kernel(self, j: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Squared-exponential kernel of joint j between broadcastable inputs (eq. 21)."""
        return self.hyper.sigma_f2[j] * np.exp(self._neg_half_inv_ls2[j, 0] * (a - b) ** 2)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self._s.shape[0]

    @property
    def n_support(self) -> int:
        """Number of GMR support points N per joint."""
        return self._s.shape[1]

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (n,) one sample -> (mean (n,) N·m, variance (n,) N²·m²).

        Hot path: no Python loop over joints, no allocation beyond a few small temporaries.

        qd in rad/s, assumed finite (the caller validates). The variance is floored twice:
        far from the training data (far-field floor) and at VARIANCE_FLOOR.

        Far-field floor (ours, not the paper's): away from the support points the KMP mean reverts
        to 0, but eq. 23's variance tends to (N/λ₂)·σ_f², which is small once λ₂ is calibrated on
        held-out data (measured: σ 0.018 N·m on a Panda wrist whose friction there is 0.25 N·m,
        which flagged contact in free motion). Out of its data the model knows no more than its
        prior, so var ≥ σ_f²(1 − c²) with c = maxᵢ k(q̇, sᵢ)/σ_f², the variance of a GP
        conditioned noise-free on the nearest support point alone: 0 on the data, σ_f² far away.
        """
        e = qd[:, None] - self._s
        np.square(e, out=e)
        np.multiply(e, self._neg_half_inv_ls2, out=e)
        np.exp(e, out=e)  # k_*/sigma_f2, (n, N)
        w = np.matmul(self._weights, e[:, :, None])[:, :, 0]  # (n, N+1)
        mean = w[:, 0]  # eq. 22
        v = w[:, 1:]
        var = self._var_scale * (self._sigma_f2 - np.einsum("ij,ij->i", v, v))  # eq. 23
        nearest = e.max(axis=1)
        np.maximum(var, self._sigma_f2 * (1.0 - nearest * nearest), out=var)  # far-field floor
        np.maximum(var, VARIANCE_FLOOR, out=var)
        return mean, var

    def predict_batch(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (T, n) -> mean (T, n), variance (T, n); for training plots and metrics.

        Same equations and floors as predict(), evaluated in chunks to bound memory.
        """
        qd = check_batch(qd, self.n_joints)
        mean = np.empty_like(qd)
        var = np.empty_like(qd)
        for start in range(0, qd.shape[0], BATCH_CHUNK):
            rows = slice(start, start + BATCH_CHUNK)
            e = np.exp(self._neg_half_inv_ls2 * (qd[rows, :, None] - self._s) ** 2)  # (t, n, N)
            w = np.matmul(self._weights, e[..., None])[..., 0]  # (t, n, N+1)
            mean[rows] = w[:, :, 0]  # eq. 22
            quad = np.einsum("tja,tja->tj", w[:, :, 1:], w[:, :, 1:])
            nearest = e.max(axis=2)
            var[rows] = np.maximum(self._var_scale * (self._sigma_f2 - quad),  # eq. 23
                                   self._sigma_f2 * (1.0 - nearest * nearest))  # far-field floor
        np.maximum(var, VARIANCE_FLOOR, out=var)
        return mean, var

    @classmethod
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, hyper: KMPHyperparameters,
            n_components: int = 10, n_support: int = 30, seed: int = 0) -> KMPResidualModel:
        """Fit GMM/GMR to qd (T, n) rad/s and tau_r (T, n) N·m, then build the KMP model."""
        reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                      n_support=n_support, seed=seed)
        return cls(reference, hyper)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/kmp.npz and directory/kmp.yaml, each atomically.

        kmp.npz holds the arrays s, mu, sigma2, length_scale, sigma_f2, lambda1, lambda2;
        kmp.yaml the format version, n_joints, n_support, the hyperparameters as lists and
        `metadata`. Each is written to a temp file in the same directory, then os.replace'd.

        metadata defaults to self.metadata and must contain plain YAML types only. The npz is
        written first, so a crash in between leaves the previous kmp.yaml.
        """
        arrays = {key: getattr(self.reference, key) for key in _REFERENCE_KEYS}
        arrays.update({key: getattr(self.hyper, key) for key in _HYPER_KEYS})
        header = {
            "format_version": FORMAT_VERSION,
            "n_joints": self.n_joints,
            "n_support": self.n_support,
            "hyperparameters": {key: getattr(self.hyper, key).tolist() for key in _HYPER_KEYS},
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, STEM, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> KMPResidualModel:
        """Load a model written by save(); the npz is read with np.load(..., allow_pickle=False).

        Missing file, missing array, wrong shape, non-finite values, an unknown format version
        or hyperparameters in kmp.yaml that disagree with kmp.npz -> ResidualModelError (a
        ValueError) whose message names the file and the problem.
        """
        directory = Path(directory)
        yaml_path, npz_path = directory / YAML_NAME, directory / NPZ_NAME
        header = read_model_header(yaml_path, ("n_support",))
        shapes = {key: (header["n_joints"], header["n_support"]) for key in _REFERENCE_KEYS}
        shapes.update({key: (header["n_joints"],) for key in _HYPER_KEYS})
        arrays = read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, _HYPER_KEYS)
        try:
            reference = GMRReference(**{key: arrays[key] for key in _REFERENCE_KEYS})
            hyper = KMPHyperparameters(**{key: arrays[key] for key in _HYPER_KEYS})
            return cls(reference, hyper, metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc
