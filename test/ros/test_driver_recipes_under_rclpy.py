"""The driver recipes of docs/ros.md under real rclpy and Fast DDS: each driver's topics, with the names, types,
rates and units it publishes them with (``test/driver_fixtures.py``), played into the node started from the
recipe's parameter file, as ``ros2 run`` starts it, and every estimate equal to ``kvark replay`` on the same bag.

- franka_ros2 (Panda): ``config/drivers/franka_panda.yaml`` as shipped; 1 kHz ``/franka/joint_states`` with τ_J in
  effort, and the 30 Hz merged ``/joint_states`` with the gripper's fingers beside it;
- ur_robot_driver: the file ``kvark init --driver ur --effort-scale …`` writes for example-robot-data's UR10
  (ur_description's frames: root ``world``, ``base`` turned 180° about z); ``/joint_states`` at 500 Hz, motor
  currents in A;
- lbr_fri_ros2_stack: the file ``kvark init --driver lbr`` writes (key ``/**/kvark_estimator``, a URDF beside it),
  the node started in the namespace ``lbr`` with that file; ``/lbr/joint_states`` at 100 Hz.

The three nodes run at once on one ROS domain of their own (loopback only), each started from another folder than
its file's, so the paths resolve against the file; the UR node in the namespace ``ur`` with its input remapped to
``/joint_states`` (two nodes called ``kvark_estimator`` in one namespace would share their outputs' names), as for
two arms on one machine. Their outputs are recorded as CDR bytes and decoded afterwards. The module runs beside the
other tests (not ``realtime``): what it checks is what arrives, not how fast, and the queue depth and the waits
below keep every sample on a machine whose cores are busy (beside the other test worker, one or both cores also
running ``yes``: 3 of 3 runs passed, and the module alone 8 of 8).
On the Franka node the stamped outputs are paired by header stamp as message_filters' ExactTime policy pairs them
(ApproximateTime pairs the same sets when stamps are equal): message_filters itself has no wheel here.
"""
from __future__ import annotations

import importlib
import os
import platform
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "test"))
WHEELS = sys.platform == "linux" and platform.machine() == "x86_64"
if not WHEELS:
    pytest.skip("the ROS 2 Jazzy wheels exist for linux x86_64 only", allow_module_level=True)

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from driver_fixtures import UR_TORQUE_CONSTANTS, franka_bag, lbr_urdf, synthetic_driver_bag  # noqa: E402
from kvark_ros.cli import main as kvark  # noqa: E402
from kvark_ros.core.config import load_config  # noqa: E402
from kvark_ros.core.estimation.model_store import load_model, save_model  # noqa: E402
from kvark_ros.core.estimation.robot_model import RobotModel  # noqa: E402
from kvark_ros.io.recorded_inputs import read_inputs  # noqa: E402
from kvark_ros.io.bag_messages import read_messages  # noqa: E402
from kvark_ros.io.common import JOINT_STATE, typestore  # noqa: E402
from kvark_ros.ros import node_check, node_process, publishers  # noqa: E402
from kvark_ros.ros.input_loop import InputGroup, InputLoop  # noqa: E402
from kvark_ros.ros.player import BagPlayer, Recording, input_recording  # noqa: E402
from kvark_ros.tools.replay import run_observer  # noqa: E402
from kvark_ros.tools.synthetic import train_synthetic  # noqa: E402

DOMAIN = 190                      # this module's ROS domain (Fast DDS: at most 232; test_node_under_rclpy: 201-232)
FRANKA_CONFIG = ROOT / "config" / "drivers" / "franka_panda.yaml"
# Topics recorded per node: the Franka node's stamped outputs (paired below), the others' τ_ext and wrench.
STAMPED = ("external_joint_torque", "external_joint_torque_stddev_stamped", "external_wrench",
           "external_wrench_with_covariance", "contact_state")
INPUT_TOPIC = {"franka": "/franka/joint_states", "ur": "/joint_states", "lbr": "/lbr/joint_states"}
MSGTYPES = {"external_joint_torque": JOINT_STATE, "external_joint_torque_stddev_stamped": JOINT_STATE,
            "external_wrench": "geometry_msgs/msg/WrenchStamped", "contact_state": JOINT_STATE,
            "external_wrench_with_covariance": "geometry_msgs/msg/TwistWithCovarianceStamped"}


