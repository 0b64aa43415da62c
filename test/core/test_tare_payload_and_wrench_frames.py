"""Tare, run-time payload and the wrench in both frames (ROS-free):
``kvark_ros.core.estimation.tare`` and the Estimator API.

Streams at rest are exactly constant (no noise), so the filter settles to a constant and what a tare
leaves is rounding; the tolerances below say which. models/panda (committed) is the trained model.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from kvark_ros.core.estimation.estimator import Estimator, payload_problem
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.payload import Payload
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.tare import ACTIVE, AVERAGING, IDLE, Tare, TareError

ROOT = Path(__file__).resolve().parents[2]
NAMES = tuple(f"j{i}" for i in range(1, 4))
Q0 = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8])            # rad, a pose away from singularities
BIAS = np.array([1.0, -2.0, 1.5, 3.0, -0.5, 0.8, -0.3])         # N·m the nominal model misses at rest
TOOL = Payload(2.0, (0.0, 0.0, 0.1), (0.01, 0.01, 0.01, 0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def trained(panda_config):
    return load_model(ROOT / "models" / "panda", panda_config.joint_names)


def test_tare_averages_at_rest_and_subtracts():
    tare = Tare(NAMES, duration=0.01, max_speed=0.02)
    with pytest.raises(TareError, match="no joint state"):
        tare.start()
    rest, tau = np.zeros(3), np.array([1.0, 2.0, 3.0])
    assert tare.apply(0.0, rest, tau) is tau and tare.state == IDLE
    tare.start()
    assert tare.state == AVERAGING
    out = [tare.apply(0.002 * k, rest, tau + 0.1 * k) for k in range(1, 7)]    # stamps 0.002 … 0.012 s
    assert tare.state == ACTIVE and tare.samples == 6, "averaged until 0.01 s after the first sample"
    assert np.allclose(tare.offset, tau + 0.35)                                # mean of 0.1 k, k = 1…6
    assert out[-1] == pytest.approx(tau + 0.6 - tare.offset)
    assert tare.apply(0.1, rest, tau) == pytest.approx(tau - tare.offset)
    tare.clear()
    assert tare.state == IDLE and tare.apply(0.2, rest, tau) is tau


def test_tare_refuses_in_motion_and_aborts_when_motion_starts():
    tare = Tare(NAMES, duration=0.01, max_speed=0.02)
    tau = np.ones(3)
    tare.apply(0.0, np.array([0.0, 0.03, 0.0]), tau)
    with pytest.raises(TareError, match="j2 moves at 0.030 rad/s"):
        tare.start()
    tare.apply(0.002, np.zeros(3), tau)
    tare.start()
    tare.apply(0.004, np.zeros(3), tau)
    tare.apply(0.006, np.array([-0.5, 0.0, 0.0]), tau)
    assert tare.state == IDLE and tare.aborted and "j1 moves" in tare.note
    tare.apply(0.008, np.zeros(3), tau)
    tare.start()
    for k in range(6):
        tare.apply(0.01 + 0.002 * k, np.zeros(3), tau)
    assert tare.state == ACTIVE
    tare.start()                                   # a second tare: the first offset applies meanwhile
    assert tare.apply(0.03, np.zeros(3), 3 * tau) == pytest.approx(2 * tau)
    tare.interrupt("the filter restarted")
    assert tare.state == ACTIVE and tare.aborted and "previous offset stays" in tare.note
    copy = Tare(NAMES, 1.0, 0.02)
    copy.continue_from(tare)
    assert copy.state == ACTIVE and np.array_equal(copy.offset, tare.offset) and copy.note == tare.note


def test_estimator_tare_removes_a_constant_bias_and_keeps_the_covariance(panda_config, trained):
    """τ_m = g(q0) − BIAS at rest: τ̂ settles to BIAS (plus the residual model's mean at rest) within 1 s;
    a tare then leaves only what τ̂ still moves after the averaging (measured 9.3e-8 N·m and a 7.4e-8 wrench with the
    20 rad/s prior of docs/method.md §4.12, 3e-9 at 30 rad/s, where τ̂ settles faster; bound 1e-6 ≪ the 0.3 N·m
    smallest bias), the wrench follows the tared τ̂ and P is that of an untared estimator, bit for bit."""
    tared, plain = (Estimator.from_config(panda_config, trained) for _ in range(2))
    tau_m = RobotModel.from_config(panda_config).gravity(Q0) - BIAS
    with pytest.raises(TareError):
        tared.start_tare()
    for k in range(1200):
        if k == 500:
            tared.start_tare()
            assert tared.tare.state == AVERAGING
        estimate = tared.step(0.002 * k, Q0, np.zeros(7), tau_m)
        reference = plain.step(0.002 * k, Q0, np.zeros(7), tau_m)
    assert tared.tare.state == ACTIVE and tared.tare.samples == 501
    assert np.abs(reference.tau_ext).min() > 0.25 and np.abs(estimate.tau_ext).max() < 1e-6
    assert np.array_equal(estimate.tau_ext, reference.tau_ext - tared.tare.offset)
    assert np.array_equal(estimate.tau_cov, reference.tau_cov)
    assert np.abs(estimate.wrench).max() < 1e-6
    tared.clear_tare()
    assert np.array_equal(tared.step(2.4, Q0, np.zeros(7), tau_m).tau_ext,
                          plain.step(2.4, Q0, np.zeros(7), tau_m).tau_ext)


def test_set_payload_is_the_model_from_config_and_shifts_tau_by_its_gravity(panda_config, trained):
    """The robot held still with a 2 kg tool the model does not know: τ̂ = −g_tool(q0). After set_payload the
    filter (kf: no residual model, so τ̂ = g_model − τ_m at rest) continues and settles to 0 within 1 s; the
    change is g_tool to rounding (1e-9 N·m against up to 9 N·m)."""
    config = replace(panda_config, observer="kf")
    with_tool = RobotModel.from_config(replace(config, payload=TOOL))
    tau_m = with_tool.gravity(Q0)
    estimator = Estimator.from_config(config, trained)
    for k in range(500):
        before = estimator.step(0.002 * k, Q0, np.zeros(7), tau_m)
    estimator.set_payload(TOOL)
    assert estimator.config.payload == TOOL
    assert np.array_equal(estimator.robot.gravity(Q0), with_tool.gravity(Q0))
    assert np.allclose(estimator.robot.mass_matrix(Q0), with_tool.mass_matrix(Q0), atol=1e-12)
    for k in range(500, 1000):
        after = estimator.step(0.002 * k, Q0, np.zeros(7), tau_m)
    g_tool = tau_m - RobotModel.from_config(config).gravity(Q0)
    assert np.abs(g_tool).max() > 5.0
    assert np.abs((after.tau_ext - before.tau_ext) - g_tool).max() < 1e-9
    estimator.configure(replace(estimator.config, payload=None))          # the run-time key path
    assert estimator.robot.payload is None


@pytest.mark.parametrize("inertia, reason", [((1.0, 1.0, 5.0, 0.0, 0.0, 0.0), "triangle"),
                                             ((-0.1, 0.1, 0.1, 0.0, 0.0, 0.0), "not positive")])
def test_a_non_physical_payload_is_refused_and_changes_nothing(panda_config, trained, inertia, reason):
    estimator = Estimator.from_config(panda_config, trained)
    bad = Payload(1.0, (0.0, 0.0, 0.05), inertia)
    assert reason in payload_problem(bad)
    with pytest.raises(ValueError, match=reason):
        estimator.set_payload(bad)
    with pytest.raises(ValueError, match=reason):
        estimator.configure(replace(panda_config, payload=bad))
    assert estimator.robot.payload is None and estimator.config.payload is None
    with pytest.raises(ValueError, match=reason):
        Estimator.from_config(replace(panda_config, payload=bad), trained)
    assert payload_problem(TOOL) is None and payload_problem(None) is None


@pytest.mark.parametrize("frame", ["base", "end_effector"])
def test_wrench_in_both_frames_is_one_rotation_apart(panda_config, trained, frame):
    """wrench_in(other frame) equals RobotModel.wrench_from_torque in that frame (the damped pseudo-inverse is
    rotation-covariant) and R is the ee_frame orientation from forward kinematics; 1e-9 is rounding."""
    config = replace(panda_config, wrench=replace(panda_config.wrench, frame=frame))
    estimator = Estimator.from_config(config, trained)
    robot = RobotModel.from_config(config)
    rng = np.random.default_rng(7)
    for k in range(30):
        q = Q0 + 0.01 * k
        estimate = estimator.step(0.002 * k, q, np.full(7, 2.0), rng.normal(0.0, 5.0, 7))   # q̇ within the bounds
    for axes in ("base", "end_effector"):
        expected, _ = robot.wrench_from_torque(q, estimate.tau_ext, None, config.wrench.damping, axes)
        assert np.abs(estimate.wrench_in(axes) - expected).max() < 1e-9
    pin.framesForwardKinematics(robot.model, robot.data, q)
    assert np.abs(estimate.ee_rotation - robot.data.oMf[robot.ee_frame_id].rotation).max() < 1e-12
    assert estimate.wrench_frame == frame and estimate.wrench_in(frame) is estimate.wrench
