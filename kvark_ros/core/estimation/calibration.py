"""Calibration of K-VARK's reported τ̂ interval on contact-free training data (docs/method.md §4.13).

The filter's covariance P follows from its noise model, and that model is only as right as its
assumptions: on the realistic simulated Panda the drifting friction and offset make the contact-free
τ̂ 1.4-2.4 times its σ, on the real Panda the torque noise that is white at the sample scale but not
within the filter's band makes it 0.2-0.3 times its σ. On contact-free data the true τ_ext is zero, so
τ̂ itself is the error, and the factor c_j that puts ``COVERAGE`` of the training τ̂_j inside ±1.96 c_j σ_j
can be read off the training recordings. The estimator reports c² P (each joint's row and column scaled
by c) plus the static friction band's σ²_s (core.estimation.stiction), and so the wrench covariance; the filter, its
gain and the contact and collision tests keep P. c is read for that whole reported interval: near rest the band
already covers part of the misfit, so the factor needed there is smaller. The factors are read at training
(``core.learning.interval_factors``); this module holds them and applies them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

COVERAGE = 0.95               # share of contact-free τ̂ inside ±1.96 c σ
CALIBRATED_OBSERVER = "kvark"  # the estimator the factors were read for (the observers differ in their P)


@dataclass(frozen=True)
class IntervalScale:
    """c (n,) per joint: reported Cov τ̂ = diag(c) P diag(c) for ``CALIBRATED_OBSERVER``."""

    scale: np.ndarray

    def __post_init__(self) -> None:
        scale = np.array(self.scale, dtype=float)
        if scale.ndim != 1 or not np.all(np.isfinite(scale)) or np.any(scale <= 0.0):
            raise ValueError(f"interval scale must be positive finite numbers, one per joint, got {self.scale}")
        scale.setflags(write=False)
        object.__setattr__(self, "scale", scale)

    def apply(self, covariance: np.ndarray) -> np.ndarray:
        """diag(c) P diag(c) of a (n, n) covariance, N²·m²."""
        return covariance * np.outer(self.scale, self.scale)

    def to_dict(self) -> dict[str, Any]:
        return {"observer": CALIBRATED_OBSERVER, "coverage": COVERAGE, "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "IntervalScale":
        if values.get("observer") != CALIBRATED_OBSERVER:
            raise ValueError(f"interval scale for observer {values.get('observer')!r}, expected {CALIBRATED_OBSERVER}")
        return cls(np.asarray(values["scale"], dtype=float))
