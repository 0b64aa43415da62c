"""Build K-VARK, its ablations A1-A4 and the oracle (``observer_catalog``): one ``build`` for the filter family.

The filter runs in the configured measurement form (``filter.measurement``): the momentum form compiled
(``kvark.KVARKFilter``), the difference form as numpy (``kvark_difference.KVARKDifferenceFilter``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.estimation.observers.base import Observer, ObserverError, ResidualPredictor
from kvark_ros.core.estimation.observers.kvark import KVARKFilter
from kvark_ros.core.estimation.observers.kvark_difference import KVARKDifferenceFilter
from kvark_ros.core.estimation.observers.variants import VARIANTS

if TYPE_CHECKING:
    from kvark_ros.core.estimation.model_store import TrainedModel
    from kvark_ros.core.estimation.observers.base import FilterTuning


def kvark_filter(variant: str, residual: ResidualPredictor, tuning: "FilterTuning", trained: "TrainedModel",
                 settings: FilterSettings, name: str) -> Observer:
    """The K-VARK filter ``variant`` (a key of ``VARIANTS``) on ``residual`` with ``tuning``, reported as ``name``."""
    if settings.measurement == "difference":
        return KVARKDifferenceFilter(variant, residual, tuning, settings, name=name,
                                     sample_period=trained.sample_period)
    if trained.momentum_noise is None:
        raise ObserverError("filter.measurement: momentum needs the model's momentum noise; retrain the model")
    noise, contact = trained.momentum_noise, None
    if VARIANTS[variant].vb:
        # Σ_d adapts at contact, so its free-motion prior need not track contacts itself (docs/method.md §4.12);
        # the fixed-Σ_d variants keep the training's bandwidth, which must.
        noise = noise.with_bandwidth(settings.prior_bandwidth, trained.sample_period)
        if settings.onset_contact_bandwidth > 0.0:                     # the least Σ_d after an accepted onset (§4.7)
            contact = noise.with_bandwidth(settings.onset_contact_bandwidth, trained.sample_period).torque_density
    return KVARKFilter(variant, residual, tuning, noise, settings, name=name, sample_period=trained.sample_period,
                       contact_density=contact)


def build(name: str, trained: "TrainedModel", settings: FilterSettings,
          oracle: ResidualPredictor | None = None) -> Observer:
    """``kvark``, ``kf``, ``kmp_kf``, ``kmp_kf_ewma``, ``kmp_kf_nis`` on the trained KMP, or ``oracle``: the
    ``kvark`` filter on the simulator's true residual (``oracle``: ``kvark_ros.sim.plant.OracleResidual``)."""
    if name in VARIANTS:
        return kvark_filter(name, trained.residual, trained.tuning, trained, settings, name)
    if name != "oracle":
        raise ObserverError(f"'{name}' is not an observer of the K-VARK family ({', '.join(VARIANTS)}, oracle)")
    if oracle is None:
        raise ObserverError("observer 'oracle' needs the simulator's plant file (pass --plant FILE)")
    if trained.augmentation is not None:
        raise ObserverError("observer 'oracle' runs on the plant's own rigid body and friction, but this "
                            "model is augmented (kvark diagnose); use a model trained without augmentation")
    return kvark_filter("kvark", oracle, trained.tuning, trained, settings, "oracle")