class Recipe:
    """One driver's parameter file, bag, node name and what its node published."""

    def __init__(self, name: str, config: Path, bag: Path, namespace: str = "", remaps: tuple[str, ...] = ()) -> None:
        self.name, self.config, self.bag, self.namespace, self.remaps = name, config, bag, namespace, remaps
        self.node = f"{namespace}/kvark_estimator"
        self.outputs: dict[str, list[bytes]] = defaultdict(list)
        self.advertised: list[tuple[str, list[str]]] = []          # (topic, types) the node publishes

    def messages(self, topic: str) -> list:
        store = typestore()
        return [store.deserialize_cdr(raw, MSGTYPES[topic]) for raw in self.outputs[topic]]


def _init(*arguments: str | Path) -> None:
    assert kvark(["init", *map(str, arguments)]) == 0


@pytest.fixture(scope="module")
def recipes(tmp_path_factory) -> list[Recipe]:
    """The three recipes' files, models and bags (module docstring), made as a user makes them."""
    root = tmp_path_factory.mktemp("drivers")
    franka = Recipe("franka", FRANKA_CONFIG, franka_bag(ROOT / "bags" / "panda_contact", root / "franka_bag"))
    scale = ",".join(map(str, UR_TORQUE_CONSTANTS))
    _init("--urdf", "example-robot-data:ur10", "--driver", "ur", "--effort-scale", scale, "--robot", "ur10",
          "--out", root / "ur" / "config" / "ur10.yaml")
    (root / "lbr" / "config" / "lbr.urdf").parent.mkdir(parents=True)
    (root / "lbr" / "config" / "lbr.urdf").write_text(lbr_urdf())
    _init("--urdf", root / "lbr" / "config" / "lbr.urdf", "--driver", "lbr", "--robot", "lbr",
          "--out", root / "lbr" / "config" / "lbr.yaml")
    made = [franka]
    for name, topic, rate, constants, namespace in (("ur", "/joint_states", 500.0, UR_TORQUE_CONSTANTS, "/ur"),
                                                      ("lbr", "/lbr/joint_states", 100.0, None, "/lbr")):
        config_path = root / name / "config" / f"{'ur10' if name == 'ur' else name}.yaml"
        config = load_config(config_path)
        robot = RobotModel.from_config(config)
        save_model(config.model_dir, train_synthetic(robot, config.robot, seed=3, duration=6.0, baselines=False,
                                                     rate=rate))
        bag = synthetic_driver_bag(robot, root / f"{name}_bag", topic, rate, 2.0, seed=11, torque_constants=constants)
        made.append(Recipe(name, config_path, bag, namespace, ("-r", "joint_states:=/joint_states") if name == "ur"
                           else ()))
    return made


def _states(recipe: Recipe) -> int:
    """How many joint states the recipe's node estimates on: those of its driver's joint-state topic."""
    return len(read_messages(recipe.bag, {INPUT_TOPIC[recipe.name]: ("input", {JOINT_STATE})}))


def _play(recipe: Recipe, start: threading.Barrier, players: list[BagPlayer]) -> None:
    """Every topic of the recipe's bag, as the driver publishes it, at real time, once every player's topics have
    their subscribers (``start``: one party per player and the recording thread). The player goes to ``players``,
    to be destroyed once the outputs have stopped: destroyed at once, a busy machine lost its last messages."""
    topics = {connection: ("driver topic", {JOINT_STATE}) for connection in
              (("/franka/joint_states", "/joint_states") if recipe.name == "franka" else (INPUT_TOPIC[recipe.name],))}
    player = BagPlayer(Recording(tuple(topics), read_messages(recipe.bag, topics)),
                       namespace=f"player_{recipe.name}")
    players.append(player)
    try:
        assert player.wait_for_subscribers(30.0), f"{recipe.name}: a topic without its subscriber"
        start.wait(60.0)
        time.sleep(2.0)         # and the nodes' subscriptions their publishers: the other side of the match, later
        player.play(1.0)
    except BaseException:
        start.abort()
        raise


