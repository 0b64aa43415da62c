"""``kvark play BAG``: publish a bag's joint states and effort commands to ROS 2, at real time or a set rate.

For users without rosbag2 (the ROS 2 wheels have none) and for the node's tests: the config's
``input.joint_states_topic`` and ``input.effort_commands_topic`` (the latter only when ``input.torque_source`` takes
τ_m from it: with ``joint_states_effort`` the node has no command subscription to wait for) are read from the bag
(as ``kvark replay`` reads them) and published under the same relative names, so ``--ros-args -r
joint_states:=/arm/joint_states`` remaps them as it would the node's. Each message goes out as the bag stores it
(its serialized CDR bytes: stamps and values bit for bit), in log order, at log time / ``--rate`` after the start,
with the sensor-data QoS the node subscribes with. Before the first message the player waits until every topic has a
subscriber (``--wait``), so a node that is still starting loses nothing.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from kvark_ros.core.config import InputSettings, load_config
from kvark_ros.io.bag_messages import TopicMessages, read_messages
from kvark_ros.io.common import FLOAT64_ARRAY, JOINT_STATE

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

NODE_NAME = "kvark_player"
MESSAGE_TYPES = {JOINT_STATE: JointState, FLOAT64_ARRAY: Float64MultiArray}
__all__ = ["BagPlayer", "Recording", "read_recording", "input_recording", "main"]


@dataclass(frozen=True)
class Recording:
    """The messages to play (``kvark_ros.io.bag_messages.TopicMessages``, in log order) and the relative config
    name each of their topics is published under."""

    names: tuple[str, ...]
    messages: TopicMessages

    @property
    def topics(self) -> tuple[tuple[str, type], ...]:
        """(config topic name, rclpy message class) of each topic."""
        return tuple((name, MESSAGE_TYPES[msgtype]) for name, msgtype in zip(self.names, self.messages.msgtypes))

    @property
    def duration(self) -> float:
        """Log time from the first message to the last, s."""
        return self.messages.duration


def read_recording(bag: str | Path, joint_states_topic: str, effort_commands_topic: str | None) -> Recording:
    """The input topics of ``bag`` (relative config names; the bag records them absolute; no command topic for
    None), read through ``kvark_ros.io``: ``BagError`` naming the config key when one is missing or of a type the
    node does not take."""
    topics = {f"/{joint_states_topic.lstrip('/')}": ("input.joint_states_topic", {JOINT_STATE})}
    names = [joint_states_topic]
    if effort_commands_topic is not None:
        topics[f"/{effort_commands_topic.lstrip('/')}"] = ("input.effort_commands_topic", {FLOAT64_ARRAY, JOINT_STATE})
        names.append(effort_commands_topic)
    return Recording(tuple(names), read_messages(bag, topics))


def input_recording(bag: str | Path, settings: InputSettings) -> Recording:
    """The topics of ``bag`` a node with the config's ``input`` settings subscribes to: the joint states, and the
    commands unless ``torque_source`` is ``joint_states_effort``."""
    commands = None if settings.torque_source == "joint_states_effort" else settings.effort_commands_topic
    return read_recording(bag, settings.joint_states_topic, commands)


class BagPlayer(Node):
    """Publishes a ``Recording`` on its topics (relative names: remappable) with the sensor-data QoS."""

    def __init__(self, recording: Recording, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.recording = recording
        self.sent_ns = np.zeros(len(recording.messages), dtype=np.int64)    # system time of each publish, ns
        self.topic_publishers = [self.create_publisher(kind, name, qos_profile_sensor_data)
                            for name, kind in recording.topics]

    def wait_for_subscribers(self, timeout: float) -> bool:
        """Until every topic has a subscriber (discovery takes a moment) or ``timeout`` s; whether they all have."""
        deadline = time.monotonic() + timeout
        while any(p.get_subscription_count() == 0 for p in self.topic_publishers):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def play(self, rate: float = 1.0, at: Callable[[float], None] | None = None) -> float:
        """Publish every message at its log time / ``rate`` after the start; ``at(t)`` (if given) is called
        before each message with its bag time t (s since the first message); ``sent_ns`` holds when each went
        out. The lateness (s) of the most delayed message, so a caller can tell how closely the schedule was
        held."""
        messages = self.recording.messages
        if not len(messages):
            return 0.0
        first = int(messages.log_ns[0])
        start = time.perf_counter()
        late = 0.0
        for index, (log_ns, topic, raw) in enumerate(messages):
            bag_time = (log_ns - first) / 1e9
            due = start + bag_time / rate
            wait = due - time.perf_counter()
            if wait > 0.0:
                time.sleep(wait)
            else:
                late = max(late, -wait)
            if at is not None:
                at(bag_time)
            self.sent_ns[index] = time.time_ns()
            self.topic_publishers[topic].publish(raw)
        return late


def playback_rate(text: str) -> float:
    """``--rate``: a speed-up factor > 0 (argparse type)."""
    try:
        rate = float(text)
    except ValueError:
        rate = math.nan
    if not rate > 0.0 or math.isinf(rate):
        raise argparse.ArgumentTypeError(f"must be a number > 0 (1 = real time), got {text!r}")
    return rate


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "play", help="publish a bag's joint states and effort commands to ROS 2 (rclpy)",
        description="Publish the joint states and effort commands of a ROS 2 bag (MCAP or sqlite3) on the config's "
                    "input topics, at real time or --rate times faster, bit for bit as recorded. Needs ROS 2 rclpy "
                    "(a ROS 2 Jazzy environment, or the ros-jazzy-* wheels of the [ros] extra). ROS arguments "
                    "follow --ros-args, e.g. --ros-args -r joint_states:=/arm/joint_states.")
    parser.add_argument("bag", help="bag to play")
    parser.add_argument("--config", default=str(Path(__file__).resolve().parents[2] / "config" / "panda.yaml"),
                        help="estimator config whose input.joint_states_topic and input.effort_commands_topic are "
                             "played (default: config/panda.yaml)")
    parser.add_argument("--rate", type=playback_rate, default=1.0,
                        help="playback speed, 1 = real time (default), 2 = twice as fast")
    parser.add_argument("--wait", type=float, default=10.0, metavar="SECONDS",
                        help="wait up to SECONDS for a subscriber on every topic before playing (default 10; "
                             "0: play at once)")
    parser.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[], dest="ros_args",
                        help="ROS arguments (remappings, parameters), as for any ROS 2 node")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    recording = input_recording(args.bag, config.input)
    rclpy.init(args=["kvark_play", "--ros-args", *args.ros_args] if args.ros_args else None)
    try:
        player = BagPlayer(recording)
        names = ", ".join(p.topic_name for p in player.topic_publishers)
        if args.wait > 0.0 and not player.wait_for_subscribers(args.wait):
            print(f"[play] no subscriber on every topic after {args.wait:g} s; playing anyway", file=sys.stderr)
        print(f"[play] {len(recording.messages)} messages, {recording.duration:.2f} s of {args.bag} at "
              f"{args.rate:g}x on {names}", flush=True)
        late = player.play(args.rate)
        print(f"[play] done; the most delayed message was {late * 1e3:.2f} ms late", flush=True)
        player.destroy_node()
    except KeyboardInterrupt:
        return 130
    finally:
        rclpy.try_shutdown()
    return 0


def main() -> int:
    """``python -m kvark_ros.ros.player …``: ``kvark play …``, with its error handling."""
    from kvark_ros.cli import main as kvark
    return kvark(["play", *sys.argv[1:]])


if __name__ == "__main__":
    sys.exit(main())
