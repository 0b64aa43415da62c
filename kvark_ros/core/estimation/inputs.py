"""What the estimator and the trainer consume: one (stamp, q, q̇, τ_m) per joint-state sample, and the one way
the commands select samples of a recording (``--trim START END``, ``--rate HZ``)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from kvark_ros.core.config import ConfigError


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

    def take(self, rows: np.ndarray) -> EstimatorInputs:
        """The samples at ``rows`` (indices or a mask), the rest of the description kept."""
        return replace(self, stamp=self.stamp[rows], q=self.q[rows], qd=self.qd[rows], tau_m=self.tau_m[rows])


def trimmed_rows(stamp: np.ndarray, start: float, end: float) -> np.ndarray:
    """Indices of the samples from ``start`` s after the first to ``end`` s before the last (``--trim START END``:
    a start-up, a stop); ConfigError if a duration is negative or the trim leaves fewer than two."""
    if start < 0.0 or end < 0.0:
        raise ConfigError(f"--trim needs two non-negative durations in seconds, got {start} {end}")
    elapsed = stamp - stamp[0]
    keep = np.flatnonzero((elapsed >= start) & (elapsed <= elapsed[-1] - end))
    if len(keep) < 2:
        raise ConfigError(f"--trim {start} {end} leaves {len(keep)} samples of a {elapsed[-1]:.2f} s recording")
    return keep


def decimation_step(stamp: np.ndarray, rate: float) -> int:
    """k of "every k-th sample" for about ``rate`` Hz (``--rate``) from the median period of ``stamp``; 1 for a rate
    of 0 (as recorded) or above the recorded one; ConfigError for a negative rate."""
    if rate < 0.0:
        raise ConfigError(f"--rate {rate:g}: give a rate in Hz, or 0 to keep the recorded one")
    if rate == 0.0 or len(stamp) < 2:
        return 1
    recorded = 1.0 / float(np.median(np.diff(stamp)))
    return max(1, int(round(recorded / rate)))


def select_samples(inputs: EstimatorInputs, trim: tuple[float, float] = (0.0, 0.0),
                   rate: float = 0.0) -> EstimatorInputs:
    """``inputs`` trimmed (``trimmed_rows``) and then decimated to about ``rate`` Hz (``decimation_step``)."""
    kept = trimmed_rows(inputs.stamp, *trim) if tuple(trim) != (0.0, 0.0) else np.arange(len(inputs))
    return inputs.take(kept[::decimation_step(inputs.stamp[kept], rate)])
