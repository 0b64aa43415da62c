"""Turn a recorded run into Estimator inputs: one (stamp, q, q̇, τ_m) per joint-state sample.

Each joint state is paired with the newest command issued at or before its stamp (the command
computed from that state is logged with the same stamp by ros2_control-style loops and by our
simulator), and no older than ``max_command_age``. Samples without a fresh command are dropped
and counted. A bag without commands falls back to the measured effort in ``joint_states``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvark_ros.io.bag import BagError, RecordedRun

STAMP_TOLERANCE = 1e-4   # s: a command logged this much after the state still pairs with it


@dataclass(frozen=True)
class EstimatorInputs:
    """stamp (T,) s; q (T, n) rad; qd (T, n) rad/s; tau_m (T, n) N·m; what τ_m came from; drops."""

    stamp: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau_m: np.ndarray
    torque_source: str
    dropped: int

    def __len__(self) -> int:
        return len(self.stamp)


def estimator_inputs(run: RecordedRun, max_command_age: float = 0.01, path: str = "bag") -> EstimatorInputs:
    """Pair joint states with commands (see module docstring)."""
    states = run.joint_states
    if run.commands is not None and len(run.commands.stamp) > 0:
        commands = run.commands
        index = np.searchsorted(commands.stamp, states.stamp + STAMP_TOLERANCE, side="right") - 1
        fresh = index >= 0
        fresh[fresh] &= states.stamp[fresh] - commands.stamp[index[fresh]] <= max_command_age
        tau_m = commands.effort[np.maximum(index, 0)]
        source = "effort_commands"
    else:
        fresh = np.isfinite(states.effort).all(axis=1)
        tau_m = states.effort
        source = "joint_states.effort"
        if not fresh.any():
            raise BagError(f"{path}: no effort commands and no measured effort in joint_states; "
                           "record the commanded torque topic (effort_commands)")
    return EstimatorInputs(states.stamp[fresh], states.position[fresh], states.velocity[fresh],
                           tau_m[fresh], source, int((~fresh).sum()))
