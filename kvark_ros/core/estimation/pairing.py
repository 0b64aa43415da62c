"""Joint states and commanded torques in, paired estimator samples out. ROS-free and message-agnostic.

One rule for the live node and for replay over a bag: :class:`StreamPairer` message by message, and
:func:`paired_rows` for a whole recording at once (in time order the rule decides every state together;
test/io/test_bulk_pairing.py checks that the two give the same samples).

Mapping names to columns
    Joints are matched by name, never by position (:class:`JointColumns`): extra joints are ignored,
    a message naming none of the configured joints is someone else's (a gripper), a missing or
    repeated configured joint rejects the message.

Pairing (:class:`StreamPairer`)
    Every message carries an *order key*: when it was published (the node: the publication time of
    the message info, or the arrival count where there is none; a bag: the stamp of the state and
    the log time of the command). A command answers the newest joint state published at or before
    it: a control loop reads a state, computes, publishes. States wait in a short queue until their
    command arrives, so a command that is delivered after the next state (an executor falling
    behind takes state k+1 before command k) still pairs with state k. A state is completed without
    a command of its own, with the newest earlier command no older than ``command_max_age`` (by
    stamps) or rejected as stale, when a command for a later state arrives, when more than
    ``max_pending`` states wait, or at :meth:`StreamPairer.flush`. Completed samples leave in the
    order of their stamps.
    Joint states must have increasing stamps: an older or repeated stamp is rejected as out of
    order; a jump back by more than ``max_gap`` is a new run (bag loop, simulator reset): the states
    still waiting are completed, then a :data:`RESET` item tells the caller to restart its filter.

Loss (:attr:`StreamPairer.lost`)
    Joint states that never arrived, counted from the stamps: the period is measured (an EWMA of the
    regular steps) and a step longer than LOSS_GAP periods lost ``round(step / period) − 1`` states.
    Messages dropped by a queue or the network reach no callback, so only their absence shows them.
"""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

MAX_PENDING = 8          # joint states waiting for their command before the oldest is completed without one
RESET = None             # an item of a returned list: restart the filter before the samples after it
LOSS_GAP = 1.5           # a gap between joint states longer than this many periods lost states
PERIOD_RATE = 0.01       # EWMA rate of the measured joint-state period


def stamp_seconds(sec: int, nanosec: int) -> float:
    """A header stamp in seconds, as integer nanoseconds / 1e9 (the same float everywhere)."""
    return (sec * 1_000_000_000 + nanosec) / 1e9


class Reject:
    """Why a message gave no sample; the keys of :attr:`StreamPairer.counts` and the node's counts."""

    OTHER_JOINTS = "ignored: joint_states message names none of the configured joints"
    MISSING_JOINT = "rejected: a configured joint is missing from joint_states"
    REPEATED_JOINT = "rejected: a joint is named twice in one message"
    MALFORMED = "rejected: joint_states without position/velocity, or lengths differ from its names"
    NO_EFFORT = "rejected: joint_states without effort (torque_source joint_states_effort)"
    OUT_OF_ORDER = "rejected: joint_states stamp not after the previous one"
    TIME_JUMP = "reset: joint_states stamp jumped backwards by more than input.max_gap"
    STALE = "rejected: no effort command within input.command_max_age"
    BAD_COMMAND = "rejected: effort command with the wrong length or joints"
    EARLY_COMMAND = "ignored: effort command before the first joint state"


class JointColumns:
    """Where each configured joint sits in a message's name list; cached per distinct name list."""

    CACHE_SIZE = 64

    def __init__(self, joint_names: Sequence[str]) -> None:
        self.joint_names = tuple(joint_names)
        # name list -> (columns | reason | None, missing joints, repeated joint, problem in words)
        self._cache: dict[tuple[str, ...], tuple[np.ndarray | str | None, list[str], str | None, str]] = {}
        self.problem = ""                   # the last rejected name list, in words
        self.missing: list[str] = []        # the configured joints it lacked
        self.repeated: str | None = None    # the configured joint it named twice

    def index(self, names: Sequence[str]) -> np.ndarray | str | None:
        """Column of each configured joint (intp array), ``None`` when the message names none of them,
        or a :class:`Reject` reason (missing or repeated joint; :attr:`problem`, :attr:`missing` and
        :attr:`repeated` then describe this name list)."""
        key = tuple(names)
        found = self._cache.get(key)
        if found is None:
            if len(self._cache) >= self.CACHE_SIZE:
                self._cache.clear()
            found = self._cache[key] = self._lookup(key)
        result = found[0]
        if isinstance(result, str):
            _, self.missing, self.repeated, self.problem = found
        return result

    def _lookup(self, names: tuple[str, ...]) -> tuple[np.ndarray | str | None, list[str], str | None, str]:
        position: dict[str, int] = {}
        repeated = None
        for i, name in enumerate(names):
            if name in position and repeated is None and name in self.joint_names:
                repeated = name
            position.setdefault(name, i)
        missing = [name for name in self.joint_names if name not in position]
        if len(missing) == len(self.joint_names):
            return None, [], None, ""
        if missing:
            return (Reject.MISSING_JOINT, missing, repeated,
                    f"joint {missing[0]!r} missing from a message naming {list(names)}")
        if repeated is not None:
            return (Reject.REPEATED_JOINT, missing, repeated,
                    f"joint {repeated!r} named twice in a message naming {list(names)}")
        return np.array([position[name] for name in self.joint_names], dtype=np.intp), [], None, ""

    @property
    def seen(self) -> list[tuple[str, ...]]:
        """Distinct name lists met since the cache was last cleared."""
        return list(self._cache)


