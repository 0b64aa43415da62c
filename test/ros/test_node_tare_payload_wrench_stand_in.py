"""The node's issue-15 features through the rclpy STAND-IN (not ROS): tare, run-time payload, the wrench in both
frames, the collision flag, the output QoS and the configured input topics.

Streams at rest are built here, exactly constant (no noise). The tare and payload tests run the ``kfmo``
observer (a Kalman momentum observer without a learned residual, so τ̂ = g_model(q) − τ_m at rest): it
settles to 1e-9 N·m within 0.5 s, while the default observer with the suite's small model (1 s of
training data) takes ~3 s on joint 2 and adds its residual mean, a function of g(q) that a payload
changes. The tolerances are then rounding (1e-9 N·m) unless a test says otherwise. Fixtures and helpers
come from ``test_node_logic_stand_in`` (the same stand-in machinery and trained model).
"""
from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.payload import Payload
from kvark_ros.core.estimation.robot_model import RobotModel

from test_node_logic_stand_in import (OUT, bag_messages, contact_bag, diagnostics, feed, make_node,  # noqa: F401
                                 model_dir, outputs, stamp_of, values_of)

ROOT = Path(__file__).resolve().parents[2]
Q0 = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8])            # rad, a pose away from singularities
BIAS = np.array([1.0, -2.0, 1.5, 3.0, -0.5, 0.8, -0.3])         # N·m the nominal model misses at rest
TOOL = Payload(2.0, (0.0, 0.0, 0.1), (0.01, 0.01, 0.01, 0.0, 0.0, 0.0))
ESTIMATE_TOPICS = ("external_joint_torque", "external_wrench", "external_wrench_in_base_frame",
                   "external_wrench_in_ee_frame", "external_joint_torque_stddev_stamped",
                   "external_wrench_with_covariance", "contact_state", "external_joint_torque_stddev",
                   "external_wrench_covariance", "contact", "collision")


def stream(ros, names, start: float, seconds: float, tau_m, qd=None, topics=("/joint_states", "/effort_commands")):
    """(log ns, topic, message) at 500 Hz from ``start`` s: a joint state at q = Q0 + q̇ t and, 0.1 ms later, its
    command τ_m (a function of the sample index, or an array), labelled with the joint names."""
    qd = np.zeros(7) if qd is None else qd
    out = []
    for k in range(int(round(seconds * 500))):
        t = start + 0.002 * k
        ns = int(round(t * 1e9))
        stamp = ros.builtin.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        state = ros.sensor.JointState(header=ros.std.Header(stamp=stamp), name=list(names),
                                      position=(Q0 + qd * (t - start)).tolist(), velocity=qd.tolist(),
                                      effort=[0.0] * 7)
        torque = tau_m(k) if callable(tau_m) else tau_m
        layout = ros.std.MultiArrayLayout(dim=[ros.std.MultiArrayDimension(label=",".join(names), size=7, stride=7)])
        out += [(ns, topics[0], state), (ns + 100_000, topics[1],
                                         ros.std.Float64MultiArray(layout=layout, data=np.asarray(torque).tolist()))]
    return out


def published_tau(ros) -> np.ndarray:
    return outputs(ros).tau


def call(ros, service: str):
    return ros.core.GRAPH.call(f"{OUT}/{service}")


