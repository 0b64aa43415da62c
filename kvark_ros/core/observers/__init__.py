"""External-torque observers, each selectable by name (config key ``observer``, CLI ``--observers``).

======================  ===================================================================
name                    what
======================  ===================================================================
kvark                   K-VARK (paper v1 Algorithm 1): KMP residual, adaptive Σ_ν, VB Σ_d
kf, kmp_kf,             its ablations A1-A4 (paper v2 Table VI)
kmp_kf_ewma, kmp_kf_nis
gmr_gp                  GMR reference → GP residual mean/variance in the K-VARK filter
gpadkf                  sparse-GP residual in an adaptive disturbance KF (heteroscedastic R,
                        EWMA empirical noise, fixed Σ_d; after Wei et al. 2023)
nnadkf                  MLP residual mean, static covariances (the A1 filter)
momentum, kfmo,         the second paper's residual-free momentum observers
sh_akfmo, vbkfmo_q, eso
oracle                  the K-VARK filter given the plant file's true friction (simulation only)
======================  ===================================================================
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from kvark_ros.core.config import OBSERVER_NAMES, EstimatorConfig
from kvark_ros.core.observers.base import FilterTuning, Observer
from kvark_ros.core.observers.kvark_filter import VARIANTS, KVARKFilter
from kvark_ros.core.observers.kvark_momentum import KVARKMomentumFilter
from kvark_ros.core.observers.momentum_observers import MOMENTUM_OBSERVER_NAMES, make_momentum_observer

if TYPE_CHECKING:
    from kvark_ros.core.model_store import TrainedModel

__all__ = ["FilterTuning", "Observer", "ObserverError", "KVARKFilter", "make_observer", "OBSERVER_NAMES",
           "OracleResidual"]

# Learned-residual baselines: the K-VARK filter variant each one runs in.
LEARNED_BASELINE_VARIANTS = {"gmr_gp": "kvark", "gpadkf": "kmp_kf_ewma", "nnadkf": "kf"}
ORACLE_VARIANCE = 1e-4   # N²·m²: the oracle's residual is exact up to the plant's noise


class ObserverError(ValueError):
    """An observer cannot be built from what was given (model, plant); the message says what to do."""


class OracleResidual:
    """The plant's true friction as a residual model (``predict(q̇) -> (mean, variance)``)."""

    def __init__(self, plant: Any, n: int) -> None:
        from kvark_ros.sim.plant import friction_torque
        self._friction = friction_torque
        self.plant = plant
        self._variance = np.full(n, ORACLE_VARIANCE)

    @property
    def n_joints(self) -> int:
        return len(self._variance)

    def predict(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._friction(self.plant, qd), self._variance


def _kvark(variant: str, residual: Any, tuning: FilterTuning, trained: "TrainedModel", config: EstimatorConfig,
           name: str) -> Observer:
    """The K-VARK filter in the configured measurement form (``filter.measurement``)."""
    if config.measurement == "difference":
        return KVARKFilter(variant, residual, tuning, config, name=name)
    if trained.momentum_noise is None:
        raise ObserverError("filter.measurement: momentum needs the model's momentum noise; retrain the model")
    return KVARKMomentumFilter(variant, residual, tuning, trained.momentum_noise, config, name=name)


def make_observer(name: str, trained: "TrainedModel", config: EstimatorConfig, plant: Any = None) -> Observer:
    """Build the observer called ``name`` from a trained model (``plant``: a PlantSpec, oracle only)."""
    if name in VARIANTS:
        return _kvark(name, trained.residual, trained.tuning, trained, config, name)
    if name in LEARNED_BASELINE_VARIANTS:
        if name not in trained.baselines:
            raise ObserverError(f"observer '{name}' needs its residual model, which this model directory lacks; "
                             "retrain without --no-baselines")
        return _kvark(LEARNED_BASELINE_VARIANTS[name], trained.baselines[name], trained.baseline_tunings[name],
                      trained, config, name)
    if name in MOMENTUM_OBSERVER_NAMES:
        return make_momentum_observer(name, len(trained.joint_names), trained.momentum_noise, config)
    if name == "oracle":
        if plant is None:
            raise ObserverError("observer 'oracle' needs the simulator's plant file (pass --plant FILE)")
        if trained.augmentation is not None:
            raise ObserverError("observer 'oracle' adds the plant's true friction to the nominal model, but this "
                                "model is augmented (kvark diagnose); use a model trained without augmentation")
        return _kvark("kvark", OracleResidual(plant, len(trained.joint_names)), trained.tuning, trained, config,
                      "oracle")
    raise ObserverError(f"unknown observer '{name}'; known: {', '.join(OBSERVER_NAMES)}")