@dataclass
class Sample:
    """One paired estimator input: stamp s, q rad, q̇ rad/s, τ_m N·m (each (n,)), and the caller's tag."""

    stamp: float
    q: np.ndarray
    qd: np.ndarray
    tau_m: np.ndarray
    tag: Any = None


class StreamPairer:
    """Pairs joint states with commands in publication order (module docstring).

    ``state``, ``stamped_state`` and ``command`` return the samples they completed (possibly none,
    possibly several), oldest first, with :data:`RESET` where a time jump restarts the run.
    ``counts`` counts every rejected message by :class:`Reject` reason (pass the caller's Counter to
    keep one tally). Each topic must arrive in its own publication order (a subscription is FIFO);
    across the two topics any interleaving gives the same pairs.
    """

    def __init__(self, command_max_age: float, max_gap: float, max_pending: int = MAX_PENDING,
                 counts: Counter[str] | None = None) -> None:
        self.command_max_age = command_max_age
        self.max_gap = max_gap
        self.max_pending = max_pending
        self.counts: Counter[str] = Counter() if counts is None else counts
        self.lost = 0                                            # joint states missing from the stamps
        self._period: float | None = None                        # measured joint-state period, s
        self.reset()

    def reset(self) -> None:
        """Forget waiting states and commands, the last command and the last stamp (a filter reset)."""
        self._waiting: deque[tuple[float, Sample]] = deque()
        self._commands: deque[tuple[float, float | None, np.ndarray]] = deque()   # (key, stamp, τ_m), unpaired
        self._last: tuple[float, np.ndarray] | None = None      # (stamp, τ_m) of the newest command passed
        self._last_stamp: float | None = None
        self._decided_stamp: float | None = None                 # stamp of the newest state paired or dropped

    @property
    def last_stamp(self) -> float | None:
        """Stamp of the newest accepted joint state (s), None before the first."""
        return self._last_stamp

    def state(self, key: float, sample: Sample) -> list[Sample | None]:
        """A joint state published at ``key``; ``sample.tau_m`` is ignored (filled on pairing)."""
        done = self._check_stamp(sample.stamp)
        if done is None:
            return []
        self._last_stamp = sample.stamp
        self._waiting.append((key, sample))
        self._decide(done)
        return done

    def stamped_state(self, sample: Sample) -> list[Sample | None]:
        """A joint state that carries its own τ_m (``torque_source: joint_states_effort``): no pairing.
        ``sample.tau_m`` None: the message had no effort (rejected after the stamp checks)."""
        done = self._check_stamp(sample.stamp)
        if done is None:
            return []
        if sample.tau_m is None:
            self.counts[Reject.NO_EFFORT] += 1
            return done
        self._last_stamp = sample.stamp
        done.append(sample)
        return done

    def command(self, key: float, tau_m: np.ndarray, stamp: float | None = None) -> list[Sample | None]:
        """A command published at ``key``; ``stamp`` (s) is its own time if it has one (a bag's log
        time), else it takes the stamp of the state it answers."""
        self._commands.append((key, stamp, tau_m))
        done: list[Sample | None] = []
        self._decide(done)
        while len(self._commands) > self.max_pending:             # commands nobody answers (states stopped)
            self._pass(self._commands.popleft())
        return done

    def flush(self) -> list[Sample | None]:
        """Complete every waiting state without a command of its own (end of a bag, a reset)."""
        done: list[Sample | None] = []
        while self._waiting:
            self._complete_oldest(done, None)
        return done

    def _check_stamp(self, stamp: float) -> list[Sample | None] | None:
        """None: out of order (counted). Else what a time jump completed, ending in RESET, or []."""
        previous = self._last_stamp
        if previous is None:
            return []
        if stamp > previous:
            self._count_loss(stamp - previous)
            return []
        if previous - stamp <= self.max_gap:
            self.counts[Reject.OUT_OF_ORDER] += 1
            return None
        done = self.flush()
        self.reset()
        self.counts[Reject.TIME_JUMP] += 1
        done.append(RESET)
        return done

    @property
    def period(self) -> float | None:
        """The joint states' measured period, s (a running mean of the regular steps); None before two."""
        return self._period

    def _count_loss(self, step: float) -> None:
        """Count the joint states a ``step`` (s) between two accepted ones skipped (module docstring)."""
        period = self._period
        if period is None:
            self._period = step
        elif step > LOSS_GAP * period:
            self.lost += int(round(step / period)) - 1
        else:
            self._period = period + PERIOD_RATE * (step - period)

    def _decide(self, done: list[Sample | None]) -> None:
        """Pair or complete the oldest waiting states as far as the commands received allow.

        A command published before the oldest waiting state answered an earlier one: it passes. The
        first command published at or after it is its own, unless the next waiting state was published
        before that command too (then the command is the next state's, and the oldest has none). With no
        such command yet the state waits, at most ``max_pending`` states deep.
        """
        waiting, commands = self._waiting, self._commands
        while waiting:
            key, _ = waiting[0]
            while commands and commands[0][0] < key:
                self._pass(commands.popleft())
            if not commands:
                if len(waiting) <= self.max_pending:
                    return
                self._complete_oldest(done, None)
            elif len(waiting) > 1 and waiting[1][0] <= commands[0][0]:
                self._complete_oldest(done, None)
            else:
                self._complete_oldest(done, commands.popleft())

    def _pass(self, command: tuple[float, float | None, np.ndarray]) -> None:
        """A command no waiting state answers becomes the newest earlier command; one published before
        any state of the run answers nothing (counted)."""
        _, stamp, tau_m = command
        own = stamp if stamp is not None else self._decided_stamp
        if own is None:
            self.counts[Reject.EARLY_COMMAND] += 1
            return
        self._last = (own, tau_m)

    def _complete_oldest(self, done: list[Sample | None], command: tuple | None) -> None:
        """The oldest waiting state with its own ``command``, or else with the newest earlier command
        if that is no older than ``command_max_age`` (by stamps), or else dropped as stale."""
        _, sample = self._waiting.popleft()
        self._decided_stamp = sample.stamp
        if command is not None:
            _, stamp, tau_m = command
            self._last = (sample.stamp if stamp is None else stamp, tau_m)
        elif self._last is None or sample.stamp - self._last[0] > self.command_max_age:
            self.counts[Reject.STALE] += 1
            return
        sample.tau_m = self._last[1]
        done.append(sample)


