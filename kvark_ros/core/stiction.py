"""Stiction-aware uncertainty: a joint at rest holds any friction torque in its static band. ROS-free.

A sliding joint's friction is a function of its velocity, which the residual model learns. A joint at
rest is different: its friction is whatever keeps it at rest, anywhere in [−F_s, F_s], and the measured
torque cannot tell that friction from an external torque (issue 17 measured ±18 N at a UR5's tool
after each push at standstill). So near q̇_j = 0 the external torque is known only up to that band.

The band F_s,j is identified at training from the friction the model sees: the residual τ_r plus the
augmentation's friction effects (docs/method.md §4.11), as half the jump of its median across zero
velocity, from samples sliding slowly either way (``SLOW``: above the velocity noise, below the speeds
where friction falls from its static to its sliding level), with τ_m and q̈ through a 50 ms filter
(``training.band_friction``). The estimate is not changed; its interval is widened by the variance of a
torque uniform on ±F_s,

    σ²_s,j(q̇_j) = F_s,j² / 3 · exp(−(q̇_j / v_s)²),

at rest fully (±1.96 σ_s = ±1.13 F_s covers the whole band) and gone once the joint slides faster than
a few v_s = ``filter.stiction_velocity``. The contact and collision tests use the widened S, so a
joint that sticks with a torque in its band does not flag contact.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

# rad/s: the slow sliding the band is read from: |q̇| in [SLOW[0], SLOW[1]], the upper end doubled up to 3
# times (0.32 rad/s) where a joint has fewer than MIN_SAMPLES each way. The upper end stays below the
# Stribeck velocities of arm joints (0.04-0.1 rad/s), over which friction falls to its sliding level: a
# window to 0.1 rad/s read 75-87 % of the simulated Panda's static levels, this one 87-102 % (docs/method.md
# §4.11).
SLOW = (0.01, 0.04)
MIN_SAMPLES = 20
FRICTION_EFFECTS = ("coulomb_friction", "stribeck_friction", "viscous_friction")


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


def friction_torque(tau_r: np.ndarray, augmentation: Any, q: np.ndarray, qd: np.ndarray,
                    tau_m: np.ndarray) -> np.ndarray:
    """The friction the model sees (T, n) N·m: the residual plus the augmentation's friction effects (which the
    augmented model already subtracted from τ_r)."""
    if augmentation is None:
        return tau_r
    friction = [effect for effect in augmentation.torque_effects if effect.name in FRICTION_EFFECTS]
    if not friction:
        return tau_r
    return tau_r + replace(augmentation, torque_effects=tuple(friction)).joint_torque(q, qd, tau_m)


def identify_band(qd: np.ndarray, friction: np.ndarray) -> np.ndarray:
    """F_s (n,) N·m: half the jump of the median friction (T, n) across q̇ (T, n) = 0 (module docstring)."""
    n = qd.shape[1]
    band = np.zeros(n)
    for j in range(n):
        low, high = SLOW
        for _ in range(4):
            forward = (qd[:, j] >= low) & (qd[:, j] <= high)
            backward = (qd[:, j] <= -low) & (qd[:, j] >= -high)
            if forward.sum() >= MIN_SAMPLES and backward.sum() >= MIN_SAMPLES:
                jump = np.median(friction[forward, j]) - np.median(friction[backward, j])
                band[j] = max(0.5 * jump, 0.0)
                break
            high *= 2.0
    return band
