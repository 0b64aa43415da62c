"""Issue 27: a bag recorded with remapped topics (``/arm/joint_states``) gives one error line naming the config key
that sets the topic, the bag's topics of the right message type and the nearest of them."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kvark_ros.io import (BagError, BagWriter, CommandSeries, JointStateSeries, RecordedRun, TopicNames,
                          WrenchSeries, write_run)
from kvark_ros.io.recorded_inputs import read_inputs

REMAPPED = TopicNames("/arm/joint_states", "/arm/effort_commands", "/arm/ft/wrench")


def _one_line(message: str, *words: str) -> None:
    assert "\n" not in message and len(message) < 400, message
    for word in words:
        assert word in message, f"{word!r} not in: {message}"


@pytest.fixture(scope="module")
def remapped(tmp_path_factory, panda_config) -> Path:
    """A bag of the Panda's joints on /arm/... topics; its joint states carry no effort (τ_m: the commands only)."""
    t = 1.0 + 0.002 * np.arange(50)
    q = np.zeros((len(t), panda_config.n_joints))
    states = JointStateSeries(t, panda_config.joint_names, q, q, np.full(q.shape, np.nan))
    run = RecordedRun(states, CommandSeries(t, q), WrenchSeries(t, "panda_hand_tcp", q[:, :3], q[:, :3]))
    bag = tmp_path_factory.mktemp("topic_hints") / "arm"
    write_run(bag, run, topics=REMAPPED)
    return bag


def _with_topics(config, **topics: str):
    return replace(config, input=replace(config.input, **topics))


def test_remapped_joint_states_topic_names_the_key_and_the_bag_topic(remapped, panda_config):
    with pytest.raises(BagError) as raised:
        read_inputs(remapped, panda_config)
    _one_line(str(raised.value), str(remapped), "/joint_states (input.joint_states_topic) is absent",
              "JointState topics: /arm/joint_states",
              "did you mean '/arm/joint_states'? set input.joint_states_topic: /arm/joint_states")


def test_remapped_effort_commands_topic_names_the_key_and_the_bag_topic(remapped, panda_config):
    config = _with_topics(panda_config, joint_states_topic="/arm/joint_states")
    with pytest.raises(BagError) as raised:
        read_inputs(remapped, config)
    _one_line(str(raised.value), str(remapped), "no effort commands on /effort_commands (input.effort_commands_topic)",
              "Float64MultiArray or JointState topics: /arm/effort_commands",       # not /arm/joint_states
              "did you mean '/arm/effort_commands'? set input.effort_commands_topic: /arm/effort_commands")
    config = _with_topics(config, effort_commands_topic="arm/effort_commands")    # the fix it names
    assert len(read_inputs(remapped, config)[1]) == 50


def test_bag_without_joint_states_says_so_and_names_the_key(tmp_path, panda_config):
    bag = tmp_path / "commands_only"
    with BagWriter(bag) as writer:
        for k in range(5):
            writer.float64_array("/effort_commands", k / 500.0, np.zeros(panda_config.n_joints))
    with pytest.raises(BagError) as raised:
        read_inputs(bag, panda_config)
    _one_line(str(raised.value), "/joint_states (input.joint_states_topic) is absent",
              "no JointState topic (its topics: /effort_commands)", "or set input.joint_states_topic")