def _status(arrays: list, node: str, part: str):
    for array in reversed(arrays):
        for status in array.status:
            if status.name == f"{node}: {part}":
                return status
    return None


def _run_nodes(recipes: list[Recipe], folder: Path) -> None:
    """Start the three nodes (from ``folder``, not their files' folders), record their outputs while the three bags
    play at once, stop them; every node must exit with 0 on SIGTERM."""
    ros_env = node_process.local_domain(DOMAIN, folder / "log")
    env = {**os.environ, **ros_env}
    env.pop("AMENT_PREFIX_PATH", None)                      # as after a pip install: no ament environment
    processes, logs = [], []
    # input.queue_depth 1000 (2 s at 500 Hz): a machine busy with three nodes and the player cannot turn a late
    # sample into a lost one; the default depth's figures are node-check's.
    for recipe in recipes:
        logs.append(open(folder / f"{recipe.name}.log", "w+"))
        namespace = ("-r", f"__ns:={recipe.namespace}") if recipe.namespace else ()
        processes.append(node_process.start_node(recipe.config, env, logs[-1], cwd=folder, ros_arguments=(
            *namespace, *recipe.remaps, "-p", "input.queue_depth:=1000")))
    try:
        with node_process.joined(ros_env):
            _record_while_playing(recipes, processes, logs)
    finally:
        codes = [node_process.stop_node(process, 20.0) for process in processes]
        tails = []
        for log in logs:
            log.seek(0)
            tails.append(log.read()[-1500:])
            log.close()
    assert codes == [0, 0, 0], tails


