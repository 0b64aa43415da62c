"""Replay pairs a run's joint states and commands all at once (kvark_ros.core.estimation.pairing.paired_rows, through
kvark_ros.io.recorded_inputs.estimator_inputs); every decision must be the streaming pairer's (StreamPairer fed the
messages in time order, as the node is)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kvark_ros.core.estimation.pairing import RESET, Sample, StreamPairer
from kvark_ros.io import CommandSeries, JointStateSeries, RecordedRun, read_run
from kvark_ros.io.recorded_inputs import estimator_inputs

ROOT = Path(__file__).resolve().parents[2]

# Stamps on a 1 ms grid (states) and a 0.5 ms grid (commands): ties between a state and a command, repeated
# and unsorted stamps, gaps longer than the pairer's queue (8 states) and runs of commands nobody answers.
STATES = st.lists(st.integers(0, 80), min_size=1, max_size=40)
COMMANDS = st.lists(st.integers(0, 160), min_size=1, max_size=40)
AGES = st.sampled_from([0.0, 0.0005, 0.001, 0.0025, 0.01, np.inf])


def _paired(run: RecordedRun, max_command_age: float) -> list[Sample]:
    """The run's states and commands through the streaming pairer, in time order: states at their stamps, commands
    at theirs, at equal times the state before its command."""
    states, commands = run.joint_states, run.commands
    assert commands is not None
    pairer = StreamPairer(max_command_age, max_gap=np.inf)
    keys = np.concatenate([states.stamp, commands.stamp])
    kinds = np.concatenate([np.zeros(len(states.stamp), dtype=np.int8), np.ones(len(commands.stamp), dtype=np.int8)])
    rows = np.concatenate([np.arange(len(states.stamp)), np.arange(len(commands.stamp))])
    samples: list[Sample] = []
    for event in np.lexsort((kinds, keys)):
        row, key = rows[event], float(keys[event])
        if kinds[event] == 0:
            done = pairer.state(key, Sample(key, states.position[row], states.velocity[row], None))
        else:
            done = pairer.command(key, commands.effort[row], stamp=key)
        samples.extend(sample for sample in done if sample is not RESET)
    samples.extend(pairer.flush())
    return samples


def _run(state_ms: list[int], command_half_ms: list[int]) -> RecordedRun:
    """Row k of every array holds k, so a sample shows which state and which command it was made of."""
    s, c = len(state_ms), len(command_half_ms)
    rows = np.arange(s, dtype=float)[:, None] * np.ones(2)
    return RecordedRun(JointStateSeries(np.array(state_ms) * 1e-3, ("a", "b"), rows, -rows, np.zeros((s, 2))),
                       CommandSeries(np.array(command_half_ms) * 5e-4, np.arange(c, dtype=float)[:, None] * np.ones(2)))


def _assert_pairer_decisions(run: RecordedRun, max_age: float) -> None:
    bulk = estimator_inputs(run, max_age)
    samples = _paired(run, max_age)
    assert bulk.dropped == len(run.joint_states.stamp) - len(samples)
    assert bulk.stamp.tobytes() == np.array([sample.stamp for sample in samples]).tobytes()
    for name in ("q", "qd", "tau_m"):
        expected = np.array([getattr(sample, name) for sample in samples]).reshape(-1, 2)
        assert getattr(bulk, name).tobytes() == expected.tobytes(), name


@settings(max_examples=400, deadline=None, derandomize=True)
@given(STATES, COMMANDS, AGES)
def test_bulk_pairing_decides_as_the_stream_pairer(state_ms: list[int], command_half_ms: list[int],
                                                   max_age: float) -> None:
    _assert_pairer_decisions(_run(state_ms, command_half_ms), max_age)


def test_bulk_pairing_on_the_committed_bags() -> None:
    for bag in sorted((ROOT / "bags").glob("panda_*")):
        run = read_run(bag)
        for max_age in (0.0, 0.001, 0.01):
            _assert_pairer_decisions(run, max_age)
