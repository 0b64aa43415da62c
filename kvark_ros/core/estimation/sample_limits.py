"""What a joint sample of a real arm can hold, and the row check every reader of robot data applies. ROS-free.

A logger killed mid-line, a packet parsed as numbers or a sensor glitch leaves rows no arm can produce:
a position of 1e305 rad, a stamp of 2.7e154 s, a joint at rest one row and 30 rad away ten milliseconds
later. Such a row must not reach a fit or a filter (one of them overflowed ``kvark diagnose``'s least
squares), and dropping it must cost a line in a report, not the file. This module is the one place
the physical bounds and the checks live: ``kvark import`` (per CSV/NPZ/MAT row), every command that
reads a bag (``kvark_ros.io.recorded_inputs.read_checked``) and, per sample, the live estimator
(:meth:`SampleLimits.violation`).

Bounds (:class:`SampleLimits`), from the URDF with margins chosen to catch corrupt values, never a
robot driven hard (a corrupt value is orders of magnitude out; a margin costs nothing):

- position within the URDF's limits widened by ``POSITION_MARGIN`` (0.1 rad): encoders of a calibrated arm
  read within a few mrad of the mechanical range, controllers overshoot soft limits by less than that, and
  a joint beyond its range by more than 5.7° is no reading of it;
- velocity within ``VELOCITY_FACTOR`` (2) times the URDF's limit: drives cap speed at the rating, and
  overshoot and differentiation noise of q̇ stay well within a factor two (the public UR10e runs peak at
  0.92 of it, their torque at 0.65 of the effort limit);
- torque within ``TORQUE_FACTOR`` (2) times the URDF's effort limit (the rated peak torque): a motor
  current's torque estimate or a torque sensor in a collision exceeds the rating briefly, not twice over.
  Torques are compared in N·m, after a log's scale factors (a motor current needs its torque constant);
- a joint the URDF gives no limit (a continuous joint, ``effort="0"``, no URDF at all) gets the generic
  bounds ``GENERIC_POSITION`` (100 rad, 16 turns), ``GENERIC_VELOCITY`` (100 rad/s, ten times the fastest
  arm joint) and ``GENERIC_TORQUE`` (1e5 N·m, ten times the largest industrial arm's base joint): only
  absurd values are caught there.

Rows (:func:`check_rows`), in this order, each dropped row counted under the first reason it fails:
the stamp is finite and within the caller's bounds; q, q̇ and τ are finite and within the bounds above;
time strictly increases: the fewest rows whose removal leaves the stamps strictly increasing are dropped
(a longest strictly increasing subsequence: a stamp spiking forward or back costs that row, not the rows
after it); and the motion is continuous: the kept rows are cut into stretches wherever a time step
exceeds ``GAP_STEPS`` (100) median steps or a joint moves further than ``VELOCITY_FACTOR`` times its
velocity limit allows in the step plus ``JUMP_TOLERANCE`` (0.01 rad, a hundred times the resolution of a
log printed to 1e-4 rad), and a stretch of fewer than ``SHORT_STRETCH`` (10) rows is dropped unless it is
the longest, but for its rows that join the rows kept on both sides: isolated glitches go, a real recording
(seconds of rows) stays, and so does a good row that a glitch had cut off. Ten rows are under 0.1 s
at 100 Hz, shorter than the 0.15 s filter window training and ``kvark diagnose`` need anyway.
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

if TYPE_CHECKING:
    from kvark_ros.core.estimation.robot_model import RobotModel

__all__ = ["Drop", "RowCheck", "SampleLimits", "VIOLATIONS", "check_rows", "counted", "drop_lines", "span"]

POSITION_MARGIN = 0.1       # rad (m for a prismatic joint) beyond the URDF's position limits
VELOCITY_FACTOR = 2.0       # × the URDF's velocity limit
TORQUE_FACTOR = 2.0         # × the URDF's effort limit
GENERIC_POSITION = 100.0    # rad, |q| of a joint without position limits (16 turns)
GENERIC_VELOCITY = 100.0    # rad/s, |q̇| of a joint without a velocity limit
GENERIC_TORQUE = 1e5        # N·m, |τ| of a joint without an effort limit
GAP_STEPS = 100.0           # a time step over this many median steps cuts the log into stretches
JUMP_TOLERANCE = 0.01       # rad, a position step allowed on top of what the velocity bound allows
SHORT_STRETCH = 10          # rows: a shorter stretch between two cuts is dropped unless it is the longest

# Outcomes of ``SampleLimits.violation`` (0: within every bound), and the row check's reasons, in check order.
WITHIN, NON_FINITE, POSITION, VELOCITY, TORQUE = range(5)
VIOLATIONS = {NON_FINITE: "non-finite", POSITION: "position", VELOCITY: "velocity", TORQUE: "torque"}
REASONS = {
    "time": "stamp not finite or out of range",
    "non-finite": "NaN or Inf in q, q̇ or τ",
    "position": f"position beyond the joint limits (+{POSITION_MARGIN:g} rad)",
    "velocity": f"velocity beyond {VELOCITY_FACTOR:g}× the velocity limit",
    "torque": f"torque beyond {TORQUE_FACTOR:g}× the effort limit",
    "repeated": "repeated stamp",
    "order": "stamp out of order",
    "far": f"stamp far from its neighbours (a step over {GAP_STEPS:g} median steps)",
    "jump": f"position jump (faster than {VELOCITY_FACTOR:g}× the velocity limit)",
}
_UNITS = {POSITION: "rad", VELOCITY: "rad/s", TORQUE: "N·m"}
_FIELDS = {POSITION: "q", VELOCITY: "q̇", TORQUE: "τ"}


def _limit(values: Sequence[float], generic: float) -> np.ndarray:
    """``values`` where they are a usable speed or effort limit (finite, positive), else ``generic``."""
    found = np.asarray(values, dtype=float)
    return np.where(np.isfinite(found) & (found > 0.0) & (found < 1e10), found, generic)


class SampleLimits:
    """Bounds of one sample (q, q̇, τ), each (n,) in joint order (module docstring): ``q_low``/``q_high`` rad,
    ``qd_max`` rad/s, ``tau_max`` N·m, margins included; ``source`` says where they come from.

    ``lower``, ``upper``, ``velocity``, ``effort``: the URDF's limits per joint (NaN, ±inf or, for velocity
    and effort, 0 where it gives none).
    """

    def __init__(self, joint_names: Sequence[str], lower: Sequence[float], upper: Sequence[float],
                 velocity: Sequence[float], effort: Sequence[float], source: str) -> None:
        self.joint_names = tuple(joint_names)
        lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        bounded = np.isfinite(lower) & np.isfinite(upper) & (lower < upper) & (np.abs(lower) < 1e10) & (
            np.abs(upper) < 1e10)
        self.q_low = np.where(bounded, lower - POSITION_MARGIN, -GENERIC_POSITION)
        self.q_high = np.where(bounded, upper + POSITION_MARGIN, GENERIC_POSITION)
        self.qd_max = VELOCITY_FACTOR * _limit(velocity, GENERIC_VELOCITY / VELOCITY_FACTOR)
        self.tau_max = TORQUE_FACTOR * _limit(effort, GENERIC_TORQUE / TORQUE_FACTOR)
        self.source = source
        self._bounds = {POSITION: (self.q_low, self.q_high), VELOCITY: (-self.qd_max, self.qd_max),
                        TORQUE: (-self.tau_max, self.tau_max)}
        n = len(self.joint_names)     # the per-sample check's buffers: (q, q̇, τ) stacked, and two flag vectors
        self._low = np.concatenate([self._bounds[kind][0] for kind in (POSITION, VELOCITY, TORQUE)])
        self._high = np.concatenate([self._bounds[kind][1] for kind in (POSITION, VELOCITY, TORQUE)])
        self._sample, self._above, self._below = np.zeros(3 * n), np.zeros(3 * n, bool), np.zeros(3 * n, bool)

    @classmethod
    def from_robot(cls, robot: RobotModel) -> SampleLimits:
        """The limits of ``robot``'s URDF (a ``RobotModel``) for its joints; a continuous joint (two
        configuration coordinates) has no position limit."""
        model, n = robot.model, robot.n
        lower, upper = np.full(n, np.nan), np.full(n, np.nan)
        for k, name in enumerate(robot.joint_names):
            joint = model.joints[model.getJointId(name)]
            if joint.nq == 1:
                lower[k], upper[k] = model.lowerPositionLimit[joint.idx_q], model.upperPositionLimit[joint.idx_q]
        return cls(robot.joint_names, lower, upper, np.asarray(model.velocityLimit)[:n],
                   np.asarray(model.effortLimit)[:n], robot.urdf_name)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3n): the lowest and the highest [q, q̇, τ] within the limits, margins included (the compiled
        input check's argument, ``compiled.inputs.check_sample``)."""
        return np.stack((self._low, self._high))

    @classmethod
    def generic(cls, joint_names: Sequence[str]) -> SampleLimits:
        """The generic bounds only (no URDF known)."""
        nothing = np.full(len(joint_names), np.nan)
        return cls(joint_names, nothing, nothing, nothing, nothing, "the generic bounds (no URDF)")

    def violation(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> int:
        """The first bound one sample (q, q̇, τ, each (n,)) breaks: ``NON_FINITE``, ``POSITION``, ``VELOCITY``,
        ``TORQUE``, or ``WITHIN`` (0). A sample within every bound allocates nothing (a few µs): the live
        estimator may call it on every sample."""
        n, sample = len(self.joint_names), self._sample
        sample[:n], sample[n:2 * n], sample[2 * n:] = q, qd, tau
        np.greater_equal(sample, self._low, out=self._above)
        np.less_equal(sample, self._high, out=self._below)
        if np.logical_and(self._above, self._below, out=self._above).all():    # NaN compares False: not within
            return WITHIN
        if not np.isfinite(sample).all():
            return NON_FINITE
        return (POSITION, VELOCITY, TORQUE)[int(np.argmin(self._above)) // n]

    def describe(self, kind: int, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> str:
        """What sample (q, q̇, τ) shows for the violation ``kind``: the first joint, its value and bound."""
        if kind == NON_FINITE:
            for field, values in (("q", q), ("q̇", qd), ("τ", tau)):
                bad = np.flatnonzero(~np.isfinite(values))
                if bad.size:
                    return f"{self.joint_names[bad[0]]} {field} = {values[bad[0]]}"
            return "finite"
        values = {POSITION: q, VELOCITY: qd, TORQUE: tau}[kind]
        low, high = self._bounds[kind]
        bad = np.flatnonzero((values < low) | (values > high))
        if not bad.size:
            return "within its bounds"
        j = int(bad[0])
        return (f"{self.joint_names[j]} {_FIELDS[kind]} = {values[j]:.4g} {_UNITS[kind]}, bounds "
                f"[{low[j]:.4g}, {high[j]:.4g}]")

    def beyond(self, kind: int, values: np.ndarray) -> np.ndarray:
        """(T,) rows of ``values`` (T, n) outside the bound ``kind`` (``POSITION``, ``VELOCITY`` or ``TORQUE``)."""
        low, high = self._bounds[kind]
        return ((values < low) | (values > high)).any(axis=1)

    def jump(self, dt: float, q_before: np.ndarray, q: np.ndarray) -> bool:
        """Whether q moved from ``q_before`` further than ``dt`` s at ``VELOCITY_FACTOR`` × the velocity limit
        allows (plus ``JUMP_TOLERANCE``): a glitch, not motion."""
        return bool((np.abs(q - q_before) > self.qd_max * dt + JUMP_TOLERANCE).any())


@dataclass(frozen=True)
class Drop:
    """Rows dropped for one reason (a key of ``REASONS``): their indices (ascending) and what the first shows."""

    reason: str
    rows: np.ndarray
    detail: str

    @property
    def text(self) -> str:
        """The reason in words."""
        return REASONS[self.reason]


@dataclass(frozen=True)
class RowCheck:
    """The outcome of :func:`check_rows`: ``kept`` (T,) bool, and the drops per reason in check order."""

    kept: np.ndarray
    drops: tuple[Drop, ...]

    @property
    def dropped(self) -> int:
        """Rows dropped, all reasons."""
        return int(len(self.kept) - self.kept.sum())

    def count(self, reason: str) -> int:
        """Rows dropped for ``reason``."""
        return sum(len(drop.rows) for drop in self.drops if drop.reason == reason)


def _longest_increasing(values: np.ndarray) -> np.ndarray:
    """(T,) bool: a longest strictly increasing subsequence of ``values``, the one of the earliest rows where
    several are as long (a backward stamp costs itself, not the rows before it; a repeat costs the later row).

    Patience sorting, O(T log T), run from the end on −values: ``heads[m]`` is the largest value that starts an
    increasing run of length m + 1 among the rows seen, and a later-seen (earlier) row of an equal value takes it.
    """
    count = len(values)
    keep = np.zeros(count, dtype=bool)
    if count == 0 or np.all(values[1:] > values[:-1]):
        keep[:] = True
        return keep
    heads: list[float] = []          # −(start value) of a run of each length, ascending
    head_rows: list[int] = []
    after = np.full(count, -1)
    negated = (-values).tolist()
    for k in range(count - 1, -1, -1):
        value = negated[k]
        length = bisect_left(heads, value)
        if length == len(heads):
            heads.append(value)
            head_rows.append(k)
        else:
            heads[length], head_rows[length] = value, k
        after[k] = head_rows[length - 1] if length else -1
    k = head_rows[-1]
    while k >= 0:
        keep[k] = True
        k = after[k]
    return keep


def _stretches(stamp: np.ndarray, q: np.ndarray, limits: SampleLimits, rows: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """(far, jump) (len(rows),) bool over ``rows`` (indices whose ``stamp`` strictly increases, finite ``q``): the
    rows of short stretches between cuts (module docstring), by whether a time gap bounds their stretch; and the
    longest step that cuts nothing, s."""
    far, jump = np.zeros(len(rows), dtype=bool), np.zeros(len(rows), dtype=bool)
    if len(rows) < 2:
        return far, jump, np.inf
    dt = np.diff(stamp[rows])
    longest_step = GAP_STEPS * float(np.median(dt))
    gap = dt > longest_step
    moved = (np.abs(np.diff(q[rows], axis=0)) > limits.qd_max * dt[:, None] + JUMP_TOLERANCE).any(axis=1)
    cut = np.flatnonzero(gap | moved)
    starts, ends = np.concatenate(([0], cut + 1)), np.concatenate((cut + 1, [len(rows)]))
    sizes = ends - starts
    longest = int(np.argmax(sizes))
    for index, (start, end) in enumerate(zip(starts, ends)):
        if sizes[index] >= SHORT_STRETCH or index == longest:
            continue
        by_gap = (start > 0 and gap[start - 1]) or (end < len(rows) and gap[end - 1])
        (far if by_gap else jump)[start:end] = True
    return far, jump, longest_step


def _rejoined(stamp: np.ndarray, q: np.ndarray, limits: SampleLimits, longest_step: float, kept: np.ndarray,
              candidates: np.ndarray) -> np.ndarray:
    """(len(candidates),) bool: the dropped rows ``candidates`` (ascending) that join the rows kept on both sides
    (later in time than the one before and earlier than the one after, with no cut to either): a good row beside a
    glitch shares its short stretch, or loses a tie of the stamp order to it, and is kept once the glitch is gone."""
    def joins(a: int, b: int) -> bool:
        step = stamp[b] - stamp[a]
        reach = limits.qd_max * step + JUMP_TOLERANCE
        return bool(0.0 < step <= longest_step and not (np.abs(q[b] - q[a]) > reach).any())

    back = np.zeros(len(candidates), dtype=bool)
    previous = -1                       # the last row kept, or kept again, before the candidate
    for index, k in enumerate(candidates.tolist()):
        at = int(np.searchsorted(kept, k))
        previous = max(previous, int(kept[at - 1])) if at > 0 else previous
        following = int(kept[at]) if at < len(kept) else -1
        if (previous < 0 or joins(previous, k)) and (following < 0 or joins(k, following)):
            back[index], previous = True, k
    return back


def check_rows(stamp: np.ndarray, q: np.ndarray, qd: np.ndarray | None, tau: np.ndarray | None,
               limits: SampleLimits, time_bounds: tuple[float, float] = (-np.inf, np.inf)) -> RowCheck:
    """Which rows of a log to keep (module docstring): ``stamp`` (T,) s, ``q``, ``qd``, ``tau`` (T, n) rad, rad/s,
    N·m in ``limits``' joint order (``qd``, ``tau`` None: not checked); ``time_bounds``: [low, high) s a stamp must
    lie in. Rows are kept in their order; nothing is sorted."""
    count = len(stamp)
    alive = np.ones(count, dtype=bool)
    drops: list[Drop] = []

    def drop(reason: str, rows: np.ndarray, detail: Callable[[int], str]) -> None:
        rows = np.flatnonzero(rows & alive) if rows.dtype == bool else rows
        if rows.size:
            drops.append(Drop(reason, rows, detail(int(rows[0]))))
            alive[rows] = False

    with np.errstate(invalid="ignore", over="ignore"):
        drop("time", ~(np.isfinite(stamp) & (stamp >= time_bounds[0]) & (stamp < time_bounds[1])),
             lambda k: f"stamp {float(stamp[k]):.9g} s")
        fields = [(kind, values) for kind, values in ((POSITION, q), (VELOCITY, qd), (TORQUE, tau))
                  if values is not None]
        finite = np.all([np.isfinite(values).all(axis=1) for _, values in fields], axis=0)
        zero = np.zeros(len(limits.joint_names))

        def sample(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return (q[k], zero if qd is None else qd[k], zero if tau is None else tau[k])

        drop("non-finite", ~finite, lambda k: limits.describe(NON_FINITE, *sample(k)))
        for kind, values in fields:
            drop(VIOLATIONS[kind], limits.beyond(kind, values), lambda k, kind=kind: limits.describe(kind, *sample(k)))
    rows = np.flatnonzero(alive)
    ns = np.array(stamp, dtype=float)                 # the rows' stamps in ns, as a bag stores them, to compare
    if np.all(np.abs(stamp[rows]) < 9e9):
        ns[rows] = np.rint(stamp[rows] * 1e9)
    increasing = _longest_increasing(ns[rows])
    ordered = rows[increasing]
    far, jump, longest_step = _stretches(stamp, q, limits, ordered)
    kept = ordered[~(far | jump)]
    candidates = np.sort(np.concatenate((rows[~increasing], ordered[far | jump])))
    back = candidates[_rejoined(stamp, q, limits, longest_step, kept, candidates)]
    stays = np.sort(np.concatenate((kept, back)))
    unordered = np.setdiff1d(rows[~increasing], back)
    repeated = unordered[np.isin(ns[unordered], ns[stays])]

    def step(k: int) -> str:
        """The step between row ``k`` and the nearest row that stays (the one before it, else the one after)."""
        at = int(np.searchsorted(stays, k))
        other = int(stays[at - 1] if at > 0 else stays[min(at, len(stays) - 1)])
        dt, moved = abs(stamp[k] - stamp[other]), np.abs(q[k] - q[other])
        j = int(np.argmax(moved - (limits.qd_max * dt + JUMP_TOLERANCE)))
        return (f"stamp {stamp[k]:.9g} s, {dt:.4g} s from the nearest row kept, {limits.joint_names[j]} "
                f"{moved[j]:.4g} rad away")

    drop("repeated", repeated, lambda k: f"stamp {stamp[k]:.9g} s, as a kept row's")
    drop("order", np.setdiff1d(unordered, repeated), lambda k: f"stamp {stamp[k]:.9g} s")
    drop("far", np.setdiff1d(ordered[far], back), step)
    drop("jump", np.setdiff1d(ordered[jump], back), step)
    return RowCheck(alive, tuple(drops))


def drop_lines(check: RowCheck, where: Callable[[int], str]) -> list[str]:
    """One line per reason: ``<reason>: N rows (<first> to <last>; first: <detail>)``, ``where`` naming a row index
    (``line 12``, ``12.345 s``)."""
    return [f"{drop.text}: {counted(len(drop.rows), 'row')} "
            f"({span(where(int(drop.rows[0])), where(int(drop.rows[-1])))}; first: {drop.detail})"
            for drop in check.drops]


def counted(count: int, noun: str) -> str:
    """``1 row``, ``3 rows``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def span(first: str, last: str) -> str:
    """``line 12`` or ``line 12 to line 40``."""
    return first if first == last else f"{first} to {last}"
