"""Warnings when a trained model is used on data it was not trained for. ROS-free.

A model is trained at one sample rate, on one robot, on real or simulated data. Each mismatch below
leaves the estimator running but its figures untrustworthy, so replay, train and the node print one
line for it (the node also puts it on ``/diagnostics``):

- rate: the config's filter times convert to sample counts at the model's rate (``PerSample``), and
  its noise levels were measured per sample at that rate; data more than ``RATE_TOLERANCE`` faster or
  slower get windows and noise of the wrong length;
- robot: the config names another robot than the model (same joint names, e.g. two Panda configs);
- source (offline only: a bag says what wrote it, a live topic does not): a model trained on kvark's
  simulated bags has learnt the simulator's friction, not a real robot's.
"""
from __future__ import annotations

from typing import Any

import numpy as np

RATE_TOLERANCE = 0.2     # relative rate difference that warns: the model's noise levels are per sample


def measured_rate(stamp: np.ndarray) -> float:
    """The data's sample rate, Hz: 1 / median period of ``stamp`` (T,) s; NaN for fewer than two samples."""
    if len(stamp) < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(stamp)))


def rate_warning(model_rate: float, data_rate: float) -> str | None:
    """One line when the data's rate (Hz) differs from the model's by more than ``RATE_TOLERANCE``."""
    if not np.isfinite(data_rate) or abs(data_rate / model_rate - 1.0) <= RATE_TOLERANCE:
        return None
    return (f"warning: the data run at {data_rate:.0f} Hz, the model was trained at {model_rate:.0f} Hz; its filter "
            f"windows and noise levels assume {model_rate:.0f} Hz: train a model on data at this rate")


def data_source(simulated: list[bool]) -> str:
    """What a model was trained on, for ``info.data_source``: ``simulator``, ``recorded`` or ``mixed``."""
    if all(simulated):
        return "simulator"
    return "mixed" if any(simulated) else "recorded"


def model_warnings(trained: Any, robot: str, data_rate: float, simulated: bool | None) -> list[str]:
    """Warning lines for running ``trained`` (a ``TrainedModel``) on data of ``robot`` at ``data_rate`` Hz
    (NaN: not known yet).

    ``simulated``: whether the data come from kvark's simulator (``EstimatorInputs.simulated``); None when
    that is unknown (the node: a live topic does not say), which skips the source check.
    """
    lines = []
    line = rate_warning(trained.sample_rate, data_rate)
    if line:
        lines.append(line)
    if trained.robot != robot:
        lines.append(f"warning: the model was trained for robot '{trained.robot}', the config is for '{robot}'; "
                     "train a model for this robot")
    if trained.info.get("data_source") == "simulator" and simulated is False:
        lines.append("warning: the model was trained on simulated bags only and the data are not simulated; its "
                     "residual is the simulator's friction: train on recordings of this robot (kvark train)")
    return lines
