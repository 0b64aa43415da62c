"""Reliability under bad input (issue 7, items 1-2): property tests and a short soak.

``Estimator.step`` and the ROS node adapter (driven through the rclpy stand-in in
``test/ros_stand_in``, as in ``ros/test_node_logic_stand_in.py``) are fed NaN/Inf, wrong lengths,
stamps going backwards, duplicate stamps, long gaps, velocities far outside the training range,
huge torques, and JointState messages with reordered, missing or extra joints, and stale
commands. Properties: no exception, the output is finite or absent, and ``status`` (Estimator)
or a counter on /diagnostics (node) names the problem. Hypothesis runs a bounded number of
examples per property; one estimator and one node are built per module and reset per example.
"""
from __future__ import annotations

import array
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kvark_ros.core.config import flatten_parameters
from kvark_ros.core.estimation.estimator import Estimator, Status
from kvark_ros.core.estimation.model_store import save_model
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.tools import soak as soak_tool
from kvark_ros.tools.synthetic import synthetic_stream, train_synthetic

ROOT = Path(__file__).resolve().parents[2]
N = 7
DT = 0.002
WARM = 20                       # good samples before the fault
ALL_STATUSES = {value for key, value in vars(Status).items() if key.isupper()}
PROPERTY = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
FEW = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
BAD_VALUES = st.sampled_from([math.nan, math.inf, -math.inf])


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def trained(panda):
    return train_synthetic(panda, "panda", seed=11, duration=4.0, baselines=False)


@pytest.fixture(scope="module")
def stream(panda):
    """Good samples (0.2 s, 500 Hz) of the synthetic arm with a step external torque."""
    return synthetic_stream(panda, 0.2, seed=21)


@pytest.fixture(scope="module")
def estimator(panda_config, panda, trained):
    return Estimator(panda_config, panda, make_observer(panda_config.observer, trained, panda_config.filter))


def fresh(estimator: Estimator) -> Estimator:
    estimator.reset()
    estimator.counts.clear()
    return estimator


