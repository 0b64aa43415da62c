"""Learned residual-torque baselines of paper v2 §V-B: GMR-GP, sparse GP (GPADKF), MLP (NNADKF).

Like the KMP model (kvark_ros.core.residual_model) each maps, per joint j, the joint velocity
q̇_j (rad/s) to the residual torque τ_r,j = τ_m,j − τ_EL,j (N·m) with a predictive variance
(N²·m²), and has the same interface: ``n_joints``, ``predict(qd (n,)) -> (mean (n,), var (n,))``
(hot path: vectorised across joints, all factors precomputed, no sklearn call),
``predict_batch(qd (T, n))``, the ``fit`` classmethod, and ``save(directory)`` /
``load(directory)`` writing their own file pair in the model directory, atomically, with no
object serialisation (arrays in .npz read with allow_pickle=False, a small YAML header beside them).

=====================  ==========  ============================================================
class                  files       model
=====================  ==========  ============================================================
GMRGPResidualModel     gmr_gp.*    exact GP (SE kernel) on samples drawn from the GMR reference
SparseGPResidualModel  sparse_gp.* FITC (default) or DTC sparse GP, 50 inducing points, raw data
MLPResidualModel       mlp.*       per-joint MLP (2 × 30 tanh), static variance
=====================  ==========  ============================================================

Predictive variances. Both GP models return the variance of a *new residual observation*:
latent (function) variance + the fitted noise variance σn². Far from the data it tends to
σf² + σn², near the data to about σn² (plus the latent uncertainty). This is the quantity the
filter's Σ_* stands for (the spread of τ_r about the predicted mean), as the GMR variance in KMP.
The MLP returns a constant per joint: the mean squared training residual (paper: "static
covariance").

ARD. The input per joint is one scalar (q̇_j), so the paper's ARD squared-exponential kernel
has a single length scale per joint here; the GP models are one-dimensional GPs per joint.

``hyperparameters_from_gp`` gives the KMP its length scale and λ₁ from the same GP fit that
GMR-GP uses (paper v2 §V-B: "length-scale obtained using ARD-based kernel hyperparameter
optimization", λ₁ "selected from the optimized likelihood/noise level").
"""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import scipy.linalg
import scipy.special
from sklearn.cluster import KMeans
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
from sklearn.neural_network import MLPRegressor
from threadpoolctl import threadpool_limits

from kvark_ros.core.residual_model import (
    VARIANCE_FLOOR,
    GMRReference,
    KMPHyperparameters,
    ResidualModelError,
    _check_training_data,
    _frozen_float_array,
    freeze_positive_vectors,
    check_listed_values,
    read_model_header,
    _read_arrays,
    fit_gmr_reference,
    save_model_pair,
)

__all__ = [
    "BASELINE_MODELS",
    "GMRGPResidualModel",
    "GPHyperparameters",
    "MLPResidualModel",
    "SparseGPResidualModel",
    "hyperparameters_from_gp",
]

FORMAT_VERSION = 1

# Jitter added to the diagonal of kernel matrices, relative to σf²: keeps the Cholesky
# factorisations of K_mm (inducing points) and K + σn²/m I well defined when points are
# closer than the length scale. 1e-8·σf² changes predictions by ≪ 1e-6 N·m.
KERNEL_JITTER_REL = 1e-8
# Bounds of the sklearn hyperparameter search, in units scaled so that the targets have unit
# RMS: amplitude σf² and noise σn² (the noise bound is low enough for noise-free data).
_AMPLITUDE_BOUNDS = (1e-4, 1e4)
_NOISE_BOUNDS = (1e-8, 1e1)
# Upper bound of the length scale, relative to the velocity range of the joint.
_MAX_LENGTH_SCALE_REL = 10.0
# Lower bound of the sparse GP's length scale, relative to the velocity range (the raw data
# can resolve short scales; this only keeps the optimiser away from degenerate values).
_MIN_LENGTH_SCALE_REL = 1e-3
# Query rows per chunk in predict_batch: bounds the (chunk, n, M) temporaries to a few MB.
_BATCH_CHUNK = 4096

_GP_HYPER_KEYS = ("length_scale", "sigma_f2", "noise_var")


def _single_threaded(func: Callable) -> Callable:
    """Run `func` (a fit, or a constructor that factorises) with BLAS/OpenMP limited to one
    thread.

    Constructors too: the factors then do not depend on the caller's thread pool, so a model
    rebuilt by load() predicts bit for bit what the fitted model predicted.

    The matrices here are small (≤ 1000², 50 × T, 30 × 30): threading gains little, and on a
    loaded machine OpenBLAS's spinning threads made the fits 5-8 × slower (measured: GMR-GP fit
    25 s with the default pool versus 3.4 s single-threaded while other jobs ran).
    """
    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with threadpool_limits(limits=1):
            return func(*args, **kwargs)
    return wrapper


