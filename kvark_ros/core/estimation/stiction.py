"""Stiction-aware uncertainty: a joint at rest holds any friction torque in its static band. ROS-free.

A sliding joint's friction is a function of its velocity, which the residual model learns. A joint at
rest is different: its friction is whatever keeps it at rest, anywhere in [−F_s, F_s], and the measured
torque cannot tell that friction from an external torque (a simulated UR5 pushed at standstill holds up to
about 18 N of it at the tool after each push). So near q̇_j = 0 the external torque is known only up to that band.

The band F_s,j is identified at training from the friction the model sees: the residual τ_r plus the
augmentation's friction effects (docs/method.md §4.11), as half the jump of its median across zero
velocity, from samples sliding slowly either way (``SLOW``: above the velocity noise, below the speeds
where friction falls from its static to its sliding level), with τ_m and q̈ through a 50 ms filter
(``core.learning.static_band``, ``training.band_friction``). The estimate is not changed; its interval is widened by the
variance of a torque uniform on ±F_s,

    σ²_s,j(q̇_j) = F_s,j² / 3 · exp(−(q̇_j / v_s)²),

at rest fully (±1.96 σ_s = ±1.13 F_s covers the whole band) and gone once the joint slides faster than
a few v_s = ``filter.stiction_velocity``. The contact and collision tests use the widened S, so a
joint that sticks with a torque in its band does not flag contact.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np



@dataclass(frozen=True)
class StictionBand:
    """band: (n,) N·m, the static friction band F_s per joint (0 where none was found)."""

    band: np.ndarray

    def variance(self, qd: np.ndarray, velocity: float) -> np.ndarray:
        """σ²_s (n,) N²·m² at joint velocities ``qd`` (n,) rad/s; ``velocity`` is v_s, rad/s (module docstring)."""
        return self.band * self.band / 3.0 * np.exp(-np.square(qd / velocity))

    def to_dict(self) -> dict[str, Any]:
        return {"band": [float(v) for v in self.band]}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "StictionBand":
        band = np.asarray(values["band"], dtype=float)
        if band.ndim != 1 or not np.all(np.isfinite(band)) or np.any(band < 0):
            raise ValueError("stiction band must be finite and non-negative")
        return cls(band)
