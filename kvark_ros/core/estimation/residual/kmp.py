"""Residual-torque model of K-VARK: GMM -> GMR reference -> KMP mean and variance.

Per joint j the model maps the joint velocity q̇_j (rad/s) to the residual torque
τ_r,j = τ_m,j − τ_EL,j (N·m), the part of the measured torque the rigid-body model does not
explain (mostly friction). Following paper v1, §III-D and §IV-B:

1. a Gaussian mixture (EM, full covariances) is fitted to the points (q̇_j, τ_r,j);
2. Gaussian mixture regression (GMR) conditions it at N support velocities s_i, giving the
   reference {s_i, μ_i, σ²_i} (eq. 18, with one output dimension: Σ = diag(σ²_i));
3. kernelised movement primitives (KMP) turn the reference into a predictive mean (eq. 22)
   and a heteroscedastic predictive variance (eq. 23) at any query velocity.

A joint may also take a second input z_j (ours, docs/method.md §3.7): its position q_j
(``qd_q``) or the model's gravity torque g_j(q) (``qd_g``), because a real robot's gap depends
on the pose, which q̇ alone cannot express. Its support points are then pairs (s_i, s2_i) and the
kernel has one length scale per input (ARD); a ``qd`` joint ignores s2 (zero inverse length
scale). ``kvark_ros.core.learning.kmp_inputs`` fits these joints and chooses each joint's inputs.

All joints are handled at once with arrays of shape (n, N); the per-joint factorisations are
computed once at construction so that a query (500 Hz, inside the filter loop) costs one kernel
evaluation and one small batched matrix-vector product.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
import scipy.linalg
from scipy.special import logsumexp

from kvark_ros.core.estimation.compiled.residual import CompiledKMP, KMPKernelArrays
from kvark_ros.core.estimation.residual.common import (
    BATCH_CHUNK,
    VARIANCE_FLOOR,
    check_batch,
    check_training_data,
    single_threaded,
)
from kvark_ros.core.estimation.residual.files import (
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
    "INPUT_KINDS",
    "GMRReference",
    "KMPHyperparameters",
    "KMPKernelArrays",
    "KMPResidualModel",
    "default_hyperparameters",
    "fit_gmr_reference",
]

STEM = "kmp"
NPZ_NAME = f"{STEM}.npz"
YAML_NAME = f"{STEM}.yaml"

# Floor of the GMR variances relative to the variance of the joint's residual torque, with an
# absolute floor for a constant residual, so that Σ in eqs. 22-23 stays positive definite.
GMR_VARIANCE_FLOOR_REL = 1e-6
GMR_VARIANCE_FLOOR_ABS = 1e-12

# Jitter of the support points' unit-kernel matrix in the two-input far-field floor: k-means centres can nearly
# coincide, and 1e-6 keeps the factor finite at a cost of at most 1e-6·σ_f² in the floor.
FLOOR_JITTER = 1e-6
_REFERENCE_KEYS = ("s", "mu", "sigma2", "s2")
_HYPER_KEYS = ("length_scale", "sigma_f2", "lambda1", "lambda2", "length_scale2")
# Inputs of a joint's residual: q̇ alone (the paper), q̇ with q, q̇ with the gravity torque g(q).
INPUT_KINDS = ("qd", "qd_q", "qd_g")


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
    length_scale2: np.ndarray | None = None  # of the second input (rad or N·m); ones when unused

    def __post_init__(self) -> None:
        if self.length_scale2 is None:
            object.__setattr__(self, "length_scale2", np.ones(np.shape(self.length_scale)))
        freeze_positive_vectors(self, _HYPER_KEYS)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.length_scale.shape[0]


@dataclass(frozen=True)
class GMRReference:
    """GMR reference per joint: support inputs s (n, N) rad/s, means mu (n, N) N·m,
    variances sigma2 (n, N) N²·m², second support inputs s2 (n, N) (zeros for q̇-only joints).

    This is the probabilistic reference {s_i, μ_i, Σ_i} of eq. 18; sigma2 must be strictly
    positive so that Σ = diag(sigma2) is positive definite. Arrays are stored as read-only
    float64 copies.
    """

    s: np.ndarray
    mu: np.ndarray
    sigma2: np.ndarray
    s2: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.s2 is None:
            object.__setattr__(self, "s2", np.zeros(np.shape(self.s)))
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


def gmr_1d(x: np.ndarray, y: np.ndarray, s: np.ndarray, n_components: int,
           seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Fit a GMM to (x, y) (T,) and condition it at inputs s (N,); return mean, variance (N,).

    The data are standardised before EM (velocity and torque scales differ by orders of
    magnitude) and the result is mapped back to physical units.
    """
    from kvark_ros.core.estimation.residual.gmm import fit_mixture      # fitting only: loading a model needs no sklearn
    x_mean, x_std = x.mean(), x.std()
    y_mean, y_std = y.mean(), y.std()
    if y_std == 0.0:
        y_std = 1.0
    data = np.column_stack(((x - x_mean) / x_std, (y - y_mean) / y_std))
    gmm = fit_mixture(data, n_components, seed)
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
        mu[j], sigma2[j] = gmr_1d(qd[:, j], tau_r[:, j], s[j], n_components, seed)
    return GMRReference(s=s, mu=mu, sigma2=sigma2)


