"""Residual-torque models: K-VARK's KMP and the learned baselines of paper v2 §V-B.

Each maps, per joint j, the joint velocity q̇_j (rad/s) to the residual torque
τ_r,j = τ_m,j − τ_EL,j (N·m) with a predictive variance (N²·m²), and has the same interface:
``n_joints``, ``predict(qd (n,)) -> (mean (n,), var (n,))`` (hot path: vectorised across joints,
all factors precomputed, no sklearn call), ``predict_batch(qd (T, n))``, the ``fit`` classmethod,
and ``save(directory)`` / ``load(directory)`` writing their own file pair in the model directory,
atomically, with no object serialisation (arrays in .npz read with allow_pickle=False, a small
YAML header beside them).

=====================  ==========  ============================================================
class                  files       model
=====================  ==========  ============================================================
KMPResidualModel       kmp.*       GMM → GMR reference → KMP (paper v1 eqs. 18-23)
GMRGPResidualModel     gmr_gp.*    exact GP (SE kernel) on samples drawn from the GMR reference
SparseGPResidualModel  sparse_gp.* FITC (default) or DTC sparse GP, 50 inducing points, raw data
MLPResidualModel       mlp.*       per-joint MLP (2 × 30 tanh), static variance
=====================  ==========  ============================================================

``LEARNED_BASELINES`` is the one list of the learned baselines: observer name -> model class,
used to fit them (``kvark train``) and to load them from a model directory.
"""

from __future__ import annotations

from kvark_ros.core.estimation.residual.files import ResidualModelError
from kvark_ros.core.estimation.residual.gp import GMRGPResidualModel, GPHyperparameters, hyperparameters_from_gp
from kvark_ros.core.estimation.residual.kmp import (
    INPUT_KINDS,
    GMRReference,
    KMPHyperparameters,
    KMPResidualModel,
    default_hyperparameters,
    fit_gmr_reference,
)
from kvark_ros.core.estimation.residual.mlp import MLPResidualModel
from kvark_ros.core.estimation.residual.sparse_gp import SparseGPResidualModel

# Observer name (docs/method.md §5.2) -> residual model class, in training order.
LEARNED_BASELINES: dict[str, type] = {
    GMRGPResidualModel.name: GMRGPResidualModel,
    SparseGPResidualModel.name: SparseGPResidualModel,
    MLPResidualModel.name: MLPResidualModel,
}

__all__ = [
    "INPUT_KINDS",
    "GMRGPResidualModel",
    "GMRReference",
    "GPHyperparameters",
    "KMPHyperparameters",
    "KMPResidualModel",
    "LEARNED_BASELINES",
    "MLPResidualModel",
    "ResidualModelError",
    "SparseGPResidualModel",
    "default_hyperparameters",
    "fit_gmr_reference",
    "hyperparameters_from_gp",
]