def test_tare_subtracts_the_rest_offset_and_reset_clears_it(ros, make_node):
    """τ_m = g(q0) − BIAS at rest: τ̂ = BIAS; after a 1 s tare the published τ̂ is rounding (1e-9 N·m against a
    0.3 N·m smallest bias)."""
    node = make_node(observer="kfmo")
    names = node._config.joint_names
    tau_m = node._estimator.robot.gravity(Q0) - BIAS
    assert not call(ros, "tare").success, "no joint state yet"
    feed(ros, stream(ros, names, 0.0, 1.0, tau_m))
    untared = published_tau(ros)[-1]
    assert np.abs(untared - BIAS).max() < 1e-9
    reply = call(ros, "tare")
    assert reply.success and "averaging" in reply.message and "1 s" in reply.message
    feed(ros, stream(ros, names, 1.0, 1.2, tau_m))
    assert np.abs(published_tau(ros)[-50:]).max() < 1e-9
    assert np.abs(outputs(ros).wrench[-50:]).max() < 1e-8
    assert call(ros, "reload_model").success and node._estimator.tare.state == "active", "a reload keeps the tare"
    feed(ros, stream(ros, names, 2.2, 0.2, tau_m))
    assert np.abs(published_tau(ros)[-100:]).max() < 1e-9
    ros.core.set_time(3.0)                      # the /diagnostics of 2.0 s came before the last averaged sample
    status = diagnostics(ros)["tare"]
    values = values_of(status)
    assert status.level == ros.diag.DiagnosticStatus.OK and values["state"] == "active" and values["samples"] == "501"
    assert float(values[f"offset_nm {names[3]}"]) == pytest.approx(untared[3], abs=1e-4)    # printed to 4 digits
    reply = call(ros, "reset")
    assert reply.success and "tare cleared" in reply.message and node._estimator.tare.state == "idle"
    feed(ros, stream(ros, names, 3.5, 1.0, tau_m))
    assert np.abs(published_tau(ros)[-1] - untared).max() < 1e-9, "untared again"


def test_tare_is_refused_in_motion_and_aborted_when_motion_starts(ros, make_node):
    node = make_node()
    names = node._config.joint_names
    moving = np.zeros(7)
    moving[2] = 0.1                                            # rad/s > tare.max_speed 0.02
    gravity = node._estimator.robot.gravity(Q0)
    feed(ros, stream(ros, names, 0.0, 0.2, gravity, qd=moving))
    reply = call(ros, "tare")
    assert not reply.success and "not at rest" in reply.message and f"{names[2]} moves at 0.100 rad/s" in reply.message
    feed(ros, stream(ros, names, 0.2, 0.2, gravity))
    assert call(ros, "tare").success
    feed(ros, stream(ros, names, 0.4, 0.2, gravity, qd=moving))
    ros.core.set_time(1.0)
    status = diagnostics(ros)["tare"]
    assert status.level == ros.diag.DiagnosticStatus.WARN and "aborted" in status.message and names[2] in status.message
    assert values_of(status)["state"] == "idle"


def test_payload_parameters_change_the_model_at_run_time(ros, make_node):
    """The arm holds a 2 kg tool the model lacks, τ̂ = −g_tool; set as parameters, τ̂ moves by g_tool (from
    pinocchio via RobotModel) and the filter continues (no warm-up)."""
    node = make_node(observer="kfmo")
    names = node._config.joint_names
    config = node._config
    tau_m = RobotModel.from_config(replace(config, payload=TOOL)).gravity(Q0)
    g_tool = tau_m - RobotModel.from_config(config).gravity(Q0)
    feed(ros, stream(ros, names, 0.0, 1.0, tau_m))
    before = published_tau(ros)[-1]
    P = ros.Parameter
    [result] = node.set_parameters([P("robot_model.payload.mass", value=TOOL.mass)])
    assert result.successful, result.reason
    [result] = node.set_parameters([P("robot_model.payload.inertia", value=list(TOOL.inertia))])    # diagonal first
    assert not result.successful and "write [0.01, 0, 0, 0.01, 0, 0.01]" in result.reason
    for name, value in (("com", list(TOOL.com)), ("inertia", [0.01, 0.0, 0.0, 0.01, 0.0, 0.01])):   # ixx ixy … izz
        [result] = node.set_parameters([P(f"robot_model.payload.{name}", value=value)])
        assert result.successful, result.reason
    assert node._estimator.robot.payload == TOOL and node._config.payload == TOOL
    feed(ros, stream(ros, names, 1.0, 1.0, tau_m))
    after = published_tau(ros)
    assert len(after) == 999, "one warm-up sample in all: the filter continued"
    assert np.abs(g_tool).max() > 5.0 and np.abs(after[-1] - before - g_tool).max() < 1e-9

    [result] = node.set_parameters([P("robot_model.payload.inertia", value=[1.0, 0.0, 0.0, 1.0, 0.0, 5.0])])
    assert not result.successful and "triangle inequality" in result.reason and "payload" in result.reason
    [result] = node.set_parameters([P("robot_model.payload.mass", value=-1.0)])
    assert not result.successful
    assert node._estimator.robot.payload == TOOL and node._config.payload == TOOL
    ros.core.set_time(3.0)
    assert values_of(diagnostics(ros)["model"])["payload"] == "2 kg at [0.0, 0.0, 0.1] m"