# --------------------------------------------------------------------------------------------
# Shared pieces
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
        freeze_positive_vectors(self, _GP_HYPER_KEYS)

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.length_scale.shape[0]

    def as_dict(self) -> dict[str, list[float]]:
        """Plain lists, for YAML headers and reports."""
        return {key: getattr(self, key).tolist() for key in _GP_HYPER_KEYS}


@dataclass(frozen=True)
class _SEFit:
    """Result of one marginal-likelihood fit of an SE + white-noise GP to 1-D data."""

    length_scale: float
    sigma_f2: float
    noise_var: float
    log_marginal_likelihood: float  # of the scaled targets, for comparison between restarts
    length_scale_at_lower_bound: bool


def _fit_se_gp(x: np.ndarray, y: np.ndarray, length_scale_bounds: tuple[float, float],
               seed: int, n_restarts: int = 2) -> _SEFit:
    """Fit σf², length scale and σn² of a zero-mean SE GP to (x, y) by maximum marginal
    likelihood (sklearn GaussianProcessRegressor, L-BFGS-B with restarts).

    The targets are divided by their RMS for the search (so the fixed amplitude and noise
    bounds are relative) and the result is mapped back to physical units. The prior mean is
    zero, as in KMP: far from the data the prediction returns to 0.
    """
    scale = float(np.sqrt(np.mean(y ** 2)))
    if not scale > 0.0:
        scale = 1.0
    low, high = length_scale_bounds
    start = float(np.clip(0.1 * (x.max() - x.min()), low, high))
    kernel = (ConstantKernel(1.0, _AMPLITUDE_BOUNDS) * RBF(start, (low, high))
              + WhiteKernel(1e-2, _NOISE_BOUNDS))
    gpr = GaussianProcessRegressor(kernel=kernel, alpha=1e-10, normalize_y=False,
                                   n_restarts_optimizer=n_restarts, random_state=seed)
    with warnings.catch_warnings():
        # A hyperparameter at its bound (typically the length scale at the support spacing)
        # is expected and reported through length_scale_at_lower_bound.
        warnings.simplefilter("ignore", ConvergenceWarning)
        gpr.fit(x[:, None], y / scale)
    fitted = gpr.kernel_
    length_scale = float(fitted.k1.k2.length_scale)
    return _SEFit(length_scale=length_scale,
                  sigma_f2=float(fitted.k1.k1.constant_value) * scale ** 2,
                  noise_var=float(fitted.k2.noise_level) * scale ** 2,
                  log_marginal_likelihood=float(gpr.log_marginal_likelihood_value_),
                  length_scale_at_lower_bound=bool(length_scale <= low * (1.0 + 1e-6)))


def _check_samples(qd: np.ndarray, tau_r: np.ndarray, minimum: int,
                   what: str) -> tuple[np.ndarray, np.ndarray]:
    """Shape/finiteness/moving-joint checks of residual_model, plus a minimum sample count."""
    n_samples = np.shape(qd)[0] if np.ndim(qd) == 2 else 0
    if np.ndim(qd) == 2 and n_samples < minimum:
        raise ValueError(f"too few samples to fit {what}: got {n_samples}, need at least {minimum}")
    # n_components=1, n_support=2: only the generic checks of _check_training_data apply.
    return _check_training_data(qd, tau_r, n_components=1, n_support=2)


class _KernelPredictor:
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
        qd = _check_batch(qd, self.n_joints)
        mean = np.empty_like(qd)
        var = np.empty_like(qd)
        m = self._n_minus
        for start in range(0, qd.shape[0], _BATCH_CHUNK):
            rows = slice(start, start + _BATCH_CHUNK)
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


def _check_batch(qd: np.ndarray, n_joints: int) -> np.ndarray:
    qd = np.asarray(qd, dtype=np.float64)
    if qd.ndim != 2 or qd.shape[1] != n_joints:
        raise ValueError(f"qd must have shape (T, {n_joints}), got {qd.shape}")
    return qd


def _se_gram(a: np.ndarray, b: np.ndarray, length_scale: float, sigma_f2: float) -> np.ndarray:
    """SE kernel matrix between 1-D inputs a (A,) and b (B,)."""
    return sigma_f2 * np.exp(-0.5 * ((a[:, None] - b[None, :]) / length_scale) ** 2)


def _cholesky(matrix: np.ndarray, what: str) -> np.ndarray:
    try:
        return scipy.linalg.cholesky(matrix, lower=True)
    except np.linalg.LinAlgError as exc:
        raise ResidualModelError(f"{what} is not numerically positive definite ({exc})") from exc


# --------------------------------------------------------------------------------------------
# GMR-GP
# --------------------------------------------------------------------------------------------


def _support_spacing(reference: GMRReference) -> np.ndarray:
    """Largest gap between neighbouring support points per joint (n,), rad/s."""
    return np.max(np.diff(reference.s, axis=1), axis=1)


