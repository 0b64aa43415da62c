"""Calibration of K-VARK's reported τ̂ interval on contact-free training data (docs/method.md §4.13).

The filter's covariance P follows from its noise model, and that model is only as right as its
assumptions: on the realistic simulated Panda the drifting friction and offset make the contact-free
τ̂ 1.4-2.4 times its σ, on the real Panda the torque noise that is white at the sample scale but not
within the filter's band makes it 0.2-0.3 times its σ. On contact-free data the true τ_ext is zero, so
τ̂ itself is the error, and the factor c_j that puts ``COVERAGE`` of the training τ̂_j inside ±1.96 c_j σ_j
can be read off the training recordings. The estimator reports c² P (each joint's row and column scaled
by c), each variance raised to at least the floor: under a load the contact test holds, P_b (the steady-state
variance of the fixed-Σ_d ``kf`` at the contact bandwidth ω_b: the adaptive filter never claims to know τ_ext better
than that filter would), in free motion c_b² P_b (``kf``'s interval as the same training data show it,
docs/method.md §4.13), plus the static friction band's σ²_s (core.estimation.stiction), and so the wrench
covariance; the filter, its gain and the contact and collision tests keep P. c is read for the interval without the
floor (which only widens it): near rest the band already covers part of the misfit, so the factor needed there is
smaller. The factors and the floor are read at training (``core.learning.interval_factors``); this module holds them
and the compiled post-step applies them (``compiled.post``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

COVERAGE = 0.95               # share of contact-free τ̂ inside ±1.96 c σ
CALIBRATED_OBSERVER = "kvark"  # the estimator the factors were read for (the observers differ in their P)


@dataclass(frozen=True)
class IntervalScale:
    """c (n,) per joint, the variance floor P_b (n,) N²·m² and its free-motion factor c_b (n,) in (0, 1]: reported
    Cov τ̂ = diag(c) P diag(c) for ``CALIBRATED_OBSERVER``, each variance at least c_b² P_b in free motion and P_b
    under a load (floor zeros: no floor, as in models trained before it; factor ones: P_b everywhere, as in models
    trained before it)."""

    scale: np.ndarray
    floor: np.ndarray | None = None
    floor_factor: np.ndarray | None = None

    def __post_init__(self) -> None:
        scale = np.array(self.scale, dtype=float)
        if scale.ndim != 1 or not np.all(np.isfinite(scale)) or np.any(scale <= 0.0):
            raise ValueError(f"interval scale must be positive finite numbers, one per joint, got {self.scale}")
        floor = np.zeros_like(scale) if self.floor is None else np.array(self.floor, dtype=float)
        if floor.shape != scale.shape or not np.all(np.isfinite(floor)) or np.any(floor < 0.0):
            raise ValueError(f"interval floor must be non-negative finite variances, one per joint, got {self.floor}")
        factor = np.ones_like(scale) if self.floor_factor is None else np.array(self.floor_factor, dtype=float)
        if factor.shape != scale.shape or not np.all((factor > 0.0) & (factor <= 1.0)):
            raise ValueError(f"interval floor factor must be in (0, 1], one per joint, got {self.floor_factor}")
        for name, value in (("scale", scale), ("floor", floor), ("floor_factor", factor),
                            ("free_floor", factor * factor * floor)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def floor_for(self, loaded: bool) -> np.ndarray:
        """The floor (n,) N²·m² in force: P_b while the contact test holds a load, c_b² P_b in free motion."""
        return self.floor if loaded else self.free_floor

    def to_dict(self) -> dict[str, Any]:
        return {"observer": CALIBRATED_OBSERVER, "coverage": COVERAGE, "scale": self.scale.tolist(),
                "floor": self.floor.tolist(), "floor_factor": self.floor_factor.tolist()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "IntervalScale":
        if values.get("observer") != CALIBRATED_OBSERVER:
            raise ValueError(f"interval scale for observer {values.get('observer')!r}, expected {CALIBRATED_OBSERVER}")
        floor, factor = values.get("floor"), values.get("floor_factor")
        return cls(np.asarray(values["scale"], dtype=float), None if floor is None else np.asarray(floor, dtype=float),
                   None if factor is None else np.asarray(factor, dtype=float))
