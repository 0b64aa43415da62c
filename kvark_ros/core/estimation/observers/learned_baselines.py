"""Build the learned-residual baselines (``observer_catalog``): each one's residual model in a K-VARK variant.

``gmr_gp`` (GMR reference → GP residual) runs in ``kvark``, ``gpadkf`` (sparse GP) in ``kmp_kf_ewma`` and
``nnadkf`` (MLP mean) in ``kf``; the residual models and their tunings are trained with the K-VARK model
(``kvark train``, unless ``--no-baselines``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.estimation.observers.base import Observer, ObserverError, ResidualPredictor
from kvark_ros.core.estimation.observers.kvark_family import kvark_filter

if TYPE_CHECKING:
    from kvark_ros.core.estimation.model_store import TrainedModel

# The K-VARK filter variant each learned residual runs in.
LEARNED_BASELINE_VARIANTS = {"gmr_gp": "kvark", "gpadkf": "kmp_kf_ewma", "nnadkf": "kf"}


def build(name: str, trained: "TrainedModel", settings: FilterSettings,
          oracle: ResidualPredictor | None = None) -> Observer:
    """The baseline ``name`` (a key of ``LEARNED_BASELINE_VARIANTS``) on its trained residual model."""
    if name not in LEARNED_BASELINE_VARIANTS:
        raise ObserverError(f"'{name}' is not a learned baseline ({', '.join(LEARNED_BASELINE_VARIANTS)})")
    if name not in trained.baselines:
        raise ObserverError(f"observer '{name}' needs its residual model, which this model directory lacks; "
                            "retrain without --no-baselines")
    return kvark_filter(LEARNED_BASELINE_VARIANTS[name], trained.baselines[name], trained.baseline_tunings[name],
                        trained, settings, name)
