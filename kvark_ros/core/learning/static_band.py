"""Identifying the static friction band F_s per joint from contact-free training data (docs/method.md §4.11).

F_s,j is half the jump of the median friction the model sees (the residual plus the augmentation's friction
effects) across zero velocity, from samples sliding slowly either way; ``core.estimation.stiction`` holds the band
and widens the reported interval with it.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from kvark_ros.core.effect_catalog import FRICTION_EFFECTS

# rad/s: the slow sliding the band is read from: |q̇| in [SLOW[0], SLOW[1]], the upper end doubled up to 3
# times (0.32 rad/s) where a joint has fewer than MIN_SAMPLES each way. The upper end stays below the
# Stribeck velocities of arm joints (0.04-0.1 rad/s), over which friction falls to its sliding level: a
# window to 0.1 rad/s read 75-87 % of the simulated Panda's static levels, this one 87-102 % (docs/method.md
# §4.11).
SLOW = (0.01, 0.04)
MIN_SAMPLES = 20


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