def test_the_wrench_in_base_and_ee_frame(ros, make_node, contact_bag):
    """Both topics every sample while subscribed, frame ids the root link and ee_frame, one rotation of the
    ee_frame apart (pinocchio's forward kinematics at the sample's q; 1e-9 N is rounding); ~/external_wrench is
    the wrench.frame one, also after wrench.frame changes at run time. Without a subscriber: not published."""
    make_node()
    feed(ros, bag_messages(ros, contact_bag)[:200])
    assert not ros.core.GRAPH.published(f"{OUT}/external_wrench_in_base_frame")
    node = make_node()
    listener = ros.rclpy.node.Node("wrench_listener")
    for topic in ("external_wrench_in_base_frame", "external_wrench_in_ee_frame"):
        [publisher] = ros.core.GRAPH.publishers[f"{OUT}/{topic}"]
        listener.create_subscription(publisher.msg_type, f"{OUT}/{topic}", lambda msg: None, 10)
    node._outputs.check_subscribers()                 # at once, rather than at the next check (100 estimates)
    messages = bag_messages(ros, contact_bag)[:400]
    feed(ros, messages[:200])
    [result] = node.set_parameters([ros.Parameter("wrench.frame", value="end_effector")])
    assert result.successful
    feed(ros, messages[200:])
    graph = ros.core.GRAPH
    base = graph.published(f"{OUT}/external_wrench_in_base_frame")
    ee = graph.published(f"{OUT}/external_wrench_in_ee_frame")
    legacy = graph.published(f"{OUT}/external_wrench")
    assert len(base) == len(ee) == len(legacy) == 199
    assert {m.header.frame_id for m in base} == {"panda_link0"}
    assert {m.header.frame_id for m in ee} == {node._config.ee_frame}
    assert legacy[:99] == base[:99] and legacy[99:] == ee[99:]
    q_at = {stamp_of(m): np.array(m.position) for _, topic, m in messages if topic == "/joint_states"}
    robot = RobotModel.from_config(node._config)

    def values(m):
        w = m.wrench
        return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])

    for in_base, in_ee in zip(base, ee):
        pin.framesForwardKinematics(robot.model, robot.data, q_at[stamp_of(in_base)])
        rotation = robot.data.oMf[robot.ee_frame_id].rotation
        expected = np.concatenate([rotation.T @ values(in_base)[:3], rotation.T @ values(in_base)[3:]])
        assert np.abs(values(in_ee) - expected).max() < 1e-9


def test_collision_flag_on_a_big_torque_step_not_on_a_small_one(ros, make_node):
    """At rest a step of −τ in τ_m on joint 4 is τ_ext = +τ: 3 × contact.collision_torque raises ~/collision
    within 20 ms (the filter's onset detector jumps to it) and it falls once the step ends; 0.3 × (2.6 N·m, plus
    the residual model's mean at rest) never does: |τ̂| stays below the limit whatever σ is."""
    node = make_node()
    names = node._config.joint_names
    limit = node._config.contact.collision_torque
    gravity = node._estimator.robot.gravity(Q0)
    for factor, expected in ((3.0, True), (0.3, False)):
        make_node()
        step = np.zeros(7)
        step[3] = factor * limit

        def tau_m(k):
            return gravity - step if 250 <= k < 350 else gravity      # 0.5-0.7 s

        feed(ros, stream(ros, names, 0.0, 1.2, tau_m))
        flags = np.array([m.position[1] == 1.0 for m in ros.core.GRAPH.published(f"{OUT}/contact_state")])
        stamps = outputs(ros).stamp
        assert flags.any() == expected
        assert not flags[stamps < 0.5].any() and not flags[stamps > 0.8].any()
        if expected:
            assert stamps[flags][0] <= 0.52 and flags[(stamps > 0.52) & (stamps < 0.7)].all()


