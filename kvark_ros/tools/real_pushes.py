"""Known pushes added to a real contact-free recording: contact tracking measured on a real robot's own data.

A contact-free recording says how much false τ_ext an observer makes, not how it follows a contact. A force
sensor would; most arms have none. A stiffly position-controlled arm holds its path under a push, so its drives
take the push up: the measured torque changes by −τ_ext and q, q̇ stay as recorded (``M q̈ + C q̇ + g + τ_f = τ_m
+ τ_ext``, docs/method.md §1.2). So a push of known force F at the end-effector origin is superposed on the
recording as

    τ_ext,k = J(q_k)ᵀ [F_k; 0],     τ_m,k ← τ_m,k − τ_ext,k,

J the end-effector Jacobian in the axes of ``wrench.frame``, and every observer is judged against that τ_ext with
the robot's own noise, friction and model misfit around it. What it leaves out: the small path deviation and the
transient of a real arm's position loop, and (on motor-current arms) the drive-gain error the push's current would
pass through. Each push ramps up over ``RAMP`` s, holds for ``HOLD`` s and ramps down, one every ``PERIOD`` s from
``FIRST`` s on, along the axes in ``DIRECTIONS`` in turn.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.tools.replay import GroundTruth

FIRST = 0.5        # s from the start of the held-out part to the first push (the filters' warm-up)
RAMP = 0.1         # s each push takes to rise and to fall (a hand or a tool meeting the arm)
HOLD = 1.0         # s each push holds its full force: a sustained contact, as in polishing or assembly
PERIOD = 3.0       # s from one push to the next: 1.8 s free motion after each, for the recovery
SETTLE = 0.3       # s of data a push must leave after it ends to count
DIRECTIONS = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0],
                       [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])   # +x, +y, −z (pressing down), ...


@dataclass(frozen=True)
class Pushes:
    """The pushed recording: ``inputs`` (τ_m less τ_ext), ``truth`` (τ_ext (T, n) N·m, wrench (T, 6) N, N·m),
    ``active`` (T,) bool where a push acts, ``after`` (T,) bool the free motion from ``SETTLE`` s after a push ends
    to the next, and ``starts`` the push start times (s from the first sample)."""

    inputs: EstimatorInputs
    truth: GroundTruth
    active: np.ndarray
    after: np.ndarray
    starts: list[float]


def push_profile(time: np.ndarray, force: float) -> tuple[np.ndarray, list[float]]:
    """(T, 3) force N along the wrench axes at ``time`` (T,) s from the first sample, and the push start times:
    trapezoids of ``force`` N (module docstring) that end ``SETTLE`` s before the data does."""
    if not np.isfinite(force) or force <= 0.0:
        raise ValueError(f"push force {force!r} N: give a positive number of newtons")
    starts = list(np.arange(FIRST, time[-1] - 2 * RAMP - HOLD - SETTLE, PERIOD))
    if not starts:
        raise ValueError(f"the held-out part lasts {time[-1]:.1f} s; a push needs "
                         f"{FIRST + 2 * RAMP + HOLD + SETTLE:.1f} s (record longer or lower --train-share)")
    profile = np.zeros((len(time), 3))
    for index, start in enumerate(starts):
        rising = np.clip((time - start) / RAMP, 0.0, 1.0)
        falling = np.clip((start + 2 * RAMP + HOLD - time) / RAMP, 0.0, 1.0)
        profile += np.outer(np.minimum(rising, falling), force * DIRECTIONS[index % len(DIRECTIONS)])
    return profile, [float(s) for s in starts]


def pushed(robot: RobotModel, frame: str, inputs: EstimatorInputs, force: float) -> Pushes:
    """``inputs`` with pushes of ``force`` N superposed (module docstring); ``frame``: ``wrench.frame``."""
    time = inputs.stamp - inputs.stamp[0]
    profile, starts = push_profile(time, force)
    wrench = np.hstack([profile, np.zeros_like(profile)])
    tau_ext = np.array([robot.jacobian(q, frame).T @ w for q, w in zip(inputs.q, wrench)])
    active = np.abs(profile).sum(axis=1) > 0.0
    after = np.zeros(len(time), dtype=bool)
    for start in starts:
        end = start + 2 * RAMP + HOLD
        after |= (time >= end + SETTLE) & (time < start + PERIOD)
    truth = GroundTruth(f"pushes of {force:g} N superposed on the recording", tau_ext, wrench)
    return Pushes(replace(inputs, tau_m=inputs.tau_m - tau_ext), truth, active, after, starts)


def phase_rmse(result: Any, pushes: Pushes) -> dict[str, float | None]:
    """Joint RMSE (mean over joints, N·m) while the pushes act (``during``) and in the free motion after them
    (``after``): how closely an observer follows a contact, and how cleanly it lets go."""
    error = result.tau_ext - pushes.truth.tau_ext

    def rmse(rows: np.ndarray) -> float | None:
        rows = rows & result.valid
        return round(float(np.sqrt(np.mean(error[rows] ** 2, axis=0)).mean()), 6) if rows.any() else None

    return {"during": rmse(pushes.active), "after": rmse(pushes.after)}
