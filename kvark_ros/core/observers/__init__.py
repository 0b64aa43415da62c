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
oracle                  the K-VARK filter given the true residual and rigid body (``oracle``: the simulator's
                        ``kvark_ros.sim.plant.OracleResidual``)
======================  ===================================================================
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from kvark_ros.core.config import OBSERVER_NAMES, FilterSettings
from kvark_ros.core.observers.base import FilterTuning, Observer, ResidualPredictor
from kvark_ros.core.observers.kvark_filter import VARIANTS, KVARKFilter
from kvark_ros.core.observers.kvark_momentum import KVARKMomentumFilter
from kvark_ros.core.observers.momentum_observers import MOMENTUM_OBSERVER_NAMES, make_momentum_observer

if TYPE_CHECKING:
    from kvark_ros.core.model_store import TrainedModel

__all__ = ["FilterTuning", "Observer", "ObserverError", "KVARKFilter", "make_observer", "OBSERVER_NAMES",
           "ResidualPredictor"]

# Learned-residual baselines: the K-VARK filter variant each one runs in.
LEARNED_BASELINE_VARIANTS = {"gmr_gp": "kvark", "gpadkf": "kmp_kf_ewma", "nnadkf": "kf"}


class ObserverError(ValueError):
    """An observer cannot be built from what was given (model, oracle); the message says what to do."""


def _kvark(variant: str, residual: ResidualPredictor, tuning: FilterTuning, trained: "TrainedModel",
           settings: FilterSettings, name: str) -> Observer:
    """The K-VARK filter in the configured measurement form (``filter.measurement``) and implementation
    (``filter.kernel``: the numpy reference or the compiled kernel; the difference form is numpy either way)."""
    form: type[KVARKMomentumFilter] = KVARKMomentumFilter
    if settings.kernel == "numba":          # imported here: numba loads (~0.2 s) only where it is chosen
        from kvark_ros.core.observers.kvark_kernel import KVARKKernelFilter
        form = KVARKKernelFilter
    if settings.measurement == "difference":
        return KVARKFilter(variant, residual, tuning, settings, name=name, sample_period=trained.sample_period)
    if trained.momentum_noise is None:
        raise ObserverError("filter.measurement: momentum needs the model's momentum noise; retrain the model")
    noise = trained.momentum_noise
    if VARIANTS[variant].vb:
        # Σ_d adapts at contact, so its free-motion prior need not track contacts itself (docs/method.md §4.12);
        # the fixed-Σ_d variants keep the training's bandwidth, which must.
        noise = noise.with_bandwidth(settings.prior_bandwidth, trained.sample_period)
    return form(variant, residual, tuning, noise, settings, name=name, sample_period=trained.sample_period)


def make_observer(name: str, trained: "TrainedModel", settings: FilterSettings,
                  oracle: ResidualPredictor | None = None) -> Observer:
    """Build the observer called ``name`` from a trained model and the ``filter.*`` settings.

    The settings' times (seconds) become sample counts at the model's sample period (``PerSample``).

    ``oracle``: the true residual, for the ``oracle`` observer only (the simulator passes its
    plant's friction, ``kvark_ros.sim.plant.OracleResidual``).
    """
    if name in VARIANTS:
        return _kvark(name, trained.residual, trained.tuning, trained, settings, name)
    if name in LEARNED_BASELINE_VARIANTS:
        if name not in trained.baselines:
            raise ObserverError(f"observer '{name}' needs its residual model, which this model directory lacks; "
                                "retrain without --no-baselines")
        return _kvark(LEARNED_BASELINE_VARIANTS[name], trained.baselines[name], trained.baseline_tunings[name],
                      trained, settings, name)
    if name in MOMENTUM_OBSERVER_NAMES:
        return make_momentum_observer(name, len(trained.joint_names), trained.momentum_noise, settings)
    if name == "oracle":
        if oracle is None:
            raise ObserverError("observer 'oracle' needs the simulator's plant file (pass --plant FILE)")
        if trained.augmentation is not None:
            raise ObserverError("observer 'oracle' runs on the plant's own rigid body and friction, but this "
                                "model is augmented (kvark diagnose); use a model trained without augmentation")
        return _kvark("kvark", oracle, trained.tuning, trained, settings, "oracle")
    raise ObserverError(f"unknown observer '{name}'; known: {', '.join(OBSERVER_NAMES)}")