@pytest.mark.parametrize("qos, reliability", [("reliable", "RELIABLE"), ("sensor_data", "BEST_EFFORT")])
def test_output_qos_is_applied_to_the_estimate_topics(ros, make_node, qos, reliability):
    make_node(output__qos=qos)
    for topic in ESTIMATE_TOPICS:
        [publisher] = ros.core.GRAPH.publishers[f"{OUT}/{topic}"]
        profile = publisher.qos_profile
        assert profile.reliability.name == reliability and profile.depth == 100, topic     # input.queue_depth
        assert profile.durability.name == "VOLATILE"
    [diagnostics_publisher] = ros.core.GRAPH.publishers["/diagnostics"]
    assert diagnostics_publisher.qos_profile.reliability.name == "RELIABLE"


def test_input_topic_names_come_from_the_config(ros, make_node, contact_bag):
    messages = bag_messages(ros, contact_bag)[:200]
    make_node()
    feed(ros, messages)
    plain = outputs(ros)
    make_node(input__joint_states_topic="/franka/joint_states", input__effort_commands_topic="controller/commands")
    assert set(ros.core.GRAPH.subscriptions) >= {"/franka/joint_states", "/controller/commands"}
    assert "/joint_states" not in ros.core.GRAPH.subscriptions
    renamed = {"/joint_states": "/franka/joint_states", "/effort_commands": "/controller/commands"}
    feed(ros, [(ns, renamed[topic], msg) for ns, topic, msg in messages])
    got = outputs(ros)
    assert len(got.stamp) == 99 and np.array_equal(got.tau, plain.tau)


def test_launch_file_resolves_paths_against_the_config_folder_and_maps_its_arguments(tmp_path):
    """launch/estimator.launch.py needs ROS to run; the parameters it passes are ``launch_parameters``' (core, run
    here): relative paths as ``kvark`` resolves them, URDF specs that name no file kept, and a file keyed for any
    namespace (``/**/kvark_estimator``) read as the node reads it. Its argument table is read from its source."""
    from kvark_ros.core.config import launch_parameters
    parameters = launch_parameters(ROOT / "config" / "panda.yaml")
    assert parameters["residual_model.model_dir"] == str(load_config(ROOT / "config" / "panda.yaml").model_dir)
    assert parameters["robot_model.urdf"] == "example-robot-data:panda"
    document = yaml.safe_load((ROOT / "config" / "panda.yaml").read_text())
    section = document.pop("kvark_estimator")
    section["ros__parameters"]["robot_model"]["urdf"] = "robot_description"
    section["ros__parameters"]["model_augmentation"] = "augmentation.yaml"
    (tmp_path / "arm.yaml").write_text(yaml.safe_dump({"/**/kvark_estimator": section}))
    parameters = launch_parameters(tmp_path / "arm.yaml")
    assert parameters["robot_model.urdf"] == "robot_description"
    assert parameters["model_augmentation"] == str(tmp_path / "augmentation.yaml")
    tree = ast.parse((ROOT / "launch" / "estimator.launch.py").read_text())
    [table] = [node.value for node in tree.body if isinstance(node, ast.Assign)
               and getattr(node.targets[0], "id", "") == "INPUT_ARGUMENTS"]
    assert dict(ast.literal_eval(table)) == {"torque_source": "torque_source", "joint_states": "joint_states_topic",
                                             "effort_commands": "effort_commands_topic"}
    assert "launch_parameters(LaunchConfiguration('config').perform(context))" in ast.unparse(tree)
