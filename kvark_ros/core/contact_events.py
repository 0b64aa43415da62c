"""Contact in a run's ground truth: which samples touch, which are contact-free, where each contact starts and ends.

One definition for the metrics, the plots, the reports and the warnings on training recordings:

- touching: some joint's true |τ_ext| exceeds ``CONTACT_TORQUE`` (a sample without a finite truth does not touch);
- contact-free: not touching and more than ``SETTLE`` s after the last touching sample;
- a contact starts at an onset, a touching sample after one that does not touch and more than ``SETTLE`` s after the
  last touching sample (a truth that dips below the threshold for a moment stays one contact; a contact already
  under way at the first sample was never seen starting and has no onset), and ends after its last touching sample
  before the next onset.
"""
from __future__ import annotations

import numpy as np

CONTACT_TORQUE = 0.5     # N·m: a true external torque above this on any joint is contact
SETTLE = 0.2             # s after a contact before motion counts as contact-free again, or a new contact can start


def touching(truth_tau: np.ndarray) -> np.ndarray:
    """(T,) bool: some joint's true |τ_ext| (T, n) N·m exceeds ``CONTACT_TORQUE``."""
    return (np.abs(np.nan_to_num(truth_tau)) > CONTACT_TORQUE).any(axis=1)


def contact_free(stamp: np.ndarray, touch: np.ndarray) -> np.ndarray:
    """(T,) bool: not touching and more than ``SETTLE`` s after the last touching sample (stamps s, (T,))."""
    last_touch = np.maximum.accumulate(np.where(touch, stamp, -np.inf))
    return ~touch & (stamp - last_touch > SETTLE)


def contacts(stamp: np.ndarray, touch: np.ndarray, limit: int | None = None) -> list[tuple[int, int]]:
    """The first ``limit`` (all by default) contacts as (onset, end) sample indices: ``touch[onset]`` is its first
    touching sample and ``end`` is one past its last (module docstring)."""
    onsets, last_touch = [], -np.inf
    touched = np.flatnonzero(touch)
    for k in touched:
        if k > 0 and not touch[k - 1] and stamp[k] - last_touch > SETTLE:
            onsets.append(int(k))
        last_touch = stamp[k]
    bounds = onsets[1:] + [len(touch)]
    spans = [(onset, int(touched[np.searchsorted(touched, bound) - 1]) + 1) for onset, bound in zip(onsets, bounds)]
    return spans if limit is None else spans[:limit]


def contact_onsets(stamp: np.ndarray, truth_tau: np.ndarray, limit: int | None = None) -> np.ndarray:
    """Stamps (s) of the first ``limit`` contact onsets of the true τ_ext (T, n) (``contacts``)."""
    return np.array([stamp[onset] for onset, _ in contacts(stamp, touching(truth_tau), limit)])
