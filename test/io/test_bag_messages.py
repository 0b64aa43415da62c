"""A bag's topics as serialised messages in log order (``kvark_ros.io.bag_messages``): what ``kvark play`` sends."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from kvark_ros.io import BagError
from kvark_ros.io.bag_messages import read_messages
from kvark_ros.io.common import FLOAT64_ARRAY, JOINT_STATE

BAG = Path(__file__).resolve().parents[2] / "bags" / "panda_contact"
TOPICS = {"/joint_states": ("input.joint_states_topic", {JOINT_STATE}),
          "/effort_commands": ("input.effort_commands_topic", {FLOAT64_ARRAY, JOINT_STATE})}


def test_the_messages_are_the_stored_bytes_in_log_order():
    messages = read_messages(BAG, TOPICS)
    with Reader(BAG) as reader:
        expected = [(log_ns, connection.topic, bytes(raw)) for connection, log_ns, raw
                    in reader.messages(connections=[c for c in reader.connections if c.topic in TOPICS])]
    assert [(log_ns, messages.topics[topic], raw) for log_ns, topic, raw in messages] == expected
    assert messages.msgtypes == (JOINT_STATE, FLOAT64_ARRAY) and len(messages) == 5000
    assert np.all(np.diff(messages.log_ns) >= 0) and messages.duration == pytest.approx(5.0, abs=0.01)


def test_a_topic_the_bag_lacks_names_its_key_and_the_nearest_topic():
    with pytest.raises(BagError, match=r"topic /arm/joint_states \(input.joint_states_topic\) is absent; .*did you "
                                       r"mean '/joint_states'"):
        read_messages(BAG, {"/arm/joint_states": TOPICS["/joint_states"]})


def test_a_topic_of_another_type_is_refused():
    with pytest.raises(BagError, match=r"/effort_commands \(input.joint_states_topic\) has type "
                                       r"std_msgs/msg/Float64MultiArray, expected sensor_msgs/msg/JointState"):
        read_messages(BAG, {"/effort_commands": TOPICS["/joint_states"]})


def test_a_truncated_bag_is_a_bag_error(tmp_path):
    copy = tmp_path / "cut"
    shutil.copytree(BAG, copy)
    storage = copy / "panda_contact.mcap"
    storage.write_bytes(storage.read_bytes()[:storage.stat().st_size // 2])
    with pytest.raises(BagError, match="corrupt or truncated"):
        read_messages(copy, TOPICS)
    with pytest.raises(BagError, match="no such bag"):
        read_messages(tmp_path / "missing", TOPICS)