def paired_rows(state_stamp: np.ndarray, command_stamp: np.ndarray,
                max_command_age: float) -> tuple[np.ndarray, np.ndarray]:
    """(joint-state rows, command rows) of the paired samples in time order: :class:`StreamPairer`'s decisions for
    every message of a recording at once (states at their stamps, commands at theirs, s; no new run: ``max_gap``
    infinite). In time order a repeated or older state stamp is out of order, a state's own command is the first
    one at or after its stamp and before the next state's, and a state without one takes the newest command before
    its stamp no older than ``max_command_age`` s (module docstring). A stamp that is not finite pairs nothing."""
    finite_states, finite_commands = np.flatnonzero(np.isfinite(state_stamp)), np.flatnonzero(np.isfinite(command_stamp))
    if not len(finite_states) or not len(finite_commands):
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    by_state = finite_states[np.argsort(state_stamp[finite_states], kind="stable")]
    stamps = state_stamp[by_state]
    accepted = np.ones(len(stamps), dtype=bool)
    accepted[1:] = stamps[1:] > stamps[:-1]              # a stamp not after the previous one is out of order
    states, stamps = by_state[accepted], stamps[accepted]
    by_command = finite_commands[np.argsort(command_stamp[finite_commands], kind="stable")]
    commands = command_stamp[by_command]
    after = np.searchsorted(commands, stamps, side="left")            # first command at or after each state
    following = np.append(stamps[1:], np.inf)
    own = after < len(commands)
    own[own] = commands[after[own]] < following[own]                  # ... and before the next state
    before = after - 1                                                # the newest command before the state
    age = stamps - commands[np.maximum(before, 0)]
    usable = own | ((before >= 0) & ~(age > max_command_age))
    return states[usable], by_command[np.where(own, after, before)[usable]]
