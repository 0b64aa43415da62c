"""Joint names to columns and joint states paired with commands (kvark_ros.core.estimation.pairing), ROS-free."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.core.estimation.pairing import RESET, JointColumns, Reject, Sample, StreamPairer, stamp_seconds

JOINTS = ("j1", "j2", "j3")
DT = 0.002          # s between joint states (500 Hz)
MAX_AGE = 0.01      # s, input.command_max_age


def test_stamp_seconds_is_integer_nanoseconds_over_1e9():
    assert stamp_seconds(1, 500_000_000) == 1.5
    assert stamp_seconds(1_700_000_000, 123) == (1_700_000_000 * 1_000_000_000 + 123) / 1e9


def test_joint_columns_match_by_name():
    columns = JointColumns(JOINTS)
    assert columns.index(["j3", "gripper", "j1", "j2"]).tolist() == [2, 3, 0]
    assert columns.index(["finger_1", "finger_2"]) is None                          # someone else's message
    assert columns.index(["j1", "j3"]) == Reject.MISSING_JOINT and columns.missing == ["j2"]
    assert columns.index(["j1", "j2", "j3", "j2"]) == Reject.REPEATED_JOINT and columns.repeated == "j2"
    assert "'j2' named twice" in columns.problem
    assert columns.index(["j1", "j2", "j3", "other", "other"]).tolist() == [0, 1, 2]   # not ours: ignored


def _stream(count: int, missing: set[int] = frozenset(), late: int = 0) -> tuple[list, list]:
    """States k at stamp k·DT (published at key 2k) and commands for every k not in ``missing`` (key 2k + 1).

    τ_m of command k is [k, k, k], so a paired sample shows which command it got."""
    states = [(2.0 * k, Sample(k * DT, np.full(3, 0.1 * k), np.zeros(3), None)) for k in range(count)]
    commands = [(2.0 * k + 1.0, np.full(3, float(k))) for k in range(count) if k not in missing]
    return states, commands


def _feed(pairer: StreamPairer, events: list) -> list:
    out = []
    for kind, key, payload in events:
        if kind == "state":
            out += pairer.state(key, Sample(payload.stamp, payload.q, payload.qd, None))
        else:
            out += pairer.command(key, payload)
    return out + pairer.flush()


def _in_order(states: list, commands: list) -> list:
    events = [("state", key, sample) for key, sample in states] + [("command", key, tau) for key, tau in commands]
    return sorted(events, key=lambda event: event[1])


def _pairs(samples: list) -> list[tuple[float, float]]:
    return [(round(s.stamp, 9), float(s.tau_m[0])) for s in samples]


def test_each_state_gets_its_own_command_in_publication_order():
    states, commands = _stream(20)
    samples = _feed(StreamPairer(MAX_AGE, 0.05), _in_order(states, commands))
    assert _pairs(samples) == [(round(k * DT, 9), float(k)) for k in range(20)]


def test_a_backlog_delivering_the_next_state_before_the_command_keeps_the_pairs():
    """The executor takes state k+1 before command k (both waiting): each state still gets its own."""
    states, commands = _stream(6)
    events = []
    for (s_key, state), (c_key, tau) in zip(states, commands):
        events.append(("state", s_key, state))
    events += [("command", key, tau) for key, tau in commands]              # all states first, then commands
    samples = _feed(StreamPairer(MAX_AGE, 0.05), events)
    assert _pairs(samples) == [(round(k * DT, 9), float(k)) for k in range(6)]


def test_a_state_without_its_command_takes_the_newest_earlier_one_until_it_is_stale():
    """Commands 3-9 missing, command_max_age 9 ms: states 3-6 (2-8 ms after command 2) take command 2;
    states 7-9 (10-14 ms) are stale; 10 and 11 have their own."""
    states, commands = _stream(12, missing=set(range(3, 10)))
    pairer = StreamPairer(0.009, 0.05)
    samples = _feed(pairer, _in_order(states, commands))
    expected = [(0, 0), (1, 1), (2, 2), (3, 2), (4, 2), (5, 2), (6, 2), (10, 10), (11, 11)]
    assert _pairs(samples) == [(round(k * DT, 9), float(command)) for k, command in expected]
    assert pairer.counts[Reject.STALE] == 3


@pytest.mark.parametrize("seed", range(40))
def test_any_delivery_order_an_executor_can_produce_gives_the_same_pairs(seed):
    """Each topic stays in its own order (a subscription is FIFO) and a command comes after the state it
    answers (it was computed from it); otherwise the two topics interleave at random, as an executor under
    load delivers them (many states before their commands, bursts of commands). Some commands are missing.
    The pairs equal those of the in-order feed."""
    rng = np.random.default_rng(seed)
    missing = set(rng.choice(40, size=6, replace=False).tolist())
    states, commands = _stream(40, missing)
    expected = _pairs(_feed(StreamPairer(MAX_AGE, 0.05), _in_order(states, commands)))
    events, i, j = [], 0, 0
    while i < len(states) or j < len(commands):
        command_ready = j < len(commands) and commands[j][0] < states[i - 1][0] + 2.0 if i else False
        if i < len(states) and (not command_ready or rng.random() < 0.5):
            events.append(("state", *states[i]))
            i += 1
        else:
            events.append(("command", *commands[j]))
            j += 1
    assert events != _in_order(states, commands)
    got = _pairs(_feed(StreamPairer(MAX_AGE, 0.05, max_pending=64), events))
    assert got == expected


def test_out_of_order_and_repeated_stamps_are_rejected_and_a_jump_back_restarts():
    pairer = StreamPairer(MAX_AGE, max_gap=0.05)
    out = pairer.state(0.0, Sample(1.000, np.zeros(3), np.zeros(3), None))
    out += pairer.command(1.0, np.ones(3))
    assert pairer.state(2.0, Sample(1.000, np.zeros(3), np.zeros(3), None)) == []           # repeated stamp
    assert pairer.state(3.0, Sample(0.990, np.zeros(3), np.zeros(3), None)) == []           # 10 ms back
    assert pairer.counts[Reject.OUT_OF_ORDER] == 2
    out += pairer.state(4.0, Sample(1.002, np.zeros(3), np.zeros(3), None))                # waits for its command
    jump = pairer.state(5.0, Sample(0.5, np.zeros(3), np.zeros(3), None))                   # a bag loop
    assert [s.stamp for s in out] == [1.000]
    assert len(jump) == 2 and jump[0].stamp == 1.002 and jump[1] is RESET                    # completed, then reset
    assert pairer.counts[Reject.TIME_JUMP] == 1 and pairer.last_stamp == 0.5


def test_commands_before_the_first_state_are_ignored_and_states_wait_at_most_max_pending():
    """A command published before any state answers nothing; it is counted once the first state shows it
    was early. Without commands, states wait max_pending deep and the older ones are dropped as stale."""
    pairer = StreamPairer(MAX_AGE, 0.05, max_pending=3)
    assert pairer.command(0.0, np.ones(3)) == []
    done = []
    for k in range(5):
        done += pairer.state(1.0 + k, Sample(k * DT, np.zeros(3), np.zeros(3), None))
    assert pairer.counts[Reject.EARLY_COMMAND] == 1
    assert pairer.counts[Reject.STALE] == 2 and done == []          # the two oldest had no command at all


def test_a_state_carrying_its_torque_is_not_paired():
    pairer = StreamPairer(MAX_AGE, 0.05)
    sample = Sample(0.0, np.zeros(3), np.zeros(3), np.ones(3))
    assert pairer.stamped_state(sample) == [sample]
    assert pairer.stamped_state(Sample(0.002, np.zeros(3), np.zeros(3), None)) == []
    assert pairer.counts[Reject.NO_EFFORT] == 1


def test_the_problem_describes_the_name_list_just_looked_up_even_when_cached():
    columns = JointColumns(JOINTS)
    assert columns.index(["j1", "j2"]) == Reject.MISSING_JOINT            # j3 missing
    assert columns.index(["j1", "j1", "j2", "j3"]) == Reject.REPEATED_JOINT
    assert columns.index(["j1", "j2"]) == Reject.MISSING_JOINT            # from the cache
    assert columns.missing == ["j3"] and "'j3' missing" in columns.problem
