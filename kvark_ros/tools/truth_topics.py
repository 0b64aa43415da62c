"""The error of ``--ground-truth topic|ft`` on a bag without that topic: which topic was looked for, the config key
that sets it, and the bag's topics of its message type, the nearest first (``kvark replay``)."""
from __future__ import annotations

from pathlib import Path

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.io import BagError, TopicNames
from kvark_ros.io.common import JOINT_STATE, WRENCH_STAMPED
from kvark_ros.io.info import topic_types
from kvark_ros.io.topic_hints import missing_topic

__all__ = ["missing_truth"]


def missing_truth(kind: str, config: EstimatorConfig, bag: str | Path | None) -> BagError:
    """``--ground-truth kind`` (``topic`` or ``ft``) needs a topic ``bag`` lacks; without ``bag``, the error names
    the topic and its config key only."""
    topics = TopicNames.from_config(config.input)
    topic, key, msgtype, what = ((topics.wrench, "input.wrench_topic", WRENCH_STAMPED, "the wrist F/T topic")
                                 if kind == "ft" else (topics.external_torque, "input.external_torque_topic",
                                                       JOINT_STATE, "the true external torque topic"))
    need = f"--ground-truth {kind} needs {what} {topic} ({key})"
    if bag is None:
        return BagError(f"{need}, which this replay does not have; set {key} to the bag's topic")
    types = topic_types(bag)
    lacks = "has no messages on it" if topic in types else "does not have it"
    return missing_topic(bag, f"{need}, but the bag {lacks}", topic, key, types, {msgtype},
                         exclude=(topics.joint_states, topics.effort_commands))