def _fit_gp_on_gmr_samples(reference: GMRReference, samples_per_support: int,
                           seed: int) -> tuple[GPHyperparameters, np.ndarray, list[dict]]:
    """Draw `samples_per_support` values y ~ N(μ_i, σ²_i) at every support point s_i of every
    joint and fit the SE GP hyperparameters to them by marginal likelihood.

    The length scale is bounded below by the support spacing (inside the optimisation, so σf²
    and σn² are fitted for the length scale that is used): between support points no data
    constrain a shorter scale, and with a scale below the spacing the GP/KMP mean sags towards
    0 and the variance ripples between support points.

    Returns the hyperparameters, the sample means ȳ (n, N) and per-joint fit info.
    """
    if samples_per_support < 1:
        raise ValueError(f"samples_per_support must be >= 1, got {samples_per_support}")
    rng = np.random.default_rng(seed)
    n, n_sup = reference.s.shape
    spacing = _support_spacing(reference)
    y_mean = np.empty((n, n_sup))
    fits = []
    for j in range(n):
        s = reference.s[j]
        y = (reference.mu[j][:, None] + np.sqrt(reference.sigma2[j])[:, None]
             * rng.standard_normal((n_sup, samples_per_support)))
        y_mean[j] = y.mean(axis=1)
        span = s[-1] - s[0]
        fit = _fit_se_gp(np.repeat(s, samples_per_support), y.ravel(),
                         (spacing[j], max(_MAX_LENGTH_SCALE_REL * span, 2.0 * spacing[j])),
                         seed=seed + j)
        fits.append(fit)
    hyper = GPHyperparameters(length_scale=[f.length_scale for f in fits],
                              sigma_f2=[f.sigma_f2 for f in fits],
                              noise_var=[f.noise_var for f in fits])
    info = [{"log_marginal_likelihood": f.log_marginal_likelihood,
             "length_scale_at_spacing": f.length_scale_at_lower_bound} for f in fits]
    return hyper, y_mean, info


