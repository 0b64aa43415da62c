"""Issue 27: ``kvark replay --ground-truth ft|topic`` on a bag without that topic names the topic looked for, the
config key that sets it and the bag's topics of its message type, the nearest first."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.io import BagError, CommandSeries, JointStateSeries, RecordedRun, TopicNames, WrenchSeries, write_run
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.replay import ground_truth


@pytest.fixture(scope="module")
def ft_elsewhere(tmp_path_factory, panda_config):
    """A bag whose wrist F/T is on /arm/ft/wrench, not the config's /ft_sensor/wrench."""
    t = 1.0 + 0.002 * np.arange(50)
    q = np.zeros((len(t), panda_config.n_joints))
    run = RecordedRun(JointStateSeries(t, panda_config.joint_names, q, q, q), CommandSeries(t, q),
                      WrenchSeries(t, "panda_hand_tcp", q[:, :3], q[:, :3]))
    bag = tmp_path_factory.mktemp("ground_truth_hints") / "bag"
    write_run(bag, run, topics=TopicNames(wrench="/arm/ft/wrench"))
    return bag


@pytest.mark.parametrize("kind, words", [
    ("ft", ("--ground-truth ft needs the wrist F/T topic /ft_sensor/wrench (input.wrench_topic)",
            "WrenchStamped topics: /arm/ft/wrench", "did you mean '/arm/ft/wrench'? set input.wrench_topic")),
    ("topic", ("--ground-truth topic needs the true external torque topic /ground_truth/external_joint_torque "
               "(input.external_torque_topic)", "no other JointState topic")),
])
def test_missing_ground_truth_topic_names_topic_key_and_the_bag_topics(ft_elsewhere, panda_config, panda, kind,
                                                                       words):
    run, inputs = read_inputs(ft_elsewhere, panda_config)
    with pytest.raises(BagError) as raised:
        ground_truth(panda, panda_config, run, inputs, None, kind, ft_elsewhere)
    message = str(raised.value)
    assert "\n" not in message and message.startswith(f"{ft_elsewhere}: "), message
    for word in words:
        assert word in message, message
    if kind == "ft":                                           # the fix it names
        config = replace(panda_config, input=replace(panda_config.input, wrench_topic="/arm/ft/wrench"))
        run, inputs = read_inputs(ft_elsewhere, config)
        assert ground_truth(panda, config, run, inputs, None, kind, ft_elsewhere).kind.startswith("wrist F/T")
