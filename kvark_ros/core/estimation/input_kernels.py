"""The compiled checks of one input sample (``Estimator.step``, docs/method.md §4.8): finite values and a driver's
re-sent state. They take no layout and call no other kernel, so numba's cache, keyed on this file, stays exact
(``step_kernel``'s module docstring)."""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.estimation.step_kernel import jit


@jit
def finite_sample(stamp: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> bool:
    """Whether stamp + q·q + q̇·q̇ + τ_m·τ_m is finite: no NaN or Inf, no |x| > ~1e154 (the reference's test)."""
    total = stamp
    for j in range(q.shape[0]):
        total += q[j] * q[j] + qd[j] * qd[j] + tau_m[j] * tau_m[j]
    return math.isfinite(total)


# A joint moving this far (rad) in one period must show it in q: far above q's floating-point rounding (~1e-15 rad),
# far below any encoder's step.
STALE_MOTION = 1e-9


@jit
def repeated_sample(dt: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray, last: np.ndarray) -> bool:
    """Whether q, q̇ and τ_m (n,) equal ``last``'s rows 0-2 (3, n) exactly although some joint moved more than
    ``STALE_MOTION`` in the ``dt`` s since: a driver that re-sent its last state under a new stamp (docs/method.md
    §4.8); an arm at rest may repeat its state exactly (a noise-free simulator). Otherwise the sample is stored in
    ``last`` for the next call."""
    n = q.shape[0]
    same, moved = True, False
    for j in range(n):
        if q[j] != last[0, j] or qd[j] != last[1, j] or tau_m[j] != last[2, j]:
            same = False
            break
        moved = moved or abs(qd[j]) * dt > STALE_MOTION
    if not same:
        for j in range(n):
            last[0, j], last[1, j], last[2, j] = q[j], qd[j], tau_m[j]
    return same and moved