class GMRGPResidualModel(_KernelPredictor):
    """GMR-GP (paper v2 §V-B): exact GP trained on data sampled from the GMR reference.

    Training: the GMR reference {s_i, μ_i, σ²_i} (fit_gmr_reference, the same N support points
    as KMP) is sampled m = samples_per_support times per support point, y_ik ~ N(μ_i, σ²_i);
    a zero-mean SE GP with white noise is fitted to the N·m points by marginal likelihood
    (sklearn). Because the m samples at s_i share their input, the exact GP posterior on them
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

    @_single_threaded
    def __init__(self, support: np.ndarray, targets: np.ndarray, hyper: GPHyperparameters,
                 samples_per_support: int = 1, reference: GMRReference | None = None,
                 metadata: Mapping[str, Any] | None = None) -> None:
        support = _frozen_float_array("support", support, ndim=2)
        targets = _frozen_float_array("targets", targets, ndim=2)
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
            gram = _se_gram(support[j], support[j], hyper.length_scale[j], sf2)
            gram[np.diag_indices(n_sup)] += (hyper.noise_var[j] / self.samples_per_support
                                             + KERNEL_JITTER_REL * sf2)
            chol = _cholesky(gram, f"joint {j}: K + σn²/m I")
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
    @_single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, n_components: int = 10,
            n_support: int = 30, samples_per_support: int = 10, seed: int = 0,
            reference: GMRReference | None = None) -> GMRGPResidualModel:
        """Fit GMM/GMR to qd (T, n) rad/s and tau_r (T, n) N·m, sample the reference
        `samples_per_support` times per support point and fit the GP to the samples.

        reference: an already fitted GMR reference (e.g. the KMP's), to skip the GMM fit;
        then qd, tau_r are not used and may be None.
        """
        if reference is None:
            reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                          n_support=n_support, seed=seed)
        hyper, y_mean, info = _fit_gp_on_gmr_samples(reference, samples_per_support, seed)
        metadata = {"fit": {"n_components": n_components if qd is not None else None,
                            "samples_per_support": samples_per_support, "seed": seed,
                            "joints": info}}
        return cls(reference.s, y_mean, hyper, samples_per_support, reference, metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/gmr_gp.npz (support, targets, the hyperparameters and, if known,
        the GMR reference mu/sigma2) and directory/gmr_gp.yaml, each atomically."""
        arrays = {"support": self.support, "targets": self.targets}
        arrays.update({key: getattr(self.hyper, key) for key in _GP_HYPER_KEYS})
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
        shapes.update({key: (n,) for key in _GP_HYPER_KEYS})
        has_reference = header.get("has_reference") is True
        if has_reference:
            shapes.update(reference_mu=(n, n_sup), reference_sigma2=(n, n_sup))
        arrays = _read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, _GP_HYPER_KEYS)
        try:
            hyper = GPHyperparameters(**{key: arrays[key] for key in _GP_HYPER_KEYS})
            reference = (GMRReference(s=arrays["support"], mu=arrays["reference_mu"],
                                      sigma2=arrays["reference_sigma2"]) if has_reference else None)
            return cls(arrays["support"], arrays["targets"], hyper, header["samples_per_support"],
                       reference, metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc


@_single_threaded
def hyperparameters_from_gp(qd: np.ndarray, tau_r: np.ndarray, n_support: int = 30,
                            seed: int = 0, *, n_components: int = 10,
                            samples_per_support: int = 10,
                            reference: GMRReference | None = None) -> KMPHyperparameters:
    """KMP hyperparameters from a GP marginal-likelihood fit on GMR-sampled data (paper v2 §V-B).

    The GP is the one GMR-GP uses (same reference, samples, seed, so the two models share
    their length scale and noise level, as in the paper):
    - length_scale: the fitted SE length scale, bounded below by the support spacing
      (max q̇ − min q̇)/(N − 1) inside the fit (KMP's variance ripples when the spacing exceeds
      the length scale, see residual_model.default_hyperparameters);
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

    qd, tau_r: (T, n) rad/s, N·m (ignored when `reference` is given).
    """
    if reference is None:
        reference = fit_gmr_reference(qd, tau_r, n_components=n_components,
                                      n_support=n_support, seed=seed)
    hyper, _, _ = _fit_gp_on_gmr_samples(reference, samples_per_support, seed)
    n_sup = reference.s.shape[1]
    length_scale = np.maximum(hyper.length_scale, _support_spacing(reference))
    lambda1 = hyper.noise_var / (samples_per_support * np.mean(reference.sigma2, axis=1))
    return KMPHyperparameters(length_scale=length_scale, sigma_f2=hyper.sigma_f2,
                              lambda1=lambda1, lambda2=n_sup * hyper.sigma_f2)


# --------------------------------------------------------------------------------------------
# Sparse GP (GPADKF)
# --------------------------------------------------------------------------------------------


class SparseGPResidualModel(_KernelPredictor):
    """Sparse GP residual model of the GPADKF baseline (paper v2 §V-B, Wei et al. 2023).

    Per joint: M = 50 inducing inputs z (k-means of the training velocities), SE kernel with
    hyperparameters fitted by an exact sklearn GP on a random subset (≤ 1000 points) of the
    raw data, and the FITC approximation (Snelson & Ghahramani 2006; `approximation="dtc"`
    gives DTC/projected process instead). With K_mm = L Lᵀ, V = L⁻¹ K_mn,
    Λ = diag(K_nn − VᵀV) + σn² (FITC) or σn² I (DTC), A = I + V Λ⁻¹ Vᵀ = L_A L_Aᵀ:
        mean     μ_* = k_*ᵀ c,   c = L⁻ᵀ A⁻¹ V Λ⁻¹ y                      (precomputed)
        variance   = σf² − ‖L⁻¹ k_*‖² + ‖L_A⁻¹ L⁻¹ k_*‖²  (latent)  + σn² (noise)
    (Quiñonero-Candela & Rasmussen, JMLR 2005, unifying view of sparse GPs.) The model stores
    z, c, L_A and the hyperparameters; L is recomputed from z.

    Attributes: inducing (n, M), mean_weights c (n, M), chol_a L_A (n, M, M), hyper,
    approximation, metadata.
    """

    name = "gpadkf"
    NPZ_NAME = "sparse_gp.npz"
    YAML_NAME = "sparse_gp.yaml"
    _STEM = "sparse_gp"

    @_single_threaded
    def __init__(self, inducing: np.ndarray, mean_weights: np.ndarray, chol_a: np.ndarray,
                 hyper: GPHyperparameters, approximation: str = "fitc",
                 metadata: Mapping[str, Any] | None = None) -> None:
        inducing = _frozen_float_array("inducing", inducing, ndim=2)
        mean_weights = _frozen_float_array("mean_weights", mean_weights, ndim=2)
        chol_a = _frozen_float_array("chol_a", chol_a, ndim=3)
        n, m = inducing.shape
        if mean_weights.shape != (n, m) or chol_a.shape != (n, m, m) or m < 1:
            raise ResidualModelError(
                f"inducing {inducing.shape}, mean_weights {mean_weights.shape} and chol_a "
                f"{chol_a.shape} must have shapes (n, M), (n, M), (n, M, M)")
        if hyper.n_joints != n:
            raise ResidualModelError(f"inducing has {n} joints, hyperparameters {hyper.n_joints}")
        if approximation not in ("fitc", "dtc"):
            raise ResidualModelError(
                f"approximation must be 'fitc' or 'dtc', got {approximation!r}")
        diag = np.diagonal(chol_a, axis1=1, axis2=2)
        if np.any(diag <= 0.0) or np.any(np.triu(chol_a, k=1) != 0.0):
            raise ResidualModelError("chol_a must be lower triangular with a positive diagonal")
        self.inducing = inducing
        self.mean_weights = mean_weights
        self.chol_a = chol_a
        self.hyper = hyper
        self.approximation = approximation
        self.metadata: dict[str, Any] = dict(metadata or {})
        # Row 0: c; rows 1..M: σf² L⁻¹; rows M+1..2M: σf² L_A⁻¹ L⁻¹ (query uses e = k_*/σf²).
        weights = np.empty((n, 1 + 2 * m, m))
        for j in range(n):
            sf2 = hyper.sigma_f2[j]
            l_inv = self._chol_inv_kmm(j)
            weights[j, 0] = sf2 * mean_weights[j]
            weights[j, 1:1 + m] = sf2 * l_inv
            weights[j, 1 + m:] = sf2 * scipy.linalg.solve_triangular(chol_a[j], l_inv, lower=True)
        self._setup_predictor(inducing, hyper, weights)

    def _chol_inv_kmm(self, j: int) -> np.ndarray:
        """L⁻¹ with L Lᵀ = K_mm + jitter, joint j."""
        z, sf2 = self.inducing[j], self.hyper.sigma_f2[j]
        kmm = _se_gram(z, z, self.hyper.length_scale[j], sf2)
        kmm[np.diag_indices(len(z))] += KERNEL_JITTER_REL * sf2
        chol = _cholesky(kmm, f"joint {j}: K_mm")
        return scipy.linalg.solve_triangular(chol, np.eye(len(z)), lower=True)

    @property
    def n_inducing(self) -> int:
        """Number of inducing points M per joint."""
        return self.inducing.shape[1]

    @classmethod
    @_single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, n_inducing: int = 50,
            n_hyper_subset: int = 1000, approximation: str = "fitc", seed: int = 0,
            n_restarts: int = 1) -> SparseGPResidualModel:
        """Fit to qd (T, n) rad/s, tau_r (T, n) N·m.

        Inducing points: k-means (sklearn KMeans, 1-D) of each joint's velocities, sorted.
        k-means centres follow the data density only weakly (∝ density^(1/3) in 1-D), so
        unlike quantiles they do not desert the slow, sparsely visited velocities where the
        friction changes fastest. Hyperparameters: exact GP marginal-likelihood fit on a
        random subset of min(T, n_hyper_subset) samples per joint, L-BFGS-B from the
        start ℓ = range/10 plus `n_restarts` random starts (each costs ~1 s at 1000 samples).
        """
        if n_inducing < 1 or n_hyper_subset < 2:
            raise ValueError(f"n_inducing must be >= 1 and n_hyper_subset >= 2, got "
                             f"{n_inducing}, {n_hyper_subset}")
        if approximation not in ("fitc", "dtc"):
            raise ValueError(f"approximation must be 'fitc' or 'dtc', got {approximation!r}")
        qd, tau_r = _check_samples(qd, tau_r, max(n_inducing, 5), "a sparse GP")
        n_samples, n = qd.shape
        rng = np.random.default_rng(seed)
        inducing = np.empty((n, n_inducing))
        mean_weights = np.empty((n, n_inducing))
        chol_a = np.empty((n, n_inducing, n_inducing))
        fits = []
        for j in range(n):
            x, y = qd[:, j], tau_r[:, j]
            n_distinct = np.unique(x).size
            if n_distinct < n_inducing:
                raise ValueError(f"joint {j}: only {n_distinct} distinct velocities, fewer than "
                                 f"the {n_inducing} inducing points")
            km = KMeans(n_clusters=n_inducing, n_init=3, random_state=seed + j).fit(x[:, None])
            z = np.sort(km.cluster_centers_[:, 0])
            subset = rng.choice(n_samples, size=min(n_samples, n_hyper_subset), replace=False)
            span = x.max() - x.min()
            fit = _fit_se_gp(x[subset], y[subset],
                             (_MIN_LENGTH_SCALE_REL * span, _MAX_LENGTH_SCALE_REL * span),
                             seed=seed + j, n_restarts=n_restarts)
            fits.append(fit)
            inducing[j] = z
            mean_weights[j], chol_a[j] = _sparse_factors(x, y, z, fit, approximation)
        hyper = GPHyperparameters(length_scale=[f.length_scale for f in fits],
                                  sigma_f2=[f.sigma_f2 for f in fits],
                                  noise_var=[f.noise_var for f in fits])
        metadata = {"fit": {"n_samples": n_samples, "n_hyper_subset": n_hyper_subset,
                            "seed": seed, "joints": [
                                {"log_marginal_likelihood": f.log_marginal_likelihood}
                                for f in fits]}}
        return cls(inducing, mean_weights, chol_a, hyper, approximation, metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/sparse_gp.npz and directory/sparse_gp.yaml, each atomically."""
        arrays = {"inducing": self.inducing, "mean_weights": self.mean_weights,
                  "chol_a": self.chol_a}
        arrays.update({key: getattr(self.hyper, key) for key in _GP_HYPER_KEYS})
        header = {
            "format_version": FORMAT_VERSION,
            "model": self.name,
            "n_joints": self.n_joints,
            "n_inducing": self.n_inducing,
            "approximation": self.approximation,
            "variance": "latent + noise (variance of a new residual observation)",
            "hyperparameters": self.hyper.as_dict(),
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, self._STEM, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> SparseGPResidualModel:
        """Load a model written by save(); np.load(..., allow_pickle=False). Any problem ->
        ResidualModelError naming the file."""
        directory = Path(directory)
        yaml_path, npz_path = directory / cls.YAML_NAME, directory / cls.NPZ_NAME
        header = read_model_header(yaml_path, ("n_inducing",), cls.name)
        if header.get("approximation") not in ("fitc", "dtc"):
            raise ResidualModelError(f"{yaml_path}: approximation must be 'fitc' or 'dtc', got "
                                     f"{header.get('approximation')!r}")
        n, m = header["n_joints"], header["n_inducing"]
        shapes: dict[str, tuple[int, ...]] = {
            "inducing": (n, m), "mean_weights": (n, m), "chol_a": (n, m, m)}
        shapes.update({key: (n,) for key in _GP_HYPER_KEYS})
        arrays = _read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, _GP_HYPER_KEYS)
        try:
            hyper = GPHyperparameters(**{key: arrays[key] for key in _GP_HYPER_KEYS})
            return cls(arrays["inducing"], arrays["mean_weights"], arrays["chol_a"], hyper,
                       header.get("approximation"), metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc


def _sparse_factors(x: np.ndarray, y: np.ndarray, z: np.ndarray, fit: _SEFit,
                    approximation: str) -> tuple[np.ndarray, np.ndarray]:
    """Mean weights c (M,) and L_A (M, M) of the FITC/DTC posterior on all data (x, y)."""
    sf2, ls, noise = fit.sigma_f2, fit.length_scale, fit.noise_var
    m = len(z)
    kmm = _se_gram(z, z, ls, sf2)
    kmm[np.diag_indices(m)] += KERNEL_JITTER_REL * sf2
    chol = _cholesky(kmm, "K_mm")
    v = scipy.linalg.solve_triangular(chol, _se_gram(z, x, ls, sf2), lower=True)  # (M, T)
    if approximation == "fitc":
        lam = np.maximum(sf2 - np.einsum("mt,mt->t", v, v), 0.0) + noise
    else:
        lam = np.full(x.shape, noise)
    v_scaled = v / lam  # V Λ⁻¹
    a = v_scaled @ v.T
    a[np.diag_indices(m)] += 1.0
    chol_a = _cholesky(a, "I + V Λ⁻¹ Vᵀ")
    u = scipy.linalg.cho_solve((chol_a, True), v_scaled @ y)  # A⁻¹ V Λ⁻¹ y
    c = scipy.linalg.solve_triangular(chol, u, lower=True, trans="T")  # L⁻ᵀ …
    return c, np.tril(chol_a)


# --------------------------------------------------------------------------------------------
# MLP (NNADKF)
# --------------------------------------------------------------------------------------------


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0, out=x)


def _tanh(x: np.ndarray) -> np.ndarray:
    return np.tanh(x, out=x)


def _logistic(x: np.ndarray) -> np.ndarray:
    return scipy.special.expit(x, out=x)


def _identity(x: np.ndarray) -> np.ndarray:
    return x


# sklearn MLPRegressor's hidden activations, in place.
_ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": _tanh, "relu": _relu, "logistic": _logistic, "identity": _identity}


class MLPResidualModel:
    """Per-joint MLP residual mean with a static variance (NNADKF baseline, paper v2 §V-B).

    One sklearn MLPRegressor per joint: input the standardised velocity, output the
    standardised residual, hidden layers (30, 30). The paper uses ELU units; sklearn has no
    ELU, so the default is tanh (smooth and saturating on the negative side like ELU). Adam,
    learning rate 1e-3, up to 300 epochs, mini-batch 512 as in the paper. The paper's
    additive correction network (online fine-tuning) is not part of this model.

    The trained weights are exported to arrays stacked across joints, coef_k (n, in_k, out_k)
    and intercept_k (n, out_k), and predict() runs the forward pass in numpy for all joints at
    once. The variance is static per joint: the mean squared training residual
    mean_t (τ_r − μ(q̇))², the "static covariance" of the paper (the filter's covariance
    matching rescales it).

    Attributes: coefs, intercepts (lists of arrays), x_mean, x_scale, y_mean, y_scale,
    variance (n,), activation, metadata.
    """

    name = "nnadkf"
    NPZ_NAME = "mlp.npz"
    YAML_NAME = "mlp.yaml"
    _STEM = "mlp"

    def __init__(self, coefs: list[np.ndarray], intercepts: list[np.ndarray],
                 x_mean: np.ndarray, x_scale: np.ndarray, y_mean: np.ndarray,
                 y_scale: np.ndarray, variance: np.ndarray, activation: str = "tanh",
                 metadata: Mapping[str, Any] | None = None) -> None:
        if activation not in _ACTIVATIONS:
            raise ResidualModelError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        if len(coefs) < 1 or len(coefs) != len(intercepts):
            raise ResidualModelError(
                f"need as many coefs as intercepts (>= 1), got {len(coefs)} and {len(intercepts)}")
        self.coefs = [_frozen_float_array(f"coef_{k}", c, ndim=3) for k, c in enumerate(coefs)]
        self.intercepts = [_frozen_float_array(f"intercept_{k}", b, ndim=2)
                           for k, b in enumerate(intercepts)]
        n = self.coefs[0].shape[0]
        width = 1
        for k, (c, b) in enumerate(zip(self.coefs, self.intercepts)):
            if c.shape[:2] != (n, width) or b.shape != (n, c.shape[2]):
                raise ResidualModelError(
                    f"layer {k}: coef {c.shape} / intercept {b.shape} do not chain "
                    f"(expected ({n}, {width}, ·) and ({n}, ·))")
            width = c.shape[2]
        if width != 1:
            raise ResidualModelError(f"the last layer must have 1 output, has {width}")
        for key, value in (("x_mean", x_mean), ("x_scale", x_scale), ("y_mean", y_mean),
                           ("y_scale", y_scale), ("variance", variance)):
            array = _frozen_float_array(key, value, ndim=1)
            if array.shape != (n,):
                raise ResidualModelError(f"{key} must have shape ({n},), got {array.shape}")
            if key in ("x_scale", "y_scale", "variance") and np.any(array <= 0.0):
                raise ResidualModelError(f"{key} must be strictly positive, got {array}")
            setattr(self, key, array)
        self.activation = activation
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._act = _ACTIVATIONS[activation]
        # Hot-path views: first layer (n, H1) (the input is a scalar per joint), last layer
        # (n, H_last) scaled by y_scale, middle layers as they are.
        self._w_in = self.coefs[0][:, 0, :]
        self._b_in = self.intercepts[0]
        self._middle = list(zip(self.coefs[1:-1], self.intercepts[1:-1]))
        self._inv_x_scale = 1.0 / self.x_scale
        if len(self.coefs) > 1:
            self._w_out = self.coefs[-1][:, :, 0] * self.y_scale[:, None]
            self._b_out = self.intercepts[-1][:, 0] * self.y_scale + self.y_mean

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return self.x_mean.shape[0]

    @property
    def hidden_layer_sizes(self) -> tuple[int, ...]:
        return tuple(c.shape[2] for c in self.coefs[:-1])

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (n,) rad/s -> (mean (n,) N·m, static variance (n,) N²·m²). Hot path."""
        if len(self.coefs) == 1:  # no hidden layer: a linear model
            return self._forward_batch(qd[None, :])[0], self.variance.copy()
        x = (qd - self.x_mean) * self._inv_x_scale
        h = x[:, None] * self._w_in
        h += self._b_in
        self._act(h)
        for w, b in self._middle:
            h = np.matmul(h[:, None, :], w)[:, 0, :]
            h += b
            self._act(h)
        mean = np.einsum("jh,jh->j", h, self._w_out)
        mean += self._b_out
        return mean, self.variance.copy()

    def _forward_batch(self, qd: np.ndarray) -> np.ndarray:
        """qd (t, n) -> mean (t, n), all layers, joints first: h (n, t, width)."""
        h = ((qd - self.x_mean) * self._inv_x_scale).T[:, :, None]  # (n, t, 1)
        last = len(self.coefs) - 1
        for k, (w, b) in enumerate(zip(self.coefs, self.intercepts)):
            h = np.matmul(h, w) + b[:, None, :]
            if k < last:
                self._act(h)
        return (h[:, :, 0] * self.y_scale[:, None] + self.y_mean[:, None]).T

    def predict_batch(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qd: (T, n) -> mean (T, n), variance (T, n) (the static variance on every row)."""
        qd = _check_batch(qd, self.n_joints)
        mean = np.empty_like(qd)
        for start in range(0, qd.shape[0], _BATCH_CHUNK):
            rows = slice(start, start + _BATCH_CHUNK)
            mean[rows] = self._forward_batch(qd[rows])
        return mean, np.broadcast_to(self.variance, qd.shape).copy()

    @classmethod
    @_single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray,
            hidden_layer_sizes: tuple[int, ...] = (30, 30), activation: str = "tanh",
            learning_rate: float = 1e-3, max_epochs: int = 300, batch_size: int = 512,
            l2: float = 1e-4, tol: float = 0.0, seed: int = 0) -> MLPResidualModel:
        """Train one MLPRegressor per joint on standardised qd (T, n) rad/s -> tau_r (T, n) N·m.

        Adam with `learning_rate`, `max_epochs` epochs (earlier only if the training loss has
        not improved by `tol` for 10 epochs; sklearn's default tol 1e-4 stopped training at
        ~120 epochs with the friction step still blurred, hence tol 0), mini-batches of
        min(batch_size, T), L2 penalty `l2` (sklearn's alpha), random_state seed + j for
        joint j. The paper's 512-sample batches need enough data: with only 3000 samples,
        300 epochs are ~1800 Adam steps and leave the step at q̇ = 0 blurred (RMSE ≈ the noise
        level in our check); batch_size 128 fixed that.
        """
        if activation not in _ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        qd, tau_r = _check_samples(qd, tau_r, 10, "an MLP")
        n_samples, n = qd.shape
        x_mean, x_scale = qd.mean(axis=0), qd.std(axis=0)
        y_mean, y_scale = tau_r.mean(axis=0), tau_r.std(axis=0)
        y_scale = np.where(y_scale > 0.0, y_scale, 1.0)
        layers: list[list[np.ndarray]] = []
        biases: list[list[np.ndarray]] = []
        epochs = []
        for j in range(n):
            net = MLPRegressor(hidden_layer_sizes=tuple(hidden_layer_sizes), activation=activation,
                               solver="adam", learning_rate_init=learning_rate,
                               max_iter=max_epochs, batch_size=min(batch_size, n_samples),
                               alpha=l2, tol=tol, n_iter_no_change=10, shuffle=True,
                               random_state=seed + j)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)  # max_epochs reached
                net.fit(((qd[:, j] - x_mean[j]) / x_scale[j])[:, None],
                        (tau_r[:, j] - y_mean[j]) / y_scale[j])
            layers.append(net.coefs_)
            biases.append(net.intercepts_)
            epochs.append(int(net.n_iter_))
        coefs = [np.stack([layers[j][k] for j in range(n)]) for k in range(len(layers[0]))]
        intercepts = [np.stack([biases[j][k] for j in range(n)]) for k in range(len(biases[0]))]
        placeholder = np.ones(n)
        model = cls(coefs, intercepts, x_mean, x_scale, y_mean, y_scale, placeholder, activation)
        residual = tau_r - model.predict_batch(qd)[0]
        variance = np.maximum(np.mean(residual ** 2, axis=0), VARIANCE_FLOOR)
        metadata = {"fit": {"n_samples": n_samples, "epochs": epochs,
                            "learning_rate": learning_rate, "batch_size": batch_size, "l2": l2,
                            "seed": seed}}
        return cls(coefs, intercepts, x_mean, x_scale, y_mean, y_scale, variance, activation,
                   metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/mlp.npz (coef_k, intercept_k, scalings, variance) and mlp.yaml."""
        arrays = {f"coef_{k}": c for k, c in enumerate(self.coefs)}
        arrays.update({f"intercept_{k}": b for k, b in enumerate(self.intercepts)})
        arrays.update(x_mean=self.x_mean, x_scale=self.x_scale, y_mean=self.y_mean,
                      y_scale=self.y_scale, variance=self.variance)
        header = {
            "format_version": FORMAT_VERSION,
            "model": self.name,
            "n_joints": self.n_joints,
            "hidden_layer_sizes": list(self.hidden_layer_sizes),
            "activation": self.activation,
            "variance": "static: mean squared training residual",
            "hyperparameters": {"variance": self.variance.tolist()},
            "metadata": dict(self.metadata if metadata is None else metadata),
        }
        save_model_pair(directory, self._STEM, arrays, header)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> MLPResidualModel:
        """Load a model written by save(); np.load(..., allow_pickle=False). Any problem ->
        ResidualModelError naming the file."""
        directory = Path(directory)
        yaml_path, npz_path = directory / cls.YAML_NAME, directory / cls.NPZ_NAME
        header = read_model_header(yaml_path, (), cls.name)
        n = header["n_joints"]
        if header.get("activation") not in _ACTIVATIONS:
            raise ResidualModelError(f"{yaml_path}: activation must be one of "
                                     f"{sorted(_ACTIVATIONS)}, got {header.get('activation')!r}")
        sizes = header.get("hidden_layer_sizes")
        if not isinstance(sizes, list) or not all(
                isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in sizes):
            raise ResidualModelError(
                f"{yaml_path}: hidden_layer_sizes must be a list of positive integers, "
                f"got {sizes!r}")
        widths = [1] + sizes + [1]
        shapes: dict[str, tuple[int, ...]] = {}
        for k in range(len(widths) - 1):
            shapes[f"coef_{k}"] = (n, widths[k], widths[k + 1])
            shapes[f"intercept_{k}"] = (n, widths[k + 1])
        shapes.update({key: (n,) for key in ("x_mean", "x_scale", "y_mean", "y_scale", "variance")})
        arrays = _read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, ("variance",))
        n_layers = len(widths) - 1
        try:
            return cls([arrays[f"coef_{k}"] for k in range(n_layers)],
                       [arrays[f"intercept_{k}"] for k in range(n_layers)],
                       arrays["x_mean"], arrays["x_scale"], arrays["y_mean"], arrays["y_scale"],
                       arrays["variance"], header.get("activation"), metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc


# Observer name (DESIGN §3) -> residual model class.
BASELINE_MODELS: dict[str, type] = {
    GMRGPResidualModel.name: GMRGPResidualModel,
    SparseGPResidualModel.name: SparseGPResidualModel,
    MLPResidualModel.name: MLPResidualModel,
}