class KMPResidualModel:
    """Vectorised across joints; all factors precomputed at construction so predict() is
    one kernel evaluation and two small products per joint (it runs at 500 Hz in a filter loop).

    Kernel (eq. 21): k(s, s') = sigma_f2 · exp(−(s − s')² / (2 length_scale²)); the paper's
    `l` plays the role of length_scale². A joint with a second input z (``inputs`` ``qd_q`` or
    ``qd_g``) multiplies it by exp(−(z − s2)² / (2 length_scale2²)) (docs/method.md §3.7). With K_j
    the Gram matrix of joint j (eq. 19) and Σ_j = diag(sigma2_j) (eq. 18):
        mean     μ_*  = k_*ᵀ (K + λ1 Σ)⁻¹ μ                              (eq. 22)
        variance Σ_*  = (N/λ2) (k_** − k_*ᵀ (K + λ2 Σ)⁻¹ k_*), k_** = sigma_f2  (eq. 23)
    Far from the support points the mean tends to 0 and the variance to N·sigma_f2/λ2. Near
    them the variance grows with the GMR variance (heteroscedastic) but is not equal to it:
    N/λ2 scales it, so the filter's covariance matching, not this model, fixes its absolute
    level.

    Attributes: reference (GMRReference), hyper (KMPHyperparameters), inputs (one of
    ``INPUT_KINDS`` per joint), needs (the extra inputs ``predict`` must be given: a subset of
    {"q", "g"}), metadata (dict, written to and read from kmp.yaml).
    """

    def __init__(self, reference: GMRReference, hyper: KMPHyperparameters,
                 metadata: Mapping[str, Any] | None = None, inputs: tuple[str, ...] | None = None) -> None:
        if reference.s.shape[0] != hyper.n_joints:
            raise ResidualModelError(
                f"reference has {reference.s.shape[0]} joints, hyperparameters have "
                f"{hyper.n_joints}")
        n, n_sup = reference.s.shape
        inputs = tuple(inputs) if inputs is not None else ("qd",) * n
        if len(inputs) != n or not set(inputs) <= set(INPUT_KINDS):
            raise ResidualModelError(f"inputs must name one of {list(INPUT_KINDS)} per joint ({n}), got {list(inputs)}")
        self.reference = reference
        self.hyper = hyper
        self.inputs = inputs
        self.needs = frozenset(kind[3:] for kind in inputs if kind != "qd")
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._s = reference.s
        self._s2 = reference.s2
        # Exponent factors of eq. 21, (n, 1); the paper's `l` plays the role of length_scale².
        self._neg_half_inv_ls2 = (-0.5 / hyper.length_scale ** 2)[:, None]
        uses_z = np.array([kind != "qd" for kind in inputs])
        self._neg_half_inv_ls2_z = np.where(uses_z, -0.5 / hyper.length_scale2 ** 2, 0.0)[:, None]
        self._takes_q = np.array([kind == "qd_q" for kind in inputs], dtype=float)
        self._takes_g = np.array([kind == "qd_g" for kind in inputs], dtype=float)
        self._z = np.zeros(n)
        self._sigma_f2 = hyper.sigma_f2
        self._var_scale = n_sup / hyper.lambda2  # N / λ2 of eq. 23, (n,)
        # Rows 0 of _weights: sigma_f2 · (K + λ1 Σ)⁻¹ μ; rows 1..N: sigma_f2 · L⁻¹ with
        # L Lᵀ = K + λ2 Σ. sigma_f2 is folded in so that a query only needs the unscaled
        # kernel e = k_*/sigma_f2: mean = w0·e (eq. 22), k_*ᵀ(K+λ2Σ)⁻¹k_* = ‖W e‖²
        # with W the rows 1..N (eq. 23).
        self._weights = np.empty((n, n_sup + 1, n_sup))
        eye = np.eye(n_sup)
        for j in range(n):
            gram = hyper.sigma_f2[j] * self._unit_kernel(j, reference.s[j][:, None], reference.s2[j][:, None],
                                                         reference.s[j][None, :], reference.s2[j][None, :])  # eq. 19
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
        # Far-field floor of two-input joints (predict): L_K⁻¹ with L_K L_Kᵀ = K/σ_f² + jitter I, the GP
        # conditioned noise-free on all support points. On a q̇ grid the nearest point bounds it tightly; in a
        # plane k-means support points sit further apart than the length scales, and the nearest-point bound
        # would dwarf the model's real error (measured: σ 0.29 N·m where the error was 0.05).
        self._two_input = uses_z
        self._floor_weights = None
        if uses_z.any():
            self._floor_weights = np.zeros((n, n_sup, n_sup))
            for j in np.flatnonzero(uses_z):
                unit = self._unit_kernel(j, reference.s[j][:, None], reference.s2[j][:, None],
                                         reference.s[j][None, :], reference.s2[j][None, :])
                chol = scipy.linalg.cholesky(unit + FLOOR_JITTER * eye, lower=True)
                self._floor_weights[j] = scipy.linalg.solve_triangular(chol, eye, lower=True)
            self._floor_weights.setflags(write=False)

    def _far_field_floor(self, e: np.ndarray) -> np.ndarray:
        """σ_f²(1 − c²), c the largest unit kernel value of e (…, n, N), → (…, n); for two-input joints
        σ_f²(1 − ‖L_K⁻¹e‖²)."""
        nearest = e.max(axis=-1)
        floor = self._sigma_f2 * (1.0 - nearest * nearest)
        if self._floor_weights is not None:
            f = np.matmul(self._floor_weights, e[..., None])[..., 0]
            gp = self._sigma_f2 * np.maximum(1.0 - np.einsum("...j,...j->...", f, f), 0.0)
            floor = np.where(self._two_input, gp, floor)
        return floor

    def _unit_kernel(self, j: int, a: np.ndarray, a2: np.ndarray, b: np.ndarray, b2: np.ndarray) -> np.ndarray:
        """k/sigma_f2 of joint j between broadcastable inputs (q̇ a, b; second inputs a2, b2), eq. 21."""
        return np.exp(self._neg_half_inv_ls2[j, 0] * (a - b) ** 2 + self._neg_half_inv_ls2_z[j, 0] * (a2 - b2) ** 2)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self._s.shape[0]

    def kernel_arrays(self) -> KMPKernelArrays:
        """This model's precomputed factors, for a compiled ``predict`` (``KMPKernelArrays``: read-only views)."""
        return KMPKernelArrays(support=self._s, support2=self._s2, neg_half_inv_ls2=self._neg_half_inv_ls2[:, 0],
                               neg_half_inv_ls2_z=self._neg_half_inv_ls2_z[:, 0], sigma_f2=self._sigma_f2,
                               var_scale=self._var_scale, takes_q=self._takes_q, takes_g=self._takes_g,
                               two_input=self._two_input, weights=self._weights, floor_weights=self._floor_weights)

    @property
    def n_support(self) -> int:
        """Number of GMR support points N per joint."""
        return self._s.shape[1]

    def second_input(self, q: np.ndarray | None, g: np.ndarray | None) -> np.ndarray:
        """z (…, n): q_j for ``qd_q`` joints, g_j for ``qd_g`` joints, 0 otherwise; ValueError if one is needed and
        missing."""
        if not self.needs:
            return self._z
        if ("q" in self.needs and q is None) or ("g" in self.needs and g is None):
            raise ValueError(f"this residual model's inputs {list(self.inputs)} need "
                             f"{' and '.join(sorted(self.needs))} besides q̇")
        z = 0.0
        if "q" in self.needs:
            z = z + self._takes_q * q
        if "g" in self.needs:
            z = z + self._takes_g * g
        return z

    @functools.cached_property
    def compiled(self) -> CompiledKMP:
        """This model packed for the compiled step (``compiled.residual.CompiledKMP``), built when first asked."""
        return CompiledKMP(self.kernel_arrays(), VARIANCE_FLOOR)

    def predict(self, qd: np.ndarray, q: np.ndarray | None = None,
                g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """qd: (n,) one sample -> (mean (n,) N·m, variance (n,) N²·m²), compiled (``compiled.residual.kmp_predict``;
        ``predict_batch`` is the numpy form, to rounding the same).

        q (n,) rad and g (n,) N·m (the model's gravity torque) are needed when ``needs`` names them.
        qd in rad/s, assumed finite (the caller validates). The variance is floored twice:
        far from the training data (far-field floor) and at VARIANCE_FLOOR.

        Far-field floor (ours, not the paper's): away from the support points the KMP mean reverts
        to 0, but eq. 23's variance tends to (N/λ₂)·σ_f², which is small once λ₂ is calibrated on
        held-out data (measured: σ 0.018 N·m on a Panda wrist whose friction there is 0.25 N·m,
        which flagged contact in free motion). Out of its data the model knows no more than its
        prior, so var ≥ σ_f²(1 − c²) with c = maxᵢ k(q̇, sᵢ)/σ_f², the variance of a GP
        conditioned noise-free on the nearest support point alone: 0 on the data, σ_f² far away. A two-input joint
        conditions on all its support points instead (``_far_field_floor``).
        """
        if self.needs:
            self.second_input(q, g)                                  # a clear error when q or g is missing
        return self.compiled.predict(qd, q, g)

    def predict_batch(self, qd: np.ndarray, q: np.ndarray | None = None,
                      g: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """qd: (T, n) -> mean (T, n), variance (T, n), in numpy: what training, plots and metrics compute with.

        q, g (T, n) as in predict(). Same equations and floors as predict(), evaluated in chunks to bound memory.
        """
        qd = check_batch(qd, self.n_joints)
        z = np.broadcast_to(self.second_input(q, g), qd.shape)
        mean = np.empty_like(qd)
        var = np.empty_like(qd)
        for start in range(0, qd.shape[0], BATCH_CHUNK):
            rows = slice(start, start + BATCH_CHUNK)
            e, w = self._batch_kernel(qd[rows], z[rows])
            mean[rows] = w[:, :, 0]  # eq. 22
            quad = np.einsum("tja,tja->tj", w[:, :, 1:], w[:, :, 1:])
            var[rows] = np.maximum(self._var_scale * (self._sigma_f2 - quad),  # eq. 23
                                   self._far_field_floor(e))  # far-field floor
        np.maximum(var, VARIANCE_FLOOR, out=var)
        return mean, var

    def _batch_kernel(self, qd: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit kernel vectors e = k_*/σ_f² (t, n, N) of queries qd, z (t, n) (eq. 20) and w = W e (t, n, N+1)."""
        e = np.exp(self._neg_half_inv_ls2 * (qd[:, :, None] - self._s) ** 2
                   + self._neg_half_inv_ls2_z * (z[:, :, None] - self._s2) ** 2)
        return e, np.matmul(self._weights, e[..., None])[..., 0]

    @single_threaded
    def _whitened_eigen(self) -> tuple[np.ndarray, np.ndarray]:
        """Per joint, Λ (n, N) and σ_f² Vᵀ D (n, N, N) of D K D = V Λ Vᵀ, D = Σ^{-1/2} (``lambda2_sweep``)."""
        n, n_sup = self._s.shape
        eigenvalues = np.empty((n, n_sup))
        project = np.empty((n, n_sup, n_sup))
        for j in range(n):
            s, s2 = self._s[j], self._s2[j]
            gram = self._sigma_f2[j] * self._unit_kernel(j, s[:, None], s2[:, None], s[None, :], s2[None, :])  # eq. 19
            d = 1.0 / np.sqrt(self.reference.sigma2[j])
            eigenvalues[j], v = np.linalg.eigh(d[:, None] * gram * d[None, :])  # D K D = V Λ Vᵀ
            project[j] = self._sigma_f2[j] * v.T * d  # p = σ_f² Vᵀ D e = Vᵀ D k_*
        return eigenvalues, project

    def lambda2_sweep(self, qd: np.ndarray, q: np.ndarray | None, g: np.ndarray | None,
                      lambda2: np.ndarray) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """For λ₂ calibration (docs/method.md §3.5): chunk by chunk of the queries qd, q, g (T, n) as in predict_batch,
        the rows (a slice), the mean (t, n) and eq. 23's variance for every candidate ``lambda2`` (G,), (G, t, n), with
        this model's other hyperparameters and the same floors.

        One eigendecomposition per joint replaces a model per candidate: with D = Σ^{-1/2} and D K D = V Λ Vᵀ,
        (K + λ₂Σ)⁻¹ = D V (Λ + λ₂ I)⁻¹ Vᵀ D, so k_*ᵀ(K + λ₂Σ)⁻¹k_* = Σᵢ pᵢ²/(Λᵢ + λ₂) with p = Vᵀ D k_*: O(N²) per
        query, then O(N) per candidate. The mean (eq. 22) does not depend on λ₂.
        """
        qd = check_batch(qd, self.n_joints)
        z = np.broadcast_to(self.second_input(q, g), qd.shape)
        lambda2 = np.asarray(lambda2, dtype=np.float64)
        eigenvalues, project = self._whitened_eigen()
        inverse = 1.0 / (eigenvalues + lambda2[:, None, None])  # (Λ + λ₂ I)⁻¹, (G, n, N)
        var_scale = self.n_support / lambda2[:, None, None]  # N/λ₂ of eq. 23
        for start in range(0, qd.shape[0], BATCH_CHUNK):
            rows = slice(start, start + BATCH_CHUNK)
            e, w = self._batch_kernel(qd[rows], z[rows])
            p = np.matmul(project, e[..., None])[..., 0]  # (t, n, N)
            quad = np.matmul((p * p).transpose(1, 0, 2), inverse.transpose(1, 2, 0)).T  # Σᵢ pᵢ²/(Λᵢ + λ₂), (G, t, n)
            var = np.maximum(var_scale * (self._sigma_f2 - quad), self._far_field_floor(e))  # eq. 23, floor
            yield rows, w[:, :, 0], np.maximum(var, VARIANCE_FLOOR)  # eq. 22

    def with_hyperparameters(self, hyper: KMPHyperparameters) -> KMPResidualModel:
        """The same reference, inputs and metadata with other hyperparameters (λ₂ calibration)."""
        return KMPResidualModel(self.reference, hyper, self.metadata, self.inputs)

    @classmethod
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, hyper: KMPHyperparameters,
            n_components: int = 10, n_support: int = 30, seed: int = 0) -> KMPResidualModel:
        """Fit GMM/GMR to qd (T, n) rad/s and tau_r (T, n) N·m, then build the q̇-only KMP model."""
        reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                      n_support=n_support, seed=seed)
        return cls(reference, hyper)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/kmp.npz and directory/kmp.yaml, each atomically.

        kmp.npz holds the arrays s, mu, sigma2, s2, length_scale, sigma_f2, lambda1, lambda2,
        length_scale2; kmp.yaml the format version, n_joints, n_support, the inputs per joint, the
        hyperparameters as lists and `metadata`. Each is written to a temp file in the same directory,
        then os.replace'd.

        metadata defaults to self.metadata and must contain plain YAML types only. The npz is
        written first, so a crash in between leaves the previous kmp.yaml.
        """
        arrays = {key: getattr(self.reference, key) for key in _REFERENCE_KEYS}
        arrays.update({key: getattr(self.hyper, key) for key in _HYPER_KEYS})
        header = {
            "format_version": FORMAT_VERSION,
            "n_joints": self.n_joints,
            "n_support": self.n_support,
            "inputs": list(self.inputs),
            "hyperparameters": {key: getattr(self.hyper, key).tolist() for key in _HYPER_KEYS},
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, STEM, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> KMPResidualModel:
        """Load a model written by save(); the npz is read with np.load(..., allow_pickle=False).

        Missing file, missing array, wrong shape, non-finite values, an unknown format version,
        unknown inputs or hyperparameters in kmp.yaml that disagree with kmp.npz -> ResidualModelError
        (a ValueError) whose message names the file and the problem. A file without ``inputs`` (written
        before joints could take a second input) is a q̇-only model without s2 and length_scale2.
        """
        directory = Path(directory)
        yaml_path, npz_path = directory / YAML_NAME, directory / NPZ_NAME
        header = read_model_header(yaml_path, ("n_support",))
        inputs = header.get("inputs")
        reference_keys, hyper_keys = _REFERENCE_KEYS, _HYPER_KEYS
        if inputs is None:
            reference_keys, hyper_keys = _REFERENCE_KEYS[:3], _HYPER_KEYS[:4]
        elif not isinstance(inputs, list) or len(inputs) != header["n_joints"] or not set(inputs) <= set(INPUT_KINDS):
            raise ResidualModelError(f"{yaml_path}: inputs must list one of {list(INPUT_KINDS)} per joint, "
                                     f"got {inputs!r}")
        shapes = {key: (header["n_joints"], header["n_support"]) for key in reference_keys}
        shapes.update({key: (header["n_joints"],) for key in hyper_keys})
        arrays = read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, hyper_keys)
        try:
            reference = GMRReference(**{key: arrays[key] for key in reference_keys})
            hyper = KMPHyperparameters(**{key: arrays[key] for key in hyper_keys})
            return cls(reference, hyper, metadata=header["metadata"], inputs=None if inputs is None else tuple(inputs))
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc
