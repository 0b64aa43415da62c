"""What the estimator and the trainer consume: one (stamp, q, q̇, τ_m) per joint-state sample, and the one way
the commands select samples of a recording (``--trim START END``, ``--rate HZ``)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from kvark_ros.core.config import ConfigError, EstimatorConfig


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


@dataclass(frozen=True, eq=False)
class EffortCalibration:
    """The rule that turns the values ``input.torque_source`` reads into τ_m (N·m): ``τ_m = scale ⊙ value + offset``
    per joint (``input.effort_scale``, ``input.effort_offset``; a motor current in A times N·m/A), applied by the
    node to every message and by every command to a bag's samples, so both see the same τ_m. scale, offset: (n,)."""

    scale: np.ndarray
    offset: np.ndarray

    @classmethod
    def from_config(cls, config: EstimatorConfig) -> EffortCalibration:
        """The config's keys, a single value repeated for every joint."""
        n = config.n_joints
        return cls(np.broadcast_to(np.asarray(config.input.effort_scale, dtype=float), (n,)).copy(),
                   np.broadcast_to(np.asarray(config.input.effort_offset, dtype=float), (n,)).copy())

    @property
    def identity(self) -> bool:
        """Whether τ_m is the value as read (scale 1, offset 0): nothing to apply."""
        return bool((self.scale == 1.0).all() and (self.offset == 0.0).all())

    def apply(self, values: np.ndarray) -> np.ndarray:
        """τ_m of ``values``: (n,) or (T, n), in the joints' order."""
        return values * self.scale + self.offset

    def to_inputs(self, inputs: EstimatorInputs) -> EstimatorInputs:
        """``inputs`` with τ_m through ``apply`` (the same object when ``identity``)."""
        return inputs if self.identity else replace(inputs, tau_m=self.apply(inputs.tau_m))


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
