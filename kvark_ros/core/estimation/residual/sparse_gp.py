"""The sparse-GP residual model of the GPADKF baseline (Wei et al. 2023): M inducing points, ARD SE."""
from __future__ import annotations

import os
from concurrent.futures import Executor
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.linalg

from kvark_ros.core.estimation.residual.common import check_samples, map_joints, single_threaded
from kvark_ros.core.estimation.residual.files import (
    FORMAT_VERSION,
    ResidualModelError,
    check_listed_values,
    frozen_float_array,
    read_arrays,
    read_model_header,
    save_model_pair,
)
from kvark_ros.core.estimation.residual.gp import (GP_HYPER_KEYS, KERNEL_JITTER_REL, MAX_LENGTH_SCALE_REL,
                                                   MIN_LENGTH_SCALE_REL, GPHyperparameters, KernelPredictor, SEFit,
                                                   cholesky, fit_se_gp, se_gram)


class SparseGPResidualModel(KernelPredictor):
    """Sparse GP residual model of the GPADKF baseline (paper v2 §V-B, Wei et al. 2023).

    Per joint: M = 50 inducing inputs z (k-means of the training velocities), SE kernel with
    hyperparameters fitted by an exact GP (``gp_fit.fit_gp``) on a random subset (≤ 1000 points) of the
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

    @single_threaded
    def __init__(self, inducing: np.ndarray, mean_weights: np.ndarray, chol_a: np.ndarray,
                 hyper: GPHyperparameters, approximation: str = "fitc",
                 metadata: Mapping[str, Any] | None = None) -> None:
        inducing = frozen_float_array("inducing", inducing, ndim=2)
        mean_weights = frozen_float_array("mean_weights", mean_weights, ndim=2)
        chol_a = frozen_float_array("chol_a", chol_a, ndim=3)
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
        kmm = se_gram(z, z, self.hyper.length_scale[j], sf2)
        kmm[np.diag_indices(len(z))] += KERNEL_JITTER_REL * sf2
        chol = cholesky(kmm, f"joint {j}: K_mm")
        return scipy.linalg.solve_triangular(chol, np.eye(len(z)), lower=True)

    @property
    def n_inducing(self) -> int:
        """Number of inducing points M per joint."""
        return self.inducing.shape[1]

    @classmethod
    @single_threaded
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, n_inducing: int = 50,
            n_hyper_subset: int = 1000, approximation: str = "fitc", seed: int = 0,
            n_restarts: int = 1, executor: Executor | None = None) -> SparseGPResidualModel:
        """Fit to qd (T, n) rad/s, tau_r (T, n) N·m, each joint (``_fit_joint``) in ``executor``'s workers when given
        (``map_joints``).

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
        qd, tau_r = check_samples(qd, tau_r, max(n_inducing, 5), "a sparse GP")
        n_samples, n = qd.shape
        rng = np.random.default_rng(seed)
        tasks = []
        for j in range(n):
            n_distinct = np.unique(qd[:, j]).size
            if n_distinct < n_inducing:
                raise ValueError(f"joint {j}: only {n_distinct} distinct velocities, fewer than "
                                 f"the {n_inducing} inducing points")
            subset = rng.choice(n_samples, size=min(n_samples, n_hyper_subset), replace=False)
            tasks.append((qd[:, j].copy(), tau_r[:, j].copy(), subset, n_inducing, approximation, seed + j, n_restarts))
        inducing, mean_weights, chol_a, fits = zip(*map_joints(_fit_joint, tasks, executor))
        hyper = GPHyperparameters(length_scale=[f.length_scale for f in fits],
                                  sigma_f2=[f.sigma_f2 for f in fits],
                                  noise_var=[f.noise_var for f in fits])
        metadata = {"fit": {"n_samples": n_samples, "n_hyper_subset": n_hyper_subset,
                            "seed": seed, "joints": [
                                {"log_marginal_likelihood": f.log_marginal_likelihood}
                                for f in fits]}}
        return cls(np.array(inducing), np.array(mean_weights), np.array(chol_a), hyper, approximation, metadata)

    def save(self, directory: str | os.PathLike, metadata: dict | None = None) -> None:
        """Writes directory/sparse_gp.npz and directory/sparse_gp.yaml, each atomically."""
        arrays = {"inducing": self.inducing, "mean_weights": self.mean_weights,
                  "chol_a": self.chol_a}
        arrays.update({key: getattr(self.hyper, key) for key in GP_HYPER_KEYS})
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
        shapes.update({key: (n,) for key in GP_HYPER_KEYS})
        arrays = read_arrays(npz_path, shapes)
        check_listed_values(yaml_path, npz_path, header.get("hyperparameters"), arrays, GP_HYPER_KEYS)
        try:
            hyper = GPHyperparameters(**{key: arrays[key] for key in GP_HYPER_KEYS})
            return cls(arrays["inducing"], arrays["mean_weights"], arrays["chol_a"], hyper,
                       header.get("approximation"), metadata=header["metadata"])
        except ResidualModelError as exc:
            raise ResidualModelError(f"{npz_path}: {exc}") from exc


def _fit_joint(x: np.ndarray, y: np.ndarray, subset: np.ndarray, n_inducing: int, approximation: str, seed: int,
               n_restarts: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, SEFit]:
    """One joint of ``SparseGPResidualModel.fit`` from its q̇ x (T,) rad/s and τ_r y (T,) N·m: the sorted inducing
    inputs z (M,), the mean weights c (M,), L_A (M, M) and the GP fitted on the rows ``subset``."""
    from sklearn.cluster import KMeans          # fitting only: loading a model needs no sklearn
    z = np.sort(KMeans(n_clusters=n_inducing, n_init=3, random_state=seed).fit(x[:, None]).cluster_centers_[:, 0])
    span = x.max() - x.min()
    fit = fit_se_gp(x[subset], y[subset], (MIN_LENGTH_SCALE_REL * span, MAX_LENGTH_SCALE_REL * span),
                    seed=seed, n_restarts=n_restarts)
    return (z,) + _sparse_factors(x, y, z, fit, approximation) + (fit,)


def _sparse_factors(x: np.ndarray, y: np.ndarray, z: np.ndarray, fit: SEFit,
                    approximation: str) -> tuple[np.ndarray, np.ndarray]:
    """Mean weights c (M,) and L_A (M, M) of the FITC/DTC posterior on all data (x, y)."""
    sf2, ls, noise = fit.sigma_f2, fit.length_scale, fit.noise_var
    m = len(z)
    kmm = se_gram(z, z, ls, sf2)
    kmm[np.diag_indices(m)] += KERNEL_JITTER_REL * sf2
    chol = cholesky(kmm, "K_mm")
    v = scipy.linalg.solve_triangular(chol, se_gram(z, x, ls, sf2), lower=True)  # (M, T)
    if approximation == "fitc":
        lam = np.maximum(sf2 - np.einsum("mt,mt->t", v, v), 0.0) + noise
    else:
        lam = np.full(x.shape, noise)
    v_scaled = v / lam  # V Λ⁻¹
    a = v_scaled @ v.T
    a[np.diag_indices(m)] += 1.0
    chol_a = cholesky(a, "I + V Λ⁻¹ Vᵀ")
    u = scipy.linalg.cho_solve((chol_a, True), v_scaled @ y)  # A⁻¹ V Λ⁻¹ y
    c = scipy.linalg.solve_triangular(chol, u, lower=True, trans="T")  # L⁻ᵀ …
    return c, np.tril(chol_a)
