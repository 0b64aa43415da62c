"""The data of a run, and the error every bag failure raises.

A *run* is what the estimator and the trainer consume: measured joint states,
commanded joint torque, and optionally the simulator's ground truth (wrist F/T
wrench and true external joint torque). Joints are matched by name, never by
position in a message (docs/method.md §1.3); units are SI; stamps are seconds.

Every failure a user can cause (bad path, not a bag, corrupt file, missing
topic or joint, wrong message type, existing output) raises :class:`BagError`
with a one-line message naming the file, the problem and the fix; a fit that
fails numerically on the data of bags (:func:`numerical_failures`) raises its
subclass :class:`FitError`, one line naming the bags, the step and what to check.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvark_ros.io.common import FloatArray, PathLike

__all__ = [
    "BagError",
    "CommandSeries",
    "FitError",
    "JointStateSeries",
    "RecordedRun",
    "SIMULATOR_SOURCE",
    "SOURCE_KEY",
    "TopicNames",
    "WrenchSeries",
    "numerical_failures",
]


class BagError(ValueError):
    """A bag cannot be read or written; the message names file, problem and fix."""


def bag_error(path: PathLike, problem: str, fix: str) -> BagError:
    """Build a one-line BagError: '<path>: <problem>; <fix>'."""
    text = f"{os.fspath(path)}: {problem}; {fix}"
    return BagError(" ".join(text.split()))


class FitError(BagError):
    """A fit on the data of bags failed numerically; the message names the bags, the step and what to check."""


# What numpy, scipy and scikit-learn raise when data defeat a computation: an SVD or a Cholesky factor that does
# not exist or converge, an overflow, a division by zero, NaN or too few samples in a fit.
NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, OverflowError, ZeroDivisionError, ValueError)


@contextmanager
def numerical_failures(bags: Sequence[PathLike], step: str, check: str) -> Iterator[None]:
    """Turn a numerical failure inside the block into one line, a :class:`FitError`: ``<bags>: <step> failed
    (<what failed>); <check>``. kvark_ros's own errors (a user error, with its own line) pass through."""
    try:
        yield
    except NUMERICAL_ERRORS as exc:
        if type(exc).__module__.startswith("kvark_ros"):
            raise
        what = " ".join(str(exc).split()) or "no message"
        names = ", ".join(os.fspath(bag) for bag in bags)
        raise FitError(f"{names}: {step} failed ({type(exc).__name__}: {what}); {check}") from exc


SOURCE_KEY = "kvark_ros.source"       # bag metadata custom_data key naming what wrote the bag
SIMULATOR_SOURCE = "simulator"


@dataclass(frozen=True)
class TopicNames:
    """Topic names of a run; rename to match a recording."""

    joint_states: str = "/joint_states"
    effort_commands: str = "/effort_commands"
    wrench: str = "/ft_sensor/wrench"
    external_torque: str = "/ground_truth/external_joint_torque"

    @classmethod
    def from_config(cls, inputs: Any) -> "TopicNames":
        """The config's ``input.*_topic`` keys as bag topics (a bag records absolute names: ``joint_states``
        is ``/joint_states``)."""
        def absolute(name: str) -> str:
            return name if name.startswith("/") else f"/{name}"

        return cls(absolute(inputs.joint_states_topic), absolute(inputs.effort_commands_topic),
                   absolute(inputs.wrench_topic), absolute(inputs.external_torque_topic))


def _as_matrix(value: Any, rows: int, cols: int, what: str) -> FloatArray:
    """Coerce to a C-contiguous float64 (rows, cols) array or raise ValueError."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.shape != (rows, cols):
        raise ValueError(f"{what} has shape {arr.shape}, expected {(rows, cols)}")
    return arr


def _as_stamps(value: Any, what: str) -> FloatArray:
    """Coerce to a 1-D float64 stamp array or raise ValueError."""
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{what} must be 1-D, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class JointStateSeries:
    """Joint states over time; columns follow ``names``.

    stamp (T,) s from header stamps; position (T, n) rad; velocity (T, n)
    rad/s; effort (T, n) N·m. A field a message leaves empty reads as NaN.
    """

    stamp: FloatArray
    names: tuple[str, ...]
    position: FloatArray
    velocity: FloatArray
    effort: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "JointStateSeries.stamp")
        names = tuple(str(n) for n in self.names)
        if len(set(names)) != len(names):
            raise ValueError(f"JointStateSeries.names has duplicates: {names}")
        shape = (stamp.shape[0], len(names))
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "names", names)
        for key in ("position", "velocity", "effort"):
            arr = _as_matrix(getattr(self, key), *shape, f"JointStateSeries.{key}")
            object.__setattr__(self, key, arr)


@dataclass(frozen=True)
class CommandSeries:
    """Commanded joint torque: stamp (T,) s (bag log time), effort (T, n) N·m in run order."""

    stamp: FloatArray
    effort: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "CommandSeries.stamp")
        effort = np.ascontiguousarray(self.effort, dtype=np.float64)
        if effort.ndim != 2 or effort.shape[0] != stamp.shape[0]:
            raise ValueError(
                f"CommandSeries.effort has shape {effort.shape}, expected ({stamp.shape[0]}, n)"
            )
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "effort", effort)


@dataclass(frozen=True)
class WrenchSeries:
    """Wrench over time in ``frame_id``: stamp (T,) s, force (T, 3) N, torque (T, 3) N·m."""

    stamp: FloatArray
    frame_id: str
    force: FloatArray
    torque: FloatArray

    def __post_init__(self) -> None:
        stamp = _as_stamps(self.stamp, "WrenchSeries.stamp")
        object.__setattr__(self, "stamp", stamp)
        object.__setattr__(self, "frame_id", str(self.frame_id))
        for key in ("force", "torque"):
            arr = _as_matrix(getattr(self, key), stamp.shape[0], 3, f"WrenchSeries.{key}")
            object.__setattr__(self, key, arr)


@dataclass(frozen=True)
class RecordedRun:
    """One recording: measured joint states, commands and optional ground truth.

    ``external_torque`` is the true external joint torque (effort field; its
    position/velocity may be zeros) in the same joint order as ``joint_states``.
    """

    joint_states: JointStateSeries
    commands: CommandSeries | None
    wrench: WrenchSeries | None = None
    external_torque: JointStateSeries | None = None
    # What wrote the bag (its metadata's custom_data ``kvark_ros.source``): "simulator: <plant>", "import: <file>",
    # or "" for a recording of a robot.
    source: str = ""

    @property
    def simulated(self) -> bool:
        """Whether the run comes from kvark's simulator (whose models must not be taken for a real robot's)."""
        return self.source.startswith(SIMULATOR_SOURCE)

    def __post_init__(self) -> None:
        n = len(self.joint_states.names)
        if self.commands is not None and self.commands.effort.shape[1] != n:
            raise ValueError(
                f"commands have {self.commands.effort.shape[1]} joints, joint_states have {n}"
            )
        if self.external_torque is not None and self.external_torque.names != self.joint_names:
            raise ValueError(
                f"external_torque joints {self.external_torque.names} differ from "
                f"joint_states joints {self.joint_names}"
            )

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint order of every (T, n) array in the run."""
        return self.joint_states.names
