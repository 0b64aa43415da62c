"""Two-run ground truth: align a reference run (the same motion without the load) to the run in time.

Paper v2 eq. 40 takes the true external torque as the difference of the measured torques of two runs of
the same trajectory, with and without the load. That needs the two runs sample by sample on the same
motion, and recordings rarely start at the same point of it. The shift is the one that minimises the
variance over the overlap of the difference of the joint positions (both resampled on one grid; its cross
term is their cross-correlation, by FFT), refined to a fraction of a sample by a parabola through the
minimum. The variance, not the mean square: a payload sags a tracking arm by a nearly constant offset
(up to 0.03 rad in the simulated payload runs). Runs that already agree when aligned at their first
samples (offset-free RMS under ``START_TOLERANCE`` on every joint) are left so: eq. 40 compares the runs
at the same point of the commanded trajectory, and a heavier arm lags it by a few ms (measured: aligning
the simulated payload pair's motion shifted it by 10 ms and quadrupled the error of the two-run truth).
The reference is then refused when its positions
still differ from the run's by more than ``Q_TOLERANCE`` (RMS on some joint over the overlap): another
motion gives no truth, only a wrong one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.io import BagError

# rad, RMS position difference on the worst joint after alignment that still counts as the same motion: a
# 2 kg payload sags the simulated Panda by up to 0.03 rad (0.019 rad RMS on panda_joint6); another trajectory
# differs by tenths of a radian.
Q_TOLERANCE = 0.05
# rad, RMS (offset removed) per joint below which runs that start together are taken as aligned as they are.
START_TOLERANCE = 0.01
MIN_OVERLAP = 0.5        # share of the run the aligned reference must cover


@dataclass(frozen=True)
class Alignment:
    """shift: s to add to the run's time since its first sample to get the reference's; q_rms: (n,) rad, the
    RMS position difference per joint after the shift; overlap: share of the run the reference covers."""

    shift: float
    q_rms: np.ndarray
    overlap: float


def interpolate(stamp: np.ndarray, source_stamp: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values`` (T', k) at ``stamp``; NaN outside the source's span."""
    out = np.empty((len(stamp), values.shape[1]))
    for column in range(values.shape[1]):
        out[:, column] = np.interp(stamp, source_stamp, values[:, column], left=np.nan, right=np.nan)
    return out


def _grid(inputs: EstimatorInputs, step: float) -> np.ndarray:
    """q (T', n) of ``inputs`` on a uniform grid of ``step`` s from its first sample (inside its span)."""
    elapsed = inputs.stamp - inputs.stamp[0]
    return interpolate(np.arange(0.0, elapsed[-1], step), elapsed, inputs.q)


def _offset_free_misfit(a: np.ndarray, b: np.ndarray, min_overlap: int) -> tuple[np.ndarray, np.ndarray]:
    """Lags L and the variance over the overlap of a[t + L] − b[t], summed over joints (NaN where the overlap is
    short), by FFT.

    Per joint, with d = a[t + L] − b[t] over N overlapping samples: N·var d = Σa² + Σb² − 2Σab − (Σa − Σb)²/N. The
    cross term Σab is the cross-correlation; the other sums come from cumulative sums."""
    from scipy.signal import correlate, correlation_lags    # here: scipy.signal costs replay 0.14 s of start-up
    lags = correlation_lags(len(a), len(b), mode="full")
    first = np.maximum(0, -lags)                          # pairs a[t + L], b[t] for t in [first, last)
    last = np.minimum(len(b), len(a) - lags)
    count = np.maximum(last - first, 1)
    total = np.zeros(len(lags))
    for j in range(a.shape[1]):
        cross = correlate(a[:, j], b[:, j], mode="full", method="fft")
        sa, sa2 = (np.concatenate([[0.0], np.cumsum(x)]) for x in (a[:, j], a[:, j] ** 2))
        sb, sb2 = (np.concatenate([[0.0], np.cumsum(x)]) for x in (b[:, j], b[:, j] ** 2))
        sum_a, sum_b = sa[last + lags] - sa[first + lags], sb[last] - sb[first]
        total += (sa2[last + lags] - sa2[first + lags] + sb2[last] - sb2[first] - 2.0 * cross
                  - (sum_a - sum_b) ** 2 / count) / count
    return lags, np.where(last - first >= min_overlap, total, np.nan)


def align_reference(run: EstimatorInputs, reference: EstimatorInputs, joint_names: Sequence[str],
                    path: str = "reference bag") -> Alignment:
    """The shift that best aligns ``reference``'s positions to ``run``'s (module docstring); ``BagError`` (one
    line) when the aligned positions still disagree or overlap too little."""
    step = float(np.median(np.diff(run.stamp)))
    a, b = _grid(run, step), _grid(reference, step)
    lags, misfit = _offset_free_misfit(a, b, int(MIN_OVERLAP * min(len(a), len(b))))
    if not np.isfinite(misfit).any():
        raise BagError(f"{path}: too short to align with the bag ({len(b)} against {len(a)} samples)")
    if misfit[lags == 0][0] <= a.shape[1] * START_TOLERANCE ** 2:
        shift = 0.0          # aligned at their starts already: keep the commanded-trajectory time (docstring)
    else:
        best = int(np.nanargmin(misfit))
        offset = 0.0
        if 0 < best < len(misfit) - 1 and np.isfinite(misfit[best - 1]) and np.isfinite(misfit[best + 1]):
            left, middle, right = misfit[best - 1], misfit[best], misfit[best + 1]   # parabola through them
            curvature = left - 2.0 * middle + right
            offset = 0.5 * (left - right) / curvature if curvature > 0.0 else 0.0
        shift = -(lags[best] + offset) * step
    elapsed = run.stamp - run.stamp[0]
    reference_q = interpolate(elapsed + shift, reference.stamp - reference.stamp[0], reference.q)
    covered = np.isfinite(reference_q).all(axis=1)
    overlap = float(covered.mean())
    q_rms = (np.sqrt(np.mean((reference_q[covered] - run.q[covered]) ** 2, axis=0)) if covered.any()
             else np.full(run.q.shape[1], np.inf))
    if overlap < MIN_OVERLAP or q_rms.max() > Q_TOLERANCE:
        worst = int(np.argmax(q_rms))
        raise BagError(f"{path}: not the same motion as the bag: after the best time shift ({shift:+.3f} s) it covers "
                       f"{overlap:.0%} of the bag and its positions differ by {q_rms[worst]:.3f} rad RMS on "
                       f"{joint_names[worst]} (tolerance {Q_TOLERANCE} rad over at least {MIN_OVERLAP:.0%}); "
                       "record the "
                       "reference on the same trajectory")
    return Alignment(float(shift), q_rms, overlap)
