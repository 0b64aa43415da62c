"""Build the second paper's residual-free momentum observers (``observer_catalog``): ``momentum``, ``kfmo``,
``sh_akfmo``, ``vbkfmo_q`` and ``eso`` (``momentum_observers``), on the trained model's momentum noise."""
from __future__ import annotations

from typing import TYPE_CHECKING

from kvark_ros.core.config import FilterSettings
from kvark_ros.core.estimation.observers.base import Observer, ResidualPredictor
from kvark_ros.core.estimation.observers.momentum_observers import make_momentum_observer

if TYPE_CHECKING:
    from kvark_ros.core.estimation.model_store import TrainedModel


def build(name: str, trained: "TrainedModel", settings: FilterSettings,
          oracle: ResidualPredictor | None = None) -> Observer:
    """The observer ``name`` for the model's joints (``make_momentum_observer``)."""
    return make_momentum_observer(name, len(trained.joint_names), trained.momentum_noise, settings)
