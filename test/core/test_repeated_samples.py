"""A stale sample (q, q̇ and τ_m repeated exactly under a new stamp while the arm moves) is rejected, and the next
fresh sample's step spans both periods (docs/method.md §4.8): the estimates equal those without the repeat."""
from __future__ import annotations

import math

import numpy as np

from kvark_ros.core.estimation.estimator import Estimator, Status
from kvark_ros.core.estimation.compiled.inputs import (ACCEPTED, NON_FINITE, NOT_INCREASING, REPEATED, STALE_MOTION,
                                                       check_sample)
from kvark_ros.tools.synthetic import step_torque, synthetic_stream


def test_repeats_while_moving_change_no_estimate(panda_config, panda_trained, panda):
    """Every 7th sample re-sent under a stamp halfway to the next: every fresh sample's estimate (τ̂, P, contact)
    equals the clean run's bit for bit, and each repeat is counted as one."""
    stream = synthetic_stream(panda, 2.0, seed=5, external=step_torque(0.7, np.full(7, 2.0)))
    clean = Estimator.from_config(panda_config, panda_trained)
    stale = Estimator.from_config(panda_config, panda_trained)
    repeats = 0
    for k in range(len(stream.stamp)):
        sample = (stream.q[k], stream.qd[k], stream.tau_m[k])
        a, b = clean.step(stream.stamp[k], *sample), stale.step(stream.stamp[k], *sample)
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.tau_ext, b.tau_ext) and np.array_equal(a.tau_cov, b.tau_cov)
            assert a.contact == b.contact
        if k % 7 == 3 and k + 1 < len(stream.stamp):
            halfway = 0.5 * (stream.stamp[k] + stream.stamp[k + 1])
            assert stale.step(halfway, *sample) is None and stale.status == Status.REPEATED
            repeats += 1
    assert stale.counts[Status.REPEATED] == repeats > 0


BOUNDS = np.stack((np.full(21, -1e3), np.full(21, 1e3)))   # bounds no sample here reaches (a test of its own below)


def test_a_repeat_at_rest_is_a_sample():
    """An arm at rest may repeat its state exactly (a noise-free simulator): not stale. Moving, it is; a motion too
    small for q to show (below STALE_MOTION in the period) is not."""
    q, tau = np.array([0.1, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]), np.ones(7)
    last = np.full((3, 7), np.nan)

    def check(stamp: float, previous: float, qd: np.ndarray) -> int:
        return check_sample(stamp, previous, q, qd, tau, last, BOUNDS)

    assert check(0.0, math.nan, np.zeros(7)) == ACCEPTED                     # first: remembered
    assert check(0.002, 0.0, np.zeros(7)) == ACCEPTED                        # at rest
    moving = np.full(7, 0.1)
    assert check(0.004, 0.002, moving) == ACCEPTED                           # q̇ changed: fresh
    assert check(0.006, 0.004, moving) == REPEATED                           # the same while moving: stale
    creeping = np.full(7, 0.5 * STALE_MOTION / 0.002)
    assert check(0.008, 0.006, creeping) == ACCEPTED
    assert check(0.010, 0.008, creeping) == ACCEPTED


def test_the_input_check_refuses_what_cannot_be_estimated():
    """A NaN, an Inf or a value whose square overflows is NON_FINITE; a stamp at or before the previous one is
    NOT_INCREASING (checked before a repeat); neither is remembered for the next check."""
    q, qd, tau, last = np.zeros(7), np.full(7, 0.1), np.ones(7), np.full((3, 7), np.nan)
    assert check_sample(1.0, math.nan, q, qd, tau, last, BOUNDS) == ACCEPTED
    for bad in (np.nan, np.inf, 1e155):
        assert check_sample(1.002, 1.0, np.full(7, bad), qd, tau, last, BOUNDS) == NON_FINITE
    assert check_sample(1.0, 1.0, q, qd, tau, last, BOUNDS) == NOT_INCREASING
    assert check_sample(0.9, 1.0, q, qd + 1.0, tau, last, BOUNDS) == NOT_INCREASING
    np.testing.assert_array_equal(last, [q, qd, tau])


def test_a_sample_beyond_the_urdf_limits_is_rejected_and_counted(panda_config, panda_trained, panda):
    """The Panda's joint 4 is limited to [−3.0718, −0.0698] rad, with the 0.1 rad margin [−3.1718, 0.0302]: q4 = 0.02
    is within, 0.05 beyond; a velocity of 2 × its 2.175 rad/s limit + 0.01 and a torque of 2 × 87 N·m + 1 are beyond
    too. Each is rejected with its own status, counted, remembered by no check, and the filter goes on."""
    estimator = Estimator.from_config(panda_config, panda_trained)
    q = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8])
    zeros, tau = np.zeros(7), panda.gravity(q)
    assert estimator.step(0.0, q, zeros, tau) is None and estimator.step(0.002, q, zeros, tau) is not None
    inside = q.copy()
    inside[3] = 0.02
    assert estimator.limits.violation(inside, zeros, tau) == 0
    for k, (bad_q, bad_qd, bad_tau) in enumerate([
            (np.where(np.arange(7) == 3, 0.05, q), zeros, tau),
            (q, np.where(np.arange(7) == 3, 2 * 2.175 + 0.01, 0.0), tau),
            (q, zeros, np.where(np.arange(7) == 3, 2 * 87.0 + 1.0, tau))]):
        assert estimator.step(0.004 + 0.002 * k, bad_q, bad_qd, bad_tau) is None
        assert estimator.status == Status.BEYOND_LIMITS
    assert estimator.counts[Status.BEYOND_LIMITS] == 3
    assert estimator.step(0.01, q, zeros, tau) is not None and estimator.status == Status.OK
