"""External-torque observers, each selectable by name (config key ``observer``, CLI ``--observer``)."""
from __future__ import annotations

from kvark_ros.core.config import OBSERVER_NAMES, EstimatorConfig
from kvark_ros.core.observers.base import FilterTuning, Observer
from kvark_ros.core.observers.kvark_filter import VARIANTS, KVARKFilter
from kvark_ros.core.residual_model import KMPResidualModel

__all__ = ["FilterTuning", "Observer", "KVARKFilter", "make_observer", "OBSERVER_NAMES"]


def make_observer(name: str, residual: KMPResidualModel, tuning: FilterTuning,
                  config: EstimatorConfig) -> Observer:
    """Build the observer called ``name`` (one of ``OBSERVER_NAMES``)."""
    if name in VARIANTS:
        return KVARKFilter(name, residual, tuning, config)
    raise ValueError(f"unknown observer '{name}'; known: {', '.join(OBSERVER_NAMES)}")
