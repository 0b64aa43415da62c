"""The physical bounds of a joint sample and the row check of ``core.estimation.sample_limits``.

The bounds are the URDF's with the module's margins (pinned on the Panda's URDF); the check keeps a clean
recording whole, drops what a real log's glitches leave (a value of 1e300, a stamp spiking forward or back, a
row of zeros in the middle of motion), each under its own reason with its first and last row, and keeps a good
row a glitch had cut off. The property test corrupts clean trajectories at random and asserts what is kept
never breaks the physics and that no more rows are dropped than were corrupted.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kvark_ros.core.estimation.sample_limits import (GENERIC_POSITION, GENERIC_TORQUE, GENERIC_VELOCITY,
                                                     JUMP_TOLERANCE, NON_FINITE, POSITION, POSITION_MARGIN, TORQUE,
                                                     TORQUE_FACTOR, VELOCITY, VELOCITY_FACTOR, WITHIN, SampleLimits,
                                                     check_rows, drop_lines)

PANDA_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PANDA_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
PANDA_SPEED = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
PANDA_EFFORT = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
JOINTS = ("a", "b")
LIMITS = SampleLimits(JOINTS, [-1.0, -2.0], [1.0, 2.0], [1.0, 2.0], [10.0, 5.0], "a test URDF")


def _clean(rows: int = 200, rate: float = 100.0, seed: int = 0) -> tuple[np.ndarray, ...]:
    """A smooth two-joint recording within ``LIMITS``: stamps (s), q (rad), q̇ (rad/s), τ (N·m)."""
    rng = np.random.default_rng(seed)
    t = 10.0 + np.arange(rows) / rate
    phase = rng.uniform(0, 2 * np.pi, 2)
    q = 0.5 * np.sin(1.0 * t[:, None] + phase)                  # |q̇| ≤ 0.5 rad/s, under both speed limits
    qd = 0.5 * np.cos(1.0 * t[:, None] + phase)
    tau = np.array([4.0, 2.0]) * np.sin(0.7 * t[:, None])
    return t, q, qd, tau


def test_bounds_are_the_urdfs_with_the_margins(panda):
    limits = SampleLimits.from_robot(panda)
    np.testing.assert_allclose(limits.q_low, PANDA_LOWER - POSITION_MARGIN, atol=1e-12)
    np.testing.assert_allclose(limits.q_high, PANDA_UPPER + POSITION_MARGIN, atol=1e-12)
    np.testing.assert_allclose(limits.qd_max, VELOCITY_FACTOR * PANDA_SPEED, atol=1e-12)
    np.testing.assert_allclose(limits.tau_max, TORQUE_FACTOR * PANDA_EFFORT, atol=1e-12)
    assert limits.joint_names == panda.joint_names and "URDF" in limits.source


def test_a_joint_without_limits_gets_the_generic_bounds():
    limits = SampleLimits(("c",), [np.nan], [np.inf], [0.0], [0.0], "a URDF with a continuous joint")
    assert (limits.q_low[0], limits.q_high[0]) == (-GENERIC_POSITION, GENERIC_POSITION)
    assert (limits.qd_max[0], limits.tau_max[0]) == (GENERIC_VELOCITY, GENERIC_TORQUE)


@pytest.mark.parametrize("q, qd, tau, outcome", [
    ([0.0, 0.0], [0.0, 0.0], [0.0, 0.0], WITHIN),
    ([1.0 + POSITION_MARGIN - 1e-9, -2.0], [-2.0, 4.0], [20.0, -10.0], WITHIN),           # at every bound
    ([1.0 + POSITION_MARGIN + 1e-9, 0.0], [0.0, 0.0], [0.0, 0.0], POSITION),
    ([0.0, 0.0], [0.0, -4.0 - 1e-9], [0.0, 0.0], VELOCITY),
    ([0.0, 0.0], [0.0, 0.0], [0.0, 10.0 + 1e-9], TORQUE),
    ([0.0, 0.0], [0.0, 0.0], [np.nan, 0.0], NON_FINITE),
    ([5.0, 0.0], [np.inf, 0.0], [0.0, 0.0], NON_FINITE),                                 # non-finite comes first
    ([0.0, 0.0], [1e300, 0.0], [1e300, 0.0], VELOCITY),
])
def test_one_sample_is_within_or_names_the_first_bound_it_breaks(q, qd, tau, outcome):
    assert LIMITS.violation(*(np.array(v, dtype=float) for v in (q, qd, tau))) == outcome


def test_a_clean_recording_is_kept_whole():
    check = check_rows(*_clean(), LIMITS)
    assert check.kept.all() and check.drops == ()


def test_each_glitch_costs_its_own_row_under_its_reason():
    t, q, qd, tau = _clean()
    t[20] = 2.7e154                       # a stamp of garbage: out of range (the importer's [0, 2**31) s)
    qd[30, 1] = 1e300                     # a value no joint reaches
    tau[40, 0] = np.nan
    q[50] = 0.0                           # a row of zeros in the middle of motion: a jump, in and out
    t[60] = t[59]                         # a repeated stamp: the later row goes
    t[70] = t[68] - 0.001                 # a stamp back in time
    t[80] = t[80] + 5.0                   # a stamp spiking forward: out of order (rows after it come earlier)
    check = check_rows(t, q, qd, tau, LIMITS, (0.0, 2.0 ** 31))
    where = {drop.reason: drop.rows.tolist() for drop in check.drops}
    assert where == {"time": [20], "non-finite": [40], "velocity": [30], "repeated": [60], "order": [70, 80],
                     "jump": [50]}
    assert check.dropped == 7 and check.count("order") == 2
    lines = drop_lines(check, lambda row: f"line {row + 2}")
    assert lines[0] == "stamp not finite or out of range: 1 row (line 22; first: stamp 2.7e+154 s)"
    assert "velocity beyond 2× the velocity limit: 1 row (line 32; first: b q̇ = 1e+300 rad/s, bounds [-4, 4])" \
        in lines
    assert any(line.startswith("stamp out of order: 2 rows (line 72 to line 82;") for line in lines)


def test_a_burst_of_garbage_at_the_start_goes_and_the_good_first_row_stays():
    """As a logger's first 0.2 s can look (the public UR10e run ur-19_09_27-11_32_02): rows within the limits but
    nowhere near the motion, between a good first row and the recording."""
    t, q, qd, tau = _clean()
    q[1:20] = np.where(np.arange(19) % 2, 0.95, -0.95)[:, None]    # within the limits; the motion stays in ±0.5
    check = check_rows(t, q, qd, tau, LIMITS)
    assert check.kept[0] and check.kept[20:].all()
    assert not check.kept[1:20].any() and {drop.reason for drop in check.drops} == {"jump"}


def test_a_stamp_far_from_the_rest_goes_but_a_real_pause_is_kept():
    t, q, qd, tau = _clean()
    t[-1] += 1e6                                           # the last row 11 days later: a corrupt stamp
    t[100:-1] += 30.0                                      # a 30 s pause of the logger, the arm held still
    q[100:-1] = q[99]
    check = check_rows(t, q, qd, tau, LIMITS)
    assert check.kept[:-1].all() and not check.kept[-1]
    assert [drop.reason for drop in check.drops] == ["far"]


def test_a_short_log_is_not_taken_for_a_glitch():
    t, q, qd, tau = _clean(rows=4)
    assert check_rows(t, q, qd, tau, LIMITS).kept.all()


def test_a_jump_the_velocity_bound_allows_is_kept():
    t, q, qd, tau = _clean(rows=50)
    step = LIMITS.qd_max[0] * (t[1] - t[0]) + JUMP_TOLERANCE
    q[25:, 0] += 0.9 * step                                # just within: a fast move, not a glitch
    assert check_rows(t, q, qd, tau, LIMITS).kept.all()
    q[25:, 0] += 0.2 * step                                # beyond, but both sides are long stretches: kept
    assert check_rows(t, q, qd, tau, LIMITS).kept.all()


CORRUPTIONS = ("nan", "inf", "huge", "zeros", "swap", "repeat", "back", "forward", "spike")


def _corrupt(kind: str, k: int, t: np.ndarray, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> None:
    """Corrupt row ``k`` (1 ≤ k < T - 1) in place the way ``kind`` says."""
    if kind == "nan":
        q[k, 0] = np.nan
    elif kind == "inf":
        tau[k, 1] = -np.inf
    elif kind == "huge":
        qd[k, 0] = 1e300
    elif kind == "zeros":
        q[k], qd[k], tau[k] = 0.7, 0.0, 0.0
    elif kind == "swap":                                   # a row with q̇ and τ swapped: τ beyond the speed bound
        qd[k], tau[k] = tau[k] + 6.0, qd[k]
    elif kind == "repeat":
        t[k] = t[k - 1]
    elif kind == "back":
        t[k] = t[k - 1] - 0.5
    elif kind == "forward":
        t[k] = t[k + 1] + 0.5
    else:                                                  # a position spike
        q[k, 1] += 1.5


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rows=st.integers(30, 300), seed=st.integers(0, 2 ** 16),
       faults=st.lists(st.tuples(st.sampled_from(CORRUPTIONS), st.floats(0.0, 1.0)), max_size=6))
def test_what_is_kept_never_breaks_the_physics(rows, seed, faults):
    """Up to six corrupted rows, each at least ``SHORT_STRETCH`` rows from the others: every kept row is finite and
    within the bounds, time strictly increases and no kept step jumps; at most one row is dropped per corruption."""
    t, q, qd, tau = _clean(rows, seed=seed)
    used: list[int] = []
    for kind, where in faults:
        k = 1 + int(where * (rows - 3))
        if all(abs(k - other) > 10 for other in used):
            _corrupt(kind, k, t, q, qd, tau)
            used.append(k)
    check = check_rows(t, q, qd, tau, LIMITS)
    kept = check.kept
    assert check.dropped <= len(used)
    for values, kind in ((q, POSITION), (qd, VELOCITY), (tau, TORQUE)):
        assert np.isfinite(values[kept]).all() and not LIMITS.beyond(kind, values[kept]).any()
    dt = np.diff(t[kept])
    assert (dt > 0).all()
    assert not (np.abs(np.diff(q[kept], axis=0)) > LIMITS.qd_max * dt[:, None] + JUMP_TOLERANCE).any()
