"""Gaussian-process residual models of the baselines (paper v2 §V-B): GMR-GP and sparse GP (GPADKF).

Like the KMP model (kvark_ros.core.estimation.residual.kmp) each maps, per joint j, the joint velocity q̇_j
(rad/s) to the residual torque τ_r,j = τ_m,j − τ_EL,j (N·m) with a predictive variance (N²·m²).

Predictive variances. Both GP models return the variance of a *new residual observation*:
latent (function) variance + the fitted noise variance σn². Far from the data it tends to
σf² + σn², near the data to about σn² (plus the latent uncertainty). This is the quantity the
filter's Σ_* stands for (the spread of τ_r about the predicted mean), as the GMR variance in KMP.

ARD. The input per joint is one scalar (q̇_j), so the paper's ARD squared-exponential kernel
has a single length scale per joint here; the GP models are one-dimensional GPs per joint.

``hyperparameters_from_gp`` gives the KMP its length scale and λ₁ from the same GP fit that
GMR-GP uses (paper v2 §V-B: "length-scale obtained using ARD-based kernel hyperparameter
optimization", λ₁ "selected from the optimized likelihood/noise level").
"""

from __future__ import annotations

import os
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.linalg

from kvark_ros.core.estimation.residual.common import (
    BATCH_CHUNK,
    VARIANCE_FLOOR,
    check_batch,
    map_joints,
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
from kvark_ros.core.estimation.residual.kmp import GMRReference, KMPHyperparameters, fit_gmr_reference

__all__ = [
    "GMRGPResidualModel",
    "GPHyperparameters",
    "hyperparameters_from_gp",
]

# Jitter added to the diagonal of kernel matrices, relative to σf²: keeps the Cholesky
# factorisations of K_mm (inducing points) and K + σn²/m I well defined when points are
# closer than the length scale. 1e-8·σf² changes predictions by ≪ 1e-6 N·m.
KERNEL_JITTER_REL = 1e-8
# Bounds of the hyperparameter search, in units scaled so that the targets have unit
# RMS: amplitude σf² and noise σn² (the noise bound is low enough for noise-free data).
_AMPLITUDE_BOUNDS = (1e-4, 1e4)
_NOISE_BOUNDS = (1e-8, 1e1)
# Upper bound of the length scale, relative to the velocity range of the joint.
MAX_LENGTH_SCALE_REL = 10.0
# Lower bound of the sparse GP's length scale, relative to the velocity range (the raw data
# can resolve short scales; this only keeps the optimiser away from degenerate values).
MIN_LENGTH_SCALE_REL = 1e-3

GP_HYPER_KEYS = ("length_scale", "sigma_f2", "noise_var")


# --------------------------------------------------------------------------------------------
# Shared GP pieces
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GPHyperparameters:
    """Per-joint SE-kernel GP hyperparameters, arrays of shape (n,), strictly positive.

    k(a, b) = sigma_f2 · exp(−(a − b)² / (2 length_scale²)); observations carry independent
    Gaussian noise of variance noise_var. Units: length_scale rad/s, sigma_f2 and noise_var
    N²·m². Stored as read-only float64 copies.
    """

    length_scale: np.ndarray
    sigma_f2: np.ndarray
    noise_var: np.ndarray

    def __post_init__(self) -> None:
        freeze_positive_vectors(self, GP_HYPER_KEYS)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.length_scale.shape[0]

    def as_dict(self) -> dict[str, list[float]]:
        """Plain lists, for YAML headers and reports."""
        return {key: getattr(self, key).tolist() for key in GP_HYPER_KEYS}


@dataclass(frozen=True)
class SEFit:
    """Result of one marginal-likelihood fit of an SE + white-noise GP to 1-D data."""

    length_scale: float
    sigma_f2: float
    noise_var: float
    log_marginal_likelihood: float  # of the scaled targets, for comparison between restarts
    length_scale_at_lower_bound: bool


def fit_se_gp(x: np.ndarray, y: np.ndarray, length_scale_bounds: tuple[float, float],
              seed: int, n_restarts: int = 2) -> SEFit:
    """Fit σf², length scale and σn² of a zero-mean SE GP to (x, y) by maximum marginal
    likelihood (``gp_fit.fit_gp``: L-BFGS-B with restarts, as sklearn's GaussianProcessRegressor).

    The targets are divided by their RMS for the search (so the fixed amplitude and noise
    bounds are relative) and the result is mapped back to physical units. The prior mean is
    zero, as in KMP: far from the data the prediction returns to 0. A hyperparameter at its bound
    (typically the length scale at the support spacing) is expected and reported through
    length_scale_at_lower_bound.
    """
    scale = float(np.sqrt(np.mean(y ** 2)))
    if not scale > 0.0:
        scale = 1.0
    low, high = length_scale_bounds
    start = float(np.clip(0.1 * (x.max() - x.min()), low, high))
    theta0 = np.log([1.0, start, 1e-2])                      # σf², ℓ, σn² in the scaled units
    bounds = np.log([_AMPLITUDE_BOUNDS, (low, high), _NOISE_BOUNDS])
    from kvark_ros.core.estimation.residual.gp_fit import fit_gp    # training only: scipy.optimize is not the node's
    fit = fit_gp(x[:, None], y / scale, theta0, bounds, n_restarts, seed)
    length_scale = float(fit.length_scale[0])
    return SEFit(length_scale=length_scale,
                 sigma_f2=fit.sigma_f2 * scale ** 2,
                 noise_var=fit.noise_var * scale ** 2,
                 log_marginal_likelihood=fit.log_marginal_likelihood,
                 length_scale_at_lower_bound=bool(length_scale <= low * (1.0 + 1e-6)))


class KernelPredictor:
    """Shared hot path of the two GP models.

    Per joint j the prediction at q̇ is, with e = exp(−(q̇ − c)²/(2ℓ²)) the unscaled kernel
    vector against the centres c (n, M) and W (n, R, M) the precomputed weights:
        w = W e,  mean = w[0],
        var = prior_var − ‖w[1 : 1+M]‖² + ‖w[1+M :]‖²      (the last block may be empty).
    """

    _centers: np.ndarray  # (n, M) rad/s
    _neg_half_inv_ls2: np.ndarray  # (n, 1)
    _weights: np.ndarray  # (n, R, M)
    _prior_var: np.ndarray  # (n,) σf² + σn²
    _n_minus: int  # M

    def _setup_predictor(self, centers: np.ndarray, hyper: GPHyperparameters,
                         weights: np.ndarray) -> None:
        self._centers = centers
        self._neg_half_inv_ls2 = (-0.5 / hyper.length_scale ** 2)[:, None]
        self._prior_var = hyper.sigma_f2 + hyper.noise_var
        self._n_minus = centers.shape[1]
        self._added = weights.shape[1] > 1 + self._n_minus
        weights.setflags(write=False)
        self._weights = weights

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self._centers.shape[0]

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (n,) one sample, rad/s -> (mean (n,) N·m, variance (n,) N²·m²).

        Hot path (500 Hz): no Python loop over joints, a few small temporaries. qd is assumed
        finite (the caller validates). Variance = latent + noise variance, floored at
        VARIANCE_FLOOR.
        """
        e = qd[:, None] - self._centers
        np.square(e, out=e)
        np.multiply(e, self._neg_half_inv_ls2, out=e)
        np.exp(e, out=e)
        w = np.matmul(self._weights, e[:, :, None])[:, :, 0]  # (n, R)
        m = self._n_minus
        a = w[:, 1:1 + m]
        var = self._prior_var - np.einsum("ij,ij->i", a, a)
        if self._added:
            b = w[:, 1 + m:]
            var += np.einsum("ij,ij->i", b, b)
        np.maximum(var, VARIANCE_FLOOR, out=var)
        return w[:, 0], var

    def predict_batch(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (T, n) -> mean (T, n), variance (T, n); same equations as predict(), chunked."""
        qd = check_batch(qd, self.n_joints)
        mean = np.empty_like(qd)
        var = np.empty_like(qd)
        m = self._n_minus
        for start in range(0, qd.shape[0], BATCH_CHUNK):
            rows = slice(start, start + BATCH_CHUNK)
            e = np.exp(self._neg_half_inv_ls2 * (qd[rows, :, None] - self._centers) ** 2)
            w = np.matmul(self._weights, e[..., None])[..., 0]  # (t, n, R)
            mean[rows] = w[:, :, 0]
            a = w[:, :, 1:1 + m]
            v = self._prior_var - np.einsum("tja,tja->tj", a, a)
            if self._added:
                b = w[:, :, 1 + m:]
                v += np.einsum("tja,tja->tj", b, b)
            var[rows] = v
        np.maximum(var, VARIANCE_FLOOR, out=var)
        return mean, var


def se_gram(a: np.ndarray, b: np.ndarray, length_scale: float, sigma_f2: float) -> np.ndarray:
    """SE kernel matrix between 1-D inputs a (A,) and b (B,)."""
    return sigma_f2 * np.exp(-0.5 * ((a[:, None] - b[None, :]) / length_scale) ** 2)


def cholesky(matrix: np.ndarray, what: str) -> np.ndarray:
    """Lower Cholesky factor of ``matrix``; ResidualModelError naming ``what`` if it is not positive definite."""
    try:
        return scipy.linalg.cholesky(matrix, lower=True)
    except np.linalg.LinAlgError as exc:
        raise ResidualModelError(f"{what} is not numerically positive definite ({exc})") from exc


# --------------------------------------------------------------------------------------------
# GMR-GP
# --------------------------------------------------------------------------------------------


def gmr_sample_noise(n: int, n_support: int, samples_per_support: int, seed: int) -> np.ndarray:
    """The standard normal draws ε (n, N, m) of the GMR samples y = μᵢ + σᵢ ε, joint after joint from one stream
    seeded by ``seed``: drawn up front, each joint's fit can run anywhere and draw what it drew in turn."""
    if samples_per_support < 1:
        raise ValueError(f"samples_per_support must be >= 1, got {samples_per_support}")
    return np.random.default_rng(seed).standard_normal((n, n_support, samples_per_support))


def fit_gp_on_joint_samples(s: np.ndarray, mu: np.ndarray, sigma2: np.ndarray, noise: np.ndarray,
                            seed: int) -> tuple[SEFit, np.ndarray]:
    """One joint of ``_fit_gp_on_gmr_samples``: samples y = μᵢ + σᵢ ε (ε: noise (N, m)) at the support points s (N,)
    rad/s of a GMR reference (μ, σ² (N,)), the SE GP fitted to them and their means ȳ (N,)."""
    y = mu[:, None] + np.sqrt(sigma2)[:, None] * noise
    spacing = np.max(np.diff(s))
    span = s[-1] - s[0]
    fit = fit_se_gp(np.repeat(s, noise.shape[1]), y.ravel(),
                    (spacing, max(MAX_LENGTH_SCALE_REL * span, 2.0 * spacing)), seed=seed)
    return fit, y.mean(axis=1)


def _fit_gp_on_gmr_samples(reference: GMRReference, samples_per_support: int, seed: int,
                           executor: Executor | None = None) -> tuple[GPHyperparameters, np.ndarray, list[dict]]:
    """Draw `samples_per_support` values y ~ N(μ_i, σ²_i) at every support point s_i of every
    joint and fit the SE GP hyperparameters to them by marginal likelihood, each joint in ``executor``'s workers
    (``map_joints``) or here.

    The length scale is bounded below by the support spacing (inside the optimisation, so σf²
    and σn² are fitted for the length scale that is used): between support points no data
    constrain a shorter scale, and with a scale below the spacing the GP/KMP mean sags towards
    0 and the variance ripples between support points.

    Returns the hyperparameters, the sample means ȳ (n, N) and per-joint fit info.
    """
    n, n_sup = reference.s.shape
    noise = gmr_sample_noise(n, n_sup, samples_per_support, seed)
    results = map_joints(fit_gp_on_joint_samples, [(reference.s[j], reference.mu[j], reference.sigma2[j], noise[j],
                                                    seed + j) for j in range(n)], executor)
    fits = [fit for fit, _ in results]
    y_mean = np.array([means for _, means in results])
    hyper = GPHyperparameters(length_scale=[f.length_scale for f in fits],
                              sigma_f2=[f.sigma_f2 for f in fits],
                              noise_var=[f.noise_var for f in fits])
    info = [{"log_marginal_likelihood": f.log_marginal_likelihood,
             "length_scale_at_spacing": f.length_scale_at_lower_bound} for f in fits]
    return hyper, y_mean, info


class GMRGPResidualModel(KernelPredictor):
    """GMR-GP (paper v2 §V-B): exact GP trained on data sampled from the GMR reference.

    Training: the GMR reference {s_i, μ_i, σ²_i} (fit_gmr_reference, the same N support points
    as KMP) is sampled m = samples_per_support times per support point, y_ik ~ N(μ_i, σ²_i);
    a zero-mean SE GP with white noise is fitted to the N·m points by marginal likelihood
    (``gp_fit.fit_gp``). Because the m samples at s_i share their input, the exact GP posterior on them
    equals the posterior of one observation ȳ_i (their mean) per support point with noise
    σn²/m (the likelihood ∏_k N(y_ik; f_i, σn²) ∝ N(ȳ_i; f_i, σn²/m) in f), so the model keeps
    only s (n, N) and ȳ (n, N) and precomputes, with L Lᵀ = K + (σn²/m) I:
        α = (K + σn²/m I)⁻¹ ȳ,     L⁻¹.
    Prediction: mean = k_*ᵀ α; variance = σf² − ‖L⁻¹ k_*‖² (latent) + σn² (noise), i.e. the
    variance of a new residual observation. Far from the data: mean → 0, variance → σf² + σn².

    Attributes: support (n, N), targets ȳ (n, N), hyper (GPHyperparameters),
    samples_per_support m, reference (the GMRReference it was sampled from, or None),
    metadata (dict, saved in gmr_gp.yaml).
    """

    name = "gmr_gp"
    NPZ_NAME = "gmr_gp.npz"
    YAML_NAME = "gmr_gp.yaml"

    @single_threaded
    def __init__(self, support: np.ndarray, targets: np.ndarray, hyper: GPHyperparameters,
                 samples_per_support: int = 1, reference: GMRReference | None = None,
                 metadata: Mapping[str, Any] | None = None) -> None:
        support = frozen_float_array("support", support, ndim=2)
        targets = frozen_float_array("targets", targets, ndim=2)
        if support.shape != targets.shape or support.shape[1] < 1:
            raise ResidualModelError(
                f"support {support.shape} and targets {targets.shape} must have the same "
                "shape (n, N), N >= 1")
        if support.shape[0] != hyper.n_joints:
            raise ResidualModelError(
                f"support has {support.shape[0]} joints, hyperparameters have {hyper.n_joints}")
        if (isinstance(samples_per_support, bool) or not isinstance(samples_per_support, (int, np.integer))
                or samples_per_support < 1):
            raise ResidualModelError(
                f"samples_per_support must be a positive integer, got {samples_per_support!r}")
        if reference is not None and reference.s.shape != support.shape:
            raise ResidualModelError(
                f"reference shape {reference.s.shape} differs from support {support.shape}")
        self.support = support
        self.targets = targets
        self.hyper = hyper
        self.samples_per_support = int(samples_per_support)
        self.reference = reference
        self.metadata: dict[str, Any] = dict(metadata or {})
        n, n_sup = support.shape
        # Row 0: σf² α; rows 1..N: σf² L⁻¹ (σf² folded in: the query uses e = k_*/σf²).
        weights = np.empty((n, n_sup + 1, n_sup))
        eye = np.eye(n_sup)
        for j in range(n):
            sf2 = hyper.sigma_f2[j]
            gram = se_gram(support[j], support[j], hyper.length_scale[j], sf2)
            gram[np.diag_indices(n_sup)] += (hyper.noise_var[j] / self.samples_per_support
                                             + KERNEL_JITTER_REL * sf2)
            chol = cholesky(gram, f"joint {j}: K + σn²/m I")
            chol_inv = scipy.linalg.solve_triangular(chol, eye, lower=True)
            alpha = chol_inv.T @ (chol_inv @ targets[j])
            weights[j, 0] = sf2 * alpha
            weights[j, 1:] = sf2 * chol_inv
        self._setup_predictor(support, hyper, weights)

    @property
    def n_support(self) -> int:
        """Number of GMR support points N per joint."""
        return self.support.shape[1]

    @classmethod
    @single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, n_components: int = 10,
            n_support: int = 30, samples_per_support: int = 10, seed: int = 0,
            reference: GMRReference | None = None, executor: Executor | None = None) -> GMRGPResidualModel:
        """Fit GMM/GMR to qd (T, n) rad/s and tau_r (T, n) N·m, sample the reference
        `samples_per_support` times per support point and fit the GP to the samples (each joint's GP in
        ``executor``'s workers when given, ``map_joints``).

        reference: an already fitted GMR reference (e.g. the KMP's), to skip the GMM fit;
        then qd, tau_r are not used and may be None.
        """
        if reference is None:
            reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                          n_support=n_support, seed=seed)
        hyper, y_mean, info = _fit_gp_on_gmr_samples(reference, samples_per_support, seed, executor)
        metadata = {"fit": {"n_components": n_components if qd is not None else None,
                            "samples_per_support": samples_per_support, "seed": seed,
                            "joints": info}}
        return cls(reference.s, y_mean, hyper, samples_per_support, reference, metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/gmr_gp.npz (support, targets, the hyperparameters and, if known,
        the GMR reference mu/sigma2) and directory/gmr_gp.yaml, each atomically."""
        arrays = {"support": self.support, "targets": self.targets}
        arrays.update({key: getattr(self.hyper, key) for key in GP_HYPER_KEYS})
        if self.reference is not None:
            arrays.update(reference_mu=self.reference.mu, reference_sigma2=self.reference.sigma2)
        header = {
            "format_version": FORMAT_VERSION,
            "model": self.name,
            "n_joints": self.n_joints,
            "n_support": self.n_support,
            "samples_per_support": self.samples_per_support,
            "has_reference": self.reference is not None,
            "variance": "latent + noise (variance of a new residual observation)",
            "hyperparameters": self.hyper.as_dict(),
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, self.name, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> GMRGPResidualModel:
        """Load a model written by save(); np.load(..., allow_pickle=False). Any problem ->
        ResidualModelError naming the file."""
        directory = Path(directory)
        yaml_path, npz_path = directory / cls.YAML_NAME, directory / cls.NPZ_NAME
        header = read_model_header(yaml_path, ("n_support", "samples_per_support"), cls.name)
        n, n_sup = header["n_joints"], header["n_support"]
        shapes: dict[str, tuple[int, ...]] = {"support": (n, n_sup), "targets": (n, n_sup)}
        shapes.update({key: (n,) for key in GP_HYPER_KEYS})
        has_reference = header.get("has_reference") is True
        if has_reference:
            shapes.update(reference_mu=(n, n_sup), reference_sigma2=(n, n_sup))
        arrays = read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, GP_HYPER_KEYS)
        try:
            hyper = GPHyperparameters(**{key: arrays[key] for key in GP_HYPER_KEYS})
            reference = (GMRReference(s=arrays["support"], mu=arrays["reference_mu"],
                                      sigma2=arrays["reference_sigma2"]) if has_reference else None)
            return cls(arrays["support"], arrays["targets"], hyper, header["samples_per_support"],
                       reference, metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc


@single_threaded
def hyperparameters_from_gp(qd: np.ndarray, tau_r: np.ndarray, n_support: int = 30,
                            seed: int = 0, *, n_components: int = 10,
                            samples_per_support: int = 10,
                            reference: GMRReference | None = None,
                            executor: Executor | None = None) -> KMPHyperparameters:
    """KMP hyperparameters from a GP marginal-likelihood fit on GMR-sampled data (paper v2 §V-B).

    The GP is the one GMR-GP uses (same reference, samples, seed, so the two models share
    their length scale and noise level, as in the paper):
    - length_scale: the fitted SE length scale, bounded below by the support spacing
      (max q̇ − min q̇)/(N − 1) inside the fit (KMP's variance ripples when the spacing exceeds
      the length scale, see kmp.default_hyperparameters);
    - sigma_f2: the fitted kernel amplitude;
    - lambda1: the fitted noise level, shared with GMR-GP so that the two means agree. GMR-GP's
      posterior mean is k_*ᵀ(K + (σn²/m) I)⁻¹ ȳ (m samples per support point, see
      GMRGPResidualModel); KMP's (eq. 22) is k_*ᵀ(K + λ₁Σ)⁻¹ μ. Equating the regularisers on
      average, λ₁ mean_i(σ²_i) = σn²/m, gives λ₁ = σn² / (m · mean_i(σ²_i)); with that KMP is
      GMR-GP with the sample means ȳ_i replaced by the exact GMR means μ_i. Since σn² ≈ the
      GMR spread when the GP fits the samples, λ₁ ≈ 1/m; it is larger (smoother mean) when the
      length-scale bound makes the GP call some structure noise. (The other reading, λ₁ =
      σn²/mean σ², ≈ 1, treats each μ_i as one noisy sample; it smooths the friction step
      more: in our tanh(20 q̇) check the KMP RMSE was about 1.5 × larger.)
    - lambda2: the default scaling N·sigma_f2 (far-field variance N·σf²/λ₂ = 1 N²·m²); the
      filter calibration step sets the variance level later.

    qd, tau_r: (T, n) rad/s, N·m (ignored when `reference` is given). Each joint's GP is fitted in ``executor``'s
    workers when given (``map_joints``).
    """
    if reference is None:
        reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                      n_support=n_support, seed=seed)
    n, n_sup = reference.s.shape
    noise = gmr_sample_noise(n, n_sup, samples_per_support, seed)
    values = map_joints(kmp_hyperparameters_of_joint, [(reference.s[j], reference.mu[j], reference.sigma2[j],
                                                        noise[j], seed + j) for j in range(n)], executor)
    length_scale, sigma_f2, lambda1 = (np.array(column) for column in zip(*values))
    return KMPHyperparameters(length_scale=length_scale, sigma_f2=sigma_f2,
                              lambda1=lambda1, lambda2=n_sup * sigma_f2)


def kmp_hyperparameters_of_joint(s: np.ndarray, mu: np.ndarray, sigma2: np.ndarray, noise: np.ndarray,
                                 seed: int) -> tuple[float, float, float]:
    """One joint of ``hyperparameters_from_gp``: (length scale, σ_f², λ₁) from the GP on the samples μᵢ + σᵢ ε of its
    GMR reference (s, μ, σ² (N,); ε: noise (N, m))."""
    fit, _ = fit_gp_on_joint_samples(s, mu, sigma2, noise, seed)
    length_scale = max(fit.length_scale, float(np.max(np.diff(s))))   # not below the support spacing
    return length_scale, fit.sigma_f2, fit.noise_var / (noise.shape[1] * np.mean(sigma2))   # λ₁ = σn²/(m mean σ²)


# --------------------------------------------------------------------------------------------
# Sparse GP (GPADKF)
# --------------------------------------------------------------------------------------------
