"""The compiled checks of one input sample (``Estimator.step``, docs/method.md §4.8): finite values within the URDF's
limits (``core.estimation.sample_limits``), a stamp after the previous one, and a driver's re-sent state.
``check_sample`` returns one of the codes below (plain ints: the estimator maps them to its ``Status``)."""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.estimation.compiled.jit import jit

PINS: dict[str, str] = {}

ACCEPTED, NON_FINITE, NOT_INCREASING, REPEATED, BEYOND_LIMITS = 0, 1, 2, 3, 4

# A joint moving this far (rad) in one period must show it in q: far above q's floating-point rounding (~1e-15 rad),
# far below any encoder's step.
STALE_MOTION = 1e-9


@jit
def check_sample(stamp: float, previous: float, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray,
                 last: np.ndarray, bounds: np.ndarray) -> int:
    """Check one sample (stamp s; q, q̇, τ_m (n,)) against the previous one (its stamp ``previous``, NaN after a
    (re)start, and its q, q̇, τ_m in ``last``'s rows 0-2, (3, n)) and ``bounds`` (2, 3n): the lowest and highest
    [q, q̇, τ_m] a real arm can hold (``SampleLimits.bounds``):

    - NON_FINITE: stamp + q·q + q̇·q̇ + τ_m·τ_m is not finite (NaN or Inf, or some |x| > ~1e154);
    - BEYOND_LIMITS: some q, q̇ or τ_m outside its bounds;
    - NOT_INCREASING: the stamp is not after the previous one (out of order or a duplicate);
    - REPEATED: q, q̇ and τ_m equal the previous sample's exactly although some joint moved more than
      ``STALE_MOTION`` in the time since: a driver that re-sent its last state under a new stamp (§4.8; an arm at
      rest may repeat its state exactly, as a noise-free simulator does);
    - ACCEPTED: otherwise, and the sample is kept in ``last`` for the next call.
    """
    n = q.shape[0]
    total = stamp
    for j in range(n):
        total += q[j] * q[j] + qd[j] * qd[j] + tau_m[j] * tau_m[j]
    if not math.isfinite(total):
        return NON_FINITE
    for j in range(n):
        if not (bounds[0, j] <= q[j] <= bounds[1, j] and bounds[0, n + j] <= qd[j] <= bounds[1, n + j]
                and bounds[0, 2 * n + j] <= tau_m[j] <= bounds[1, 2 * n + j]):
            return BEYOND_LIMITS
    if not math.isnan(previous):
        if stamp <= previous:
            return NOT_INCREASING
        dt = stamp - previous
        same, moved = True, False
        for j in range(n):
            if q[j] != last[0, j] or qd[j] != last[1, j] or tau_m[j] != last[2, j]:
                same = False
                break
            moved = moved or abs(qd[j]) * dt > STALE_MOTION
        if same and moved:
            return REPEATED
    for j in range(n):
        last[0, j], last[1, j], last[2, j] = q[j], qd[j], tau_m[j]
    return ACCEPTED
