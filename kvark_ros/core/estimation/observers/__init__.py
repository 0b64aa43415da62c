"""External-torque observers, each selectable by name (config key ``observer``, CLI ``--observers``).

The names, what each one is and the module that builds it are one table, ``kvark_ros.core.observer_catalog``
(``kvark replay --help`` lists them); ``make_observer`` imports only the module of the observer asked for.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.observer_catalog import OBSERVER_NAMES, OBSERVERS_BY_NAME
from kvark_ros.core.estimation.observers.base import FilterTuning, Observer, ObserverError, ResidualPredictor
from kvark_ros.core.estimation.observers.learned_baselines import LEARNED_BASELINE_VARIANTS

if TYPE_CHECKING:
    from kvark_ros.core.estimation.model_store import TrainedModel

__all__ = ["FilterTuning", "Observer", "ObserverError", "LEARNED_BASELINE_VARIANTS", "make_observer", "OBSERVER_NAMES",
           "ResidualPredictor"]


def make_observer(name: str, trained: "TrainedModel", settings: FilterSettings,
                  oracle: ResidualPredictor | None = None) -> Observer:
    """Build the observer called ``name`` from a trained model and the ``filter.*`` settings.

    The settings' times (seconds) become sample counts at the model's sample period (``PerSample``).

    ``oracle``: the true residual, for the ``oracle`` observer only (the simulator passes its
    plant's friction, ``kvark_ros.sim.plant.OracleResidual``).
    """
    entry = OBSERVERS_BY_NAME.get(name)
    if entry is None:
        raise ObserverError(f"unknown observer '{name}'; known: {', '.join(OBSERVER_NAMES)}")
    return importlib.import_module(entry.module).build(name, trained, settings, oracle)