def sample(stream, k: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    return float(stream.stamp[k]), stream.q[k].copy(), stream.qd[k].copy(), stream.tau_m[k].copy()


def assert_finite_or_none(estimate) -> None:
    if estimate is None:
        return
    for value in (estimate.stamp, estimate.tau_ext, estimate.tau_cov, estimate.wrench, estimate.wrench_cov):
        assert value is None or np.isfinite(value).all(), estimate


def run_samples(estimator: Estimator, samples) -> list:
    """Step every sample; each output must be finite or None and the status a known one."""
    out = []
    for stamp, q, qd, tau_m in samples:
        estimate = estimator.step(stamp, q, qd, tau_m)
        assert_finite_or_none(estimate)
        assert estimator.status in ALL_STATUSES
        out.append(estimate)
    return out


def assert_state_spd(estimator: Estimator) -> None:
    min_eig, _, asymmetry = soak_tool.check_spd(soak_tool.state_covariances(estimator))
    assert min_eig > 0.0 and asymmetry <= soak_tool.SYMMETRY_TOLERANCE, (min_eig, asymmetry)


def same_estimates(a, b) -> bool:
    if (a is None) != (b is None):
        return False
    return a is None or (np.array_equal(a.tau_ext, b.tau_ext) and np.array_equal(a.wrench, b.wrench))


def assert_rejected_without_effect(estimator: Estimator, stream, bad, status: str) -> None:
    """``bad`` after WARM good samples is rejected with ``status`` and changes no later output."""
    good = [sample(stream, k) for k in range(WARM + 5)]
    reference = run_samples(fresh(estimator), good)
    fresh(estimator)
    run_samples(estimator, good[:WARM])
    assert estimator.step(*bad) is None
    assert estimator.status == status and estimator.counts[status] == 1
    after = run_samples(estimator, good[WARM:])
    assert all(same_estimates(x, y) for x, y in zip(after, reference[WARM:])), "a rejected sample reached the filter"
    assert_state_spd(estimator)


# --------------------------------------------------------------------------- Estimator.step


@PROPERTY
@given(field=st.integers(0, 3), joint=st.integers(0, N - 1), value=BAD_VALUES)
def test_nan_or_inf_in_any_field_is_rejected_and_named(estimator, stream, field, joint, value):
    stamp, q, qd, tau_m = sample(stream, WARM)
    if field == 0:
        stamp = value
    else:
        (q, qd, tau_m)[field - 1][joint] = value
    assert_rejected_without_effect(estimator, stream, (stamp, q, qd, tau_m), Status.NON_FINITE)


@PROPERTY
@given(which=st.integers(0, 2), length=st.integers(0, 12).filter(lambda m: m != N), two_d=st.booleans())
def test_wrong_lengths_are_rejected_and_named(estimator, stream, which, length, two_d):
    stamp, q, qd, tau_m = sample(stream, WARM)
    arrays = [q, qd, tau_m]
    arrays[which] = np.zeros((1, N) if two_d else length)
    assert_rejected_without_effect(estimator, stream, (stamp, *arrays), Status.BAD_SHAPE)


@PROPERTY
@given(back=st.one_of(st.just(0.0), st.floats(1e-9, 1e6)))
def test_time_going_backwards_or_duplicate_stamps_are_rejected(estimator, stream, back):
    stamp, q, qd, tau_m = sample(stream, WARM)
    previous = float(stream.stamp[WARM - 1])
    assert_rejected_without_effect(estimator, stream, (previous - back, q, qd, tau_m), Status.STAMP_NOT_INCREASING)


@PROPERTY
@given(extra=st.floats(1e-6, 1e6))
def test_gaps_longer_than_max_gap_reset_the_filter(estimator, stream, panda_config, extra):
    fresh(estimator)
    run_samples(estimator, [sample(stream, k) for k in range(WARM)])
    previous = float(stream.stamp[WARM - 1])
    _, q, qd, tau_m = sample(stream, WARM)
    stamp = previous + panda_config.input.max_gap + max(extra, 1e-9 * previous)
    assert estimator.step(stamp, q, qd, tau_m) is None
    assert estimator.status == Status.GAP_RESET and estimator.counts[Status.GAP_RESET] == 1
    # The filter starts over: the next sample estimates from the reset state.
    estimate = estimator.step(stamp + DT, *sample(stream, WARM + 1)[1:])
    assert estimate is not None and estimator.status == Status.OK
    assert_finite_or_none(estimate)
    assert_state_spd(estimator)


def test_a_gap_of_at_most_max_gap_does_not_reset(estimator, stream, panda_config):
    fresh(estimator)
    run_samples(estimator, [sample(stream, k) for k in range(WARM)])
    stamp = float(stream.stamp[WARM - 1]) + 0.999 * panda_config.input.max_gap
    assert estimator.step(stamp, *sample(stream, WARM)[1:]) is not None
    assert estimator.counts[Status.GAP_RESET] == 0


@PROPERTY
@given(fraction=st.lists(st.floats(-0.99, 0.99), min_size=N, max_size=N), steps=st.integers(1, 40),
       scale=st.floats(0.0, 1.0))
def test_velocities_far_outside_training_stay_finite(estimator, stream, trained, fraction, steps, scale):
    """Velocities up to the URDF's bound (2 × its limit, far beyond the training's ≲ 1 rad/s) and torques up to 11 ×
    the last (within the bound): every estimate finite, the filter healthy; a joint that drives past its position bound is rejected."""
    fresh(estimator)
    run_samples(estimator, [sample(stream, k) for k in range(WARM)])
    qd_far = np.array(fraction) * estimator.limits.qd_max
    q = stream.q[WARM - 1]
    bound = 0.99 * estimator.limits.tau_max
    tau_m = np.clip(stream.tau_m[WARM - 1] * (1.0 + 10.0 * scale), -bound, bound)
    stamps = float(stream.stamp[WARM - 1]) + DT * np.arange(1, steps + 1)
    out = run_samples(estimator, [(t, q + DT * qd_far * i, qd_far, tau_m) for i, t in enumerate(stamps)])
    assert estimator.status in (Status.OK, Status.DIVERGED_RESET, Status.BEYOND_LIMITS)
    assert any(e is not None for e in out) or estimator.counts[Status.DIVERGED_RESET] > 0
    assert_state_spd(estimator)


def test_residual_variance_inflates_outside_the_training_range(trained, stream):
    """The residual model is less sure far from its data: its variance grows, the filter trusts it less."""
    _, inside = trained.residual.predict(stream.qd[WARM])
    for speed in (5.0, 20.0, 50.0):
        for sign in (1.0, -1.0):
            mean, outside = trained.residual.predict(np.full(N, sign * speed))
            assert np.isfinite(mean).all() and np.isfinite(outside).all()
            assert (outside >= inside).all(), (speed, outside, inside)
            assert outside.sum() > inside.sum()


@PROPERTY
@given(fraction=st.lists(st.one_of(st.floats(-1.0, 1.0), st.sampled_from([1.0, -1.0])), min_size=N, max_size=N),
       steps=st.integers(1, 30))
def test_saturated_torques_stay_finite(estimator, stream, fraction, steps):
    """τ_m anywhere up to the URDF's bound (2 × the effort limit), held for up to 60 ms: finite, healthy, and it
    recovers; beyond the bound the sample is rejected as beyond the limits."""
    fresh(estimator)
    run_samples(estimator, [sample(stream, k) for k in range(WARM)])
    tau = np.array(fraction) * estimator.limits.tau_max
    samples = [(float(stream.stamp[WARM + i]), stream.q[WARM + i], stream.qd[WARM + i], tau) for i in range(steps)]
    run_samples(estimator, samples)
    assert estimator.status in (Status.OK, Status.DIVERGED_RESET)
    assert_state_spd(estimator)
    # And it recovers: good samples give estimates again (after a reset if the filter diverged).
    fresh_out = run_samples(estimator, [sample(stream, k) for k in range(WARM + steps, WARM + steps + 5)])
    assert fresh_out[-1] is not None
    beyond = 1.01 * estimator.limits.tau_max
    assert estimator.step(float(stream.stamp[WARM + steps + 5]), stream.q[WARM + steps + 5], stream.qd[WARM + steps + 5],
                          beyond) is None and estimator.status == Status.BEYOND_LIMITS


ANY_FLOAT = st.one_of(st.floats(-1e3, 1e3), st.floats(allow_nan=True, allow_infinity=True),
                      st.sampled_from([0.0, 1e6, -1e6, 1e300, -1e300, math.nan, math.inf]))


@st.composite
def fuzz_samples(draw):
    """A sequence of samples from good ones with any field spoiled: values, lengths, stamps."""
    out = []
    stamp = 0.0
    for k in range(draw(st.integers(1, 30))):
        _ = k
        stamp += draw(st.one_of(st.just(DT), st.floats(-1.0, 1.0), st.sampled_from([0.0, 0.06, -0.06, 1e6])))
        arrays = []
        for _field in range(3):
            length = draw(st.sampled_from([N, N, N, N, 0, 6, 8]))
            arrays.append(np.array(draw(st.lists(ANY_FLOAT, min_size=length, max_size=length)), dtype=float))
        out.append((draw(st.one_of(st.just(stamp), ANY_FLOAT)), *arrays))
    return out


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")   # 1e300 @ 1e300: rejected as Inf
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")   # inf + -inf: rejected
@PROPERTY
@given(samples=fuzz_samples())
def test_any_input_sequence_gives_finite_output_or_none_and_counts_every_step(estimator, samples):
    fresh(estimator)
    out = run_samples(estimator, samples)
    assert sum(estimator.counts.values()) == len(samples)
    for estimate, status in zip(out, [None] * len(out)):
        del status
        assert estimate is None or estimate.tau_ext.shape == (N,)
    assert_state_spd(estimator)


# --------------------------------------------------------------------------- the ROS node (stand-in)

OUT = "/kvark_estimator"
OUTPUT_TOPICS = (f"{OUT}/external_joint_torque", f"{OUT}/external_wrench", f"{OUT}/external_joint_torque_stddev",
                 f"{OUT}/external_wrench_covariance")


@pytest.fixture(scope="module")
def node(ros, trained, tmp_path_factory):
    """One node (config/panda.yaml, a synthetic model) for the module; ``reset_node`` between examples."""
    directory = tmp_path_factory.mktemp("reliability_model") / "panda"
    save_model(directory, trained)
    document = yaml.safe_load((ROOT / "config" / "panda.yaml").read_text())
    parameters = flatten_parameters(document["kvark_estimator"]["ros__parameters"])
    parameters["residual_model.model_dir"] = str(directory)
    ros.core.reset()
    ros.rclpy.init()
    the_node = ros.node.EstimatorNode(
        parameter_overrides=[ros.Parameter(name, value=value) for name, value in parameters.items()])
    assert the_node._estimator is not None, the_node._model_problem
    yield the_node
    the_node.destroy_node()
    ros.rclpy.try_shutdown()
    ros.core.reset()


def reset_node(node) -> None:
    node._estimator.reset()
    node._pairer.reset()
    node._counts.clear()
    node._estimator.counts.clear()


def all_counts(node) -> dict:
    return dict(node._all_counts())


def published_since(ros, marks: dict) -> dict:
    return {topic: ros.core.GRAPH.published(topic)[marks[topic]:] for topic in OUTPUT_TOPICS}


def assert_published_finite(messages: dict) -> None:
    for topic, msgs in messages.items():
        for msg in msgs:
            if hasattr(msg, "wrench"):
                w = msg.wrench
                values = [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]
            else:
                values = msg.effort if hasattr(msg, "effort") else msg.data
            assert np.isfinite(np.asarray(values, dtype=float)).all(), topic


NAMES = [f"panda_joint{i}" for i in range(1, N + 1)]
NODE_FAULTS = ("nan_position", "nan_velocity", "inf_command", "reordered", "extra_joints", "missing_joint",
               "duplicate_stamp", "older_stamp", "stale_command", "malformed", "bad_command", "unknown_joints")
# The diagnostic counter each fault must increment (None: valid input, same output as without it).
EXPECTED_COUNTER = {
    "nan_position": Status.NON_FINITE, "nan_velocity": Status.NON_FINITE, "inf_command": Status.NON_FINITE,
    "missing_joint": "MISSING_JOINT", "duplicate_stamp": "OUT_OF_ORDER", "older_stamp": "OUT_OF_ORDER",
    "stale_command": "STALE", "malformed": "MALFORMED", "bad_command": "BAD_COMMAND",
    "unknown_joints": "OTHER_JOINTS", "reordered": None, "extra_joints": None,
}


def node_messages(ros, stream, faults: dict[int, str]) -> list[tuple[int, str, object]]:
    """(clock ns, topic, message) for the stream's samples, with ``faults[k]`` applied to sample k."""
    out = []
    last = None
    for k in range(len(stream.stamp)):
        fault = faults.get(k)
        t_ns = int(round(stream.stamp[k] * 1e9)) + 1_000_000_000
        names = list(NAMES)
        position, velocity, effort = (list(map(float, stream.q[k])), list(map(float, stream.qd[k])),
                                      list(map(float, stream.tau_m[k])))
        command = list(effort)
        stamp_ns = t_ns
        if fault == "nan_position":
            position[k % N] = math.nan
        elif fault == "nan_velocity":
            velocity[(k + 3) % N] = math.nan
        elif fault == "inf_command":
            command[k % N] = math.inf
        elif fault == "reordered":
            order = [(i * 3) % N for i in range(N)]
            names, position, velocity = ([names[i] for i in order], [position[i] for i in order],
                                         [velocity[i] for i in order])
        elif fault == "extra_joints":
            names, position, velocity = (names + ["panda_finger_joint1", "panda_finger_joint2"],
                                         position + [0.01, 0.01], velocity + [0.0, 0.0])
        elif fault == "missing_joint":
            drop = k % N
            names, position, velocity = ([x for i, x in enumerate(names) if i != drop],
                                         [x for i, x in enumerate(position) if i != drop],
                                         [x for i, x in enumerate(velocity) if i != drop])
        elif fault in ("duplicate_stamp", "older_stamp") and last is not None:
            stamp_ns = last - (0 if fault == "duplicate_stamp" else 4_000_000)
        elif fault == "malformed":
            velocity = velocity[:-1]
        elif fault == "unknown_joints":
            names = ["gripper_a", "gripper_b"]
            position, velocity = [0.0, 0.0], [0.0, 0.0]
        effort_field = effort[:len(names)] + [0.0] * max(0, len(names) - len(effort))
        header = ros.std.Header(stamp=ros.builtin.Time(sec=stamp_ns // 1_000_000_000,
                                                       nanosec=stamp_ns % 1_000_000_000))
        state = ros.sensor.JointState(header=header, name=names, position=array.array("d", position),
                                      velocity=array.array("d", velocity), effort=array.array("d", effort_field))
        out.append((t_ns, "/joint_states", state))
        if fault == "stale_command":
            pass                                  # no command for this and the next samples
        elif fault == "bad_command":
            out.append((t_ns, "/effort_commands", ros.std.Float64MultiArray(data=array.array("d", command[:-2]))))
        else:
            out.append((t_ns, "/effort_commands", ros.std.Float64MultiArray(data=array.array("d", command))))
        if fault is None:          # a stamp the node surely took: a later duplicate repeats it
            last = stamp_ns
    return out


def drive(ros, node, messages) -> tuple[dict, dict]:
    """Feed ``messages``; (counts before → after difference, everything published meanwhile)."""
    reset_node(node)
    marks = {topic: len(ros.core.GRAPH.published(topic)) for topic in OUTPUT_TOPICS}
    for t_ns, topic, msg in messages:
        ros.core.set_time(nanoseconds=t_ns)
        ros.core.GRAPH.deliver(topic, msg)
    return all_counts(node), published_since(ros, marks)


def counter_key(ros, name: str | None) -> str | None:
    return getattr(ros.node.Drop, name) if name is not None and hasattr(ros.node.Drop, name) else name


@FEW
@given(faults=st.dictionaries(st.integers(WARM, 80), st.sampled_from(NODE_FAULTS), min_size=1, max_size=6),
       stale_run=st.integers(1, 12))
def test_node_survives_bad_messages_and_counts_them(ros, node, stream, faults, stale_run):
    # A stale command lasts several samples: the node pairs a state with a command at most
    # input.command_max_age older, then rejects it as stale.
    faults = dict(faults)
    for k, fault in list(faults.items()):
        if fault == "stale_command":
            for j in range(k + 1, k + stale_run):
                faults.setdefault(j, "stale_command")
    messages = node_messages(ros, SimpleNamespace(stamp=stream.stamp[:100], q=stream.q, qd=stream.qd,
                                                  tau_m=stream.tau_m), faults)
    counts, published = drive(ros, node, messages)
    assert_published_finite(published)
    assert len(published[f"{OUT}/external_joint_torque"]) > 0
    longest, run = 0, 0                           # longest run of consecutive samples without a command
    for k in range(100):
        run = run + 1 if faults.get(k) == "stale_command" else 0
        longest = max(longest, run)
    for fault in set(faults.values()):
        key = counter_key(ros, EXPECTED_COUNTER[fault])
        if fault == "stale_command" and longest * DT <= node._config.input.command_max_age + DT / 2:
            continue                              # a short run is bridged by the previous command
        if key is not None:
            assert counts.get(key, 0) > 0, (fault, counts)
    node._publish_diagnostics()                   # the summary is built without error
    assert ros.core.GRAPH.published("/diagnostics")


@pytest.mark.parametrize("fault", NODE_FAULTS)
def test_node_each_fault_increments_its_counter(ros, node, stream, fault):
    faults = {k: fault for k in range(30, 40 if fault == "stale_command" else 31)}
    counts, published = drive(ros, node, node_messages(ros, stream, faults))
    assert_published_finite(published)
    key = counter_key(ros, EXPECTED_COUNTER[fault])
    rejected = {k: v for k, v in counts.items() if k not in (Status.OK, Status.WARMUP)}
    if key is None:                                   # valid input: nothing rejected
        assert rejected == {}, counts
        assert len(published[f"{OUT}/external_joint_torque"]) == len(stream.stamp) - 1
    else:
        assert counts.get(key, 0) >= 1, counts
    node._publish_diagnostics()


def test_node_reordered_and_extra_joints_change_nothing(ros, node, stream):
    plain = node_messages(ros, stream, {})
    shuffled = node_messages(ros, stream, {k: ("reordered" if k % 2 else "extra_joints")
                                           for k in range(len(stream.stamp))})
    _, a = drive(ros, node, plain)
    _, b = drive(ros, node, shuffled)
    tau_a = np.array([m.effort for m in a[f"{OUT}/external_joint_torque"]])
    tau_b = np.array([m.effort for m in b[f"{OUT}/external_joint_torque"]])
    assert tau_a.shape == (len(stream.stamp) - 1, N) and np.array_equal(tau_a, tau_b)


def test_node_nan_sample_is_not_published_and_counted(ros, node, stream):
    counts, published = drive(ros, node, node_messages(ros, stream, {30: "nan_position", 40: "inf_command"}))
    assert counts[Status.NON_FINITE] == 2
    assert len(published[f"{OUT}/external_joint_torque"]) == len(stream.stamp) - 1 - 2
    assert_published_finite(published)


# --------------------------------------------------------------------------- short soak


def test_short_soak_has_no_nan_no_crash_and_spd_covariance(panda_config, panda, trained):
    result = soak_tool.soak(panda_config, panda, trained, steps=2 * 10 ** 4, seed=3, check_every=2000)
    summary = result.summary()
    assert result.failures() == [], summary
    assert summary["steps"] == 2 * 10 ** 4 and summary["crashes"] == 0 and summary["nan_outputs"] == 0
    assert summary["faults_injected"] > 10 and summary["misclassified"] == {}, summary
    assert summary["min_eig_P"] > 0.0 and summary["checks"] == 10
    assert summary["outputs"] > 0.9 * summary["steps"]


def test_soak_failures_name_nan_crash_and_non_spd():
    assert soak_tool.SoakResult(min_eig_P=1.0).failures() == []
    assert len(soak_tool.SoakResult(nan_outputs=1, crashes=1, first_crash="Traceback\nValueError: x",
                                    non_spd_checks=1, min_eig_P=-1.0).failures()) == 3
    assert soak_tool.check_spd([np.array([[1.0, 2.0], [2.0, 1.0]])])[0] < 0.0
    assert math.isnan(soak_tool.check_spd([np.full((2, 2), math.nan)])[0])
