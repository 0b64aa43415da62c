"""Where a wrist F/T reading is the true end-effector wrench, and where it is not.

A flange sensor measures only what acts beyond the flange. A push on a link before it moves the joints (the true
τ_ext is large) while the sensor reads nothing: taking its 0 N as the truth there would call a correct estimate of
20 N an error of 20 N. The sensor observes the external wrench where that wrench explains the true joint torque,
τ_ext ≈ Jᵀ w (J of the end-effector origin in the wrench's axes), up to the larger of ``CONTACT_TORQUE`` (a
remainder below what counts as contact) and ``UNEXPLAINED_SHARE`` of |τ_ext| (kinematic model differences); free
motion (both zero) counts as observed. Elsewhere the truth wrench is unknown (NaN), so the figures leave it out
and the force RMSE skips it.
"""
from __future__ import annotations

import numpy as np

from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.contact_events import CONTACT_TORQUE

UNEXPLAINED_SHARE = 0.1


def explained_by_wrench(robot: RobotModel, frame: str, q: np.ndarray, tau_ext: np.ndarray,
                        wrench: np.ndarray) -> np.ndarray:
    """(T,) bool: whether the wrench (T, 6) at the end-effector origin in ``frame``'s axes (``base`` or
    ``end_effector``) explains the true joint torque (T, n) N·m at q (T, n) rad (module docstring); False where
    either is not finite."""
    finite = np.isfinite(tau_ext).all(axis=1) & np.isfinite(wrench).all(axis=1)
    remainder = np.full(len(q), np.inf)
    for k in np.flatnonzero(finite):
        remainder[k] = np.abs(tau_ext[k] - robot.jacobian(q[k], frame).T @ wrench[k]).max()
    tolerance = np.maximum(CONTACT_TORQUE, UNEXPLAINED_SHARE * np.abs(np.nan_to_num(tau_ext)).max(axis=1))
    return finite & (remainder <= tolerance)


def sensed_wrench(robot: RobotModel, frame: str, q: np.ndarray, tau_ext: np.ndarray,
                  wrench: np.ndarray) -> np.ndarray:
    """The sensor's wrench (T, 6) as a ground truth: NaN on the samples it does not explain the true torque."""
    return np.where(explained_by_wrench(robot, frame, q, tau_ext, wrench)[:, None], wrench, np.nan)
