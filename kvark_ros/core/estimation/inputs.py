"""What the estimator and the trainer consume: one (stamp, q, q̇, τ_m) per joint-state sample."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EstimatorInputs:
    """stamp (T,) s; q (T, n) rad; qd (T, n) rad/s; tau_m (T, n) N·m; what τ_m came from; drops; whether the
    data come from kvark's simulator (a model trained on them is not a real robot's)."""

    stamp: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau_m: np.ndarray
    torque_source: str
    dropped: int
    simulated: bool = False

    def __len__(self) -> int:
        return len(self.stamp)