def _record_while_playing(recipes: list[Recipe], processes: list, logs: list) -> None:
    client = rclpy.create_node("kvark_driver_recipes")
    diagnostics: list = []
    client.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 100)
    reliable = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
    # The outputs (~6 000 messages/s) on the node's own input loop, every ready message per wake: lighter than
    # rclpy's Python executor, which a busy machine could leave 1 s behind (the writers keep the last 1 000).
    group, subscriptions, players = InputGroup(), [], []
    for recipe in recipes:
        for topic in (STAMPED if recipe.name == "franka" else ("external_joint_torque", "external_wrench")):
            subscriptions.append(client.create_subscription(
                publishers.TOPICS[topic], f"{recipe.node}/{topic}",
                lambda raw, _info, store=recipe.outputs[topic]: store.append(raw), reliable, callback_group=group,
                raw=True))
    outputs = InputLoop(client, subscriptions, group, threading.Lock())
    recording = threading.Thread(target=outputs.spin, daemon=True)
    recording.start()
    executor = SingleThreadedExecutor()
    executor.add_node(client)
    spinning = threading.Thread(target=executor.spin, daemon=True)
    spinning.start()

    def wait(condition, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            if any(process.poll() is not None for process in processes) or time.monotonic() > deadline:
                for log in logs:
                    log.seek(0)
                raise AssertionError(f"{what}: {[log.read()[-1500:] for log in logs]}")
            time.sleep(0.05)

    try:
        wait(lambda: all(_status(diagnostics, r.node, "model") is not None and _status(diagnostics, r.node, "model")
                         .message != "no estimator yet" for r in recipes), 180.0, "the nodes did not come up")
        problems = [_status(diagnostics, r.node, "model").message for r in recipes
                    if _status(diagnostics, r.node, "model").message.startswith("no estimator")]
        assert not problems, problems
        wait(lambda: all(s.get_publisher_count() > 0 for s in subscriptions), 30.0, "outputs never matched")
        # A matched publisher can come before its node's name (another discovery message, late on a busy machine)
        wait(lambda: {("kvark_estimator", r.namespace or "/") for r in recipes}
             <= set(client.get_node_names_and_namespaces()), 30.0, "the nodes' names never seen")
        for recipe in recipes:
            recipe.advertised = client.get_publisher_names_and_types_by_node("kvark_estimator",
                                                                             recipe.namespace or "/")
        seen = len(diagnostics)                 # each node's next /diagnostics tick notices our subscriptions
        wait(lambda: len(diagnostics) >= seen + 3, 10.0, "no /diagnostics tick")
        start = threading.Barrier(len(recipes) + 1)
        threads = [threading.Thread(target=_play, args=(recipe, start, players)) for recipe in recipes]
        for thread in threads:
            thread.start()
        start.wait(60.0)                        # every player's topics have their subscribers
        for thread in threads:
            thread.join(60.0)
        # until no output came for 1.5 s, or for 0.3 s once every node has published an estimate for each joint
        # state but its first (what a late extra estimate would then have to beat: a node publishes within ms)
        expected = [_states(recipe) - 1 for recipe in recipes]
        counts, quiet = None, time.monotonic()
        while time.monotonic() - quiet < (0.3 if counts == expected else 1.5):
            time.sleep(0.05)
            now = [len(r.outputs["external_joint_torque"]) for r in recipes]
            if now != counts:
                counts, quiet = now, time.monotonic()
    finally:
        for player in players:
            player.destroy_node()
        outputs.stop()
        recording.join(10.0)
        executor.shutdown()
        client.destroy_node()


@pytest.fixture(scope="module")
def played(recipes, tmp_path_factory) -> list[Recipe]:
    _run_nodes(recipes, tmp_path_factory.mktemp("run"))
    return recipes


def _replay(recipe: Recipe):
    """(config, stamps of the valid rows, ObserverRun) of ``kvark replay`` on the recipe's bag and file."""
    config = load_config(recipe.config)
    inputs = read_inputs(recipe.bag, config, log=None)[1]
    result = run_observer(config, load_model(config.model_dir, config.joint_names), inputs, config.observer)
    return config, inputs.stamp[result.valid], result


def _stamp(message) -> float:
    return message.header.stamp.sec + message.header.stamp.nanosec * 1e-9


@pytest.mark.parametrize("driver", ["franka", "ur", "lbr"])
def test_each_drivers_topics_into_the_node_from_its_recipe_equal_replay(played, driver):
    """Every estimate replay gives on the driver's bag arrives, nothing else, each within 1e-9 N·m (the same code
    on the same numbers): the topic, the rate, the unit (the UR's amperes through input.effort_scale, in the node
    as in replay) and, for KUKA, the namespace and the file's key and paths are right."""
    recipe = next(r for r in played if r.name == driver)
    config = load_config(recipe.config)
    torque = [(_stamp(m), np.asarray(m.effort), 0) for m in recipe.messages("external_joint_torque")]
    figures = node_check.compare(torque, config, config.model_dir, str(recipe.bag))
    states = _states(recipe)
    expected = states - 1                                  # every joint state but the first (it starts the filter)
    assert figures["estimates_expected"] == expected and states == {"franka": 2001, "ur": 1000, "lbr": 200}[driver]
    assert figures["estimates_received"] == figures["estimates_matched"] == expected, figures
    assert figures["max_abs_difference"] <= node_check.TOLERANCE
    frames = {m.header.frame_id for m in recipe.messages("external_wrench")}
    assert frames == {"franka": {"panda_link0"}, "ur": {"base"}, "lbr": {"lbr_link_0"}}[driver]


def test_the_urs_amperes_become_newton_metres(played):
    """The UR bag's effort is τ_m / k in A. With the scale, τ_ext is the synthetic stream's residual (its friction,
    at most 1.3 N·m per joint, plus noise, which the model trained on the same generator follows): below 3 N·m on
    every sample. Read as N·m (scale 1) the same bag would leave τ_ext = (1 − 1/k) of the gravity torque, which
    exceeds 20 N·m on the shoulder lift in this motion (checked here on the bag)."""
    recipe = next(r for r in played if r.name == "ur")
    tau = np.array([m.effort for m in recipe.messages("external_joint_torque")])
    assert np.abs(tau).max() < 3.0
    config, _, _ = _replay(recipe)
    inputs = read_inputs(recipe.bag, config, log=None)[1]
    gravity = RobotModel.from_config(config).gravity(inputs.q[0])
    assert abs((1.0 - 1.0 / UR_TORQUE_CONSTANTS[1]) * gravity[1]) > 20.0


def test_stamped_outputs_pair_by_header_stamp_and_hold_replays_values(played):
    """ExactTime pairing of τ_ext, σ, the wrench, the wrench with its covariance and the flags of the Franka node:
    every τ_ext stamp has exactly one message of each (nothing unpaired); σ and the flags are replay's, the wrench
    with covariance carries the wrench of the same stamp and frame, Σ_F symmetric with √diag = replay's σ_F."""
    recipe = next(r for r in played if r.name == "franka")
    by_topic = {topic: {_stamp(m): m for m in recipe.messages(topic)} for topic in STAMPED}
    assert all(len(by_topic[topic]) == len(recipe.outputs[topic]) for topic in STAMPED), "a repeated stamp"
    pairs = [tuple(by_topic[topic][stamp] for topic in STAMPED) for stamp in sorted(by_topic[STAMPED[0]])
             if all(stamp in by_topic[topic] for topic in STAMPED)]
    assert len(pairs) == len(by_topic[STAMPED[0]]) == 2000
    assert all(set(by_topic[topic]) == set(by_topic[STAMPED[0]]) for topic in STAMPED)
    _, stamps, result = _replay(recipe)
    assert np.array_equal([_stamp(pair[0]) for pair in pairs], stamps)
    sigma = np.array([pair[1].effort for pair in pairs])
    assert np.abs(sigma - result.tau_std[result.valid]).max() <= node_check.TOLERANCE
    flags = np.array([pair[4].position for pair in pairs])
    assert [pair[4].name for pair in pairs[:1]] == [list(publishers.FLAGS)]
    assert np.array_equal(flags[:, 0] == 1.0, result.contact[result.valid])
    assert np.array_equal(flags[:, 1] == 1.0, result.collision[result.valid])
    for _, _, wrench, with_covariance, _ in pairs:
        w, t = wrench.wrench, with_covariance.twist.twist
        assert [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z] == [
            t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z]
        assert wrench.header.frame_id == with_covariance.header.frame_id == "panda_link0"
    covariance = np.array([pair[3].twist.covariance for pair in pairs]).reshape(-1, 6, 6)
    assert np.array_equal(covariance, covariance.transpose(0, 2, 1))
    assert np.abs(np.sqrt(covariance[:, range(6), range(6)]) - result.wrench_std[result.valid]).max() <= 1e-9


def test_no_output_topic_without_a_header(played):
    """Every topic a running node advertises has a header, but the four deprecated ones (docs/ros.md) and ROS's own
    ``/rosout`` and ``/parameter_events``; the node advertises every topic of ``publishers.TOPICS``."""
    ours = {"/rosout", "/parameter_events"}
    for recipe in played:
        advertised = dict(recipe.advertised)
        assert {f"{recipe.node}/{topic}" for topic in publishers.TOPICS} <= set(advertised), recipe.name
        for topic, types in advertised.items():
            if topic in ours:
                continue
            package, _, name = types[0].split("/")
            kind = getattr(importlib.import_module(f"{package}.msg"), name)
            has_header = "header" in kind.get_fields_and_field_types()
            assert has_header != (topic.rsplit("/", 1)[1] in publishers.DEPRECATED), (recipe.name, topic, types)


def test_play_sends_no_commands_for_a_joint_states_effort_config(tmp_path):
    """``kvark play`` (and node-check) with a config whose τ_m is the joint states' effort publishes the joint states
    alone, so it never waits for a command subscriber that does not come; the bag needs no command topic."""
    bag = franka_bag(ROOT / "bags" / "panda_contact", tmp_path / "franka", seconds=0.1)
    recording = input_recording(bag, load_config(FRANKA_CONFIG).input)
    assert [name for name, _ in recording.topics] == ["franka/joint_states"] and len(recording.messages) == 101
    rclpy.init(domain_id=DOMAIN)
    try:
        player = BagPlayer(recording)
        assert [p.topic_name for p in player.topic_publishers] == ["/franka/joint_states"]
        player.destroy_node()
    finally:
        rclpy.try_shutdown()
