"""The wrench near singular poses (docs/method.md §1.4.1): condition number, unobservable directions, damping bias.

Poses: ``REGULAR`` (Panda, smallest σ 0.19, κ ≈ 9.5), the stretched Panda ``q = 0`` (σ₆ = 0 exactly: a
moment about base x; joint 4 at 0 is 0.07 rad past its limit, which the model ignores) and the UR5's
wrist singularity (home with joint 5 at 0: wrist 1 and wrist 3 aligned, σ₆ ≈ 6e-17). δ = 0.05 and the
prior (50 N, 5 N·m) are config/panda.yaml's. Known wrenches F give the torques τ = Jᵀ F exactly.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.robot_model import RobotModel

from test_node_logic_stand_in import diagnostics, feed, make_node, model_dir, values_of  # noqa: F401

REGULAR = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8])
DAMPING, PRIOR = 0.05, (50.0, 5.0)
PRIOR_COV = np.diag(np.repeat(np.square(PRIOR), 3))                  # Σ_prior, N² and N²·m²
UR5_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint"]
UR5_WRIST_SINGULAR = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, 0.0, 0.0])


@pytest.fixture(scope="module")
def ur5() -> RobotModel:
    return RobotModel("example-robot-data:ur5", UR5_JOINTS, "tool0")


def todays(robot: RobotModel, q: np.ndarray, tau: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The wrench and covariance before §1.4.1, written out: J⁺ = (J Jᵀ + δ² I)⁻¹ J, F = J⁺ τ, Σ = J⁺ P J⁺ᵀ."""
    jac = robot.jacobian(q)
    pinv = np.linalg.solve(jac @ jac.T + DAMPING ** 2 * np.eye(6), jac)
    return pinv @ tau, pinv @ cov @ pinv.T


def test_regular_pose_is_unchanged(panda):
    """Nothing is flagged (every σ_i ≥ δ) and F, Σ_F equal today's to rounding (1e-12 relative: a 6×6 solve in
    double precision at κ ≈ 10); κ = 9.5 there, asserted below 20."""
    cov = np.diag(np.linspace(0.05, 0.5, 7))
    tau = np.array([1.0, -2.0, 0.5, 3.0, -1.0, 0.2, 0.1])
    solution = panda.solve_wrench(REGULAR, tau, cov, DAMPING, "base", PRIOR)
    wrench, wrench_cov = todays(panda, REGULAR, tau, cov)
    assert 1.0 < solution.condition < 20.0 and solution.weak.shape == (6, 0)
    assert np.abs(solution.wrench - wrench).max() <= 1e-12 * np.abs(wrench).max()
    assert np.abs(solution.cov - wrench_cov).max() <= 1e-12 * np.abs(wrench_cov).max()


@pytest.mark.parametrize("robot_name, q", [("panda", np.zeros(7)), ("ur5", UR5_WRIST_SINGULAR)])
def test_singular_pose_flags_the_direction_and_its_interval_holds_the_truth(robot_name, q, request):
    """At a singular pose κ > 1e8 (σ₆ ~ 1e-17: numerically zero) and exactly one direction u is flagged. A true
    wrench whose component along u is one prior standard deviation s_u = √(uᵀ Σ_prior u): the estimate keeps
    none of it (c = 1), the reported variance along u is at least s_u² and the truth lies at 1 s_u, inside the
    1.96 s_u interval; today's variance along u is ~0 (J⁺ has no gain there), its interval excludes the truth."""
    robot = request.getfixturevalue(robot_name)
    n = robot.n
    u_expected = np.linalg.svd(robot.jacobian(q))[0][:, -1]
    solution = robot.solve_wrench(q, np.zeros(n), np.eye(n), DAMPING, "base", PRIOR)
    assert solution.condition > 1e8 and solution.weak.shape == (6, 1)
    u = solution.weak[:, 0]
    assert abs(u @ u_expected) == pytest.approx(1.0, abs=1e-9)
    scale = np.sqrt(u @ PRIOR_COV @ u)
    others = np.array([10.0, -5.0, 20.0, 1.0, 1.0, -2.0])
    truth = PRIOR_COV @ u / scale + (others - (u @ others) * u)     # uᵀF = s_u, any observable part
    tau = robot.jacobian(q).T @ truth
    cov = 0.01 * np.eye(n)                                          # 0.1 N·m per joint
    solution = robot.solve_wrench(q, tau, cov, DAMPING, "base", PRIOR)
    variance = u @ solution.cov @ u
    assert variance >= scale ** 2 * (1.0 - 1e-9)
    assert abs(u @ (solution.wrench - truth)) <= 1.96 * np.sqrt(variance)
    wrench, wrench_cov = todays(robot, q, tau, cov)
    assert abs(u @ (wrench - truth)) > 1.96 * np.sqrt(max(u @ wrench_cov @ u, 0.0)) + 0.9 * scale
    unbiased = robot.wrench_from_torque(q, tau, cov, DAMPING)[1]                # without a prior: today's Σ_F
    assert np.allclose(unbiased, wrench_cov, rtol=0.0, atol=1e-9)


def test_bias_is_added_along_the_weak_directions_only(panda):
    """Σ_F − J⁺ P J⁺ᵀ = B_w Σ_prior B_wᵀ lies in the span of the weak directions: it vanishes on the others
    (1e-9 N² against the 25 N²·m² added)."""
    q, cov = np.zeros(7), np.eye(7)
    solution = panda.solve_wrench(q, np.zeros(7), cov, DAMPING, "base", PRIOR)
    added = solution.cov - todays(panda, q, np.zeros(7), cov)[1]
    u = np.linalg.svd(panda.jacobian(q))[0]
    strong = u[:, :5]
    assert np.abs(strong.T @ added @ strong).max() < 1e-9
    assert solution.weak[:, 0] @ added @ solution.weak[:, 0] == pytest.approx(25.0, rel=1e-9)   # m² (moment x)


def test_fewer_joints_than_wrench_axes_leave_directions_unobservable(panda_config):
    """A 4-joint arm (Panda joints 1-4, the rest locked): J is 6×4, so at least 2 directions are missing
    (σ = 0 by shape): κ is ∞ and each missing direction carries at least its prior variance."""
    arm = RobotModel(panda_config.urdf, panda_config.joint_names[:4], "panda_link4")
    q = np.array([0.1, -0.4, 0.2, -2.0])
    solution = arm.solve_wrench(q, np.zeros(4), np.eye(4), DAMPING, "base", PRIOR)
    assert solution.condition == np.inf and solution.weak.shape[1] >= 2
    for u in solution.weak.T:
        assert u @ solution.cov @ u >= u @ PRIOR_COV @ u * (1.0 - 1e-9)


@pytest.mark.parametrize("frame", ["base", "end_effector"])
def test_estimates_carry_the_condition_and_the_directions_in_the_wrench_axes(panda_config, panda_trained, frame):
    """The Estimator at rest: at REGULAR κ < 20 and observable; at q = 0 the weak direction is reported in the
    wrench's axes (u_ee = diag(Rᵀ, Rᵀ) u_base) with the prior's variance along it, and counted."""
    config = replace(panda_config, wrench=replace(panda_config.wrench, frame=frame))
    estimator = Estimator.from_config(config, panda_trained)
    zero = np.zeros(7)
    for k, q in enumerate([REGULAR, REGULAR, zero, zero]):
        estimate = estimator.step(0.002 * k, q, zero, estimator.robot.gravity(q))
        if k == 1:
            assert estimate.wrench_observable and 1.0 < estimate.jacobian_condition < 20.0
    assert not estimate.wrench_observable and estimate.jacobian_condition > 1e8
    assert estimator.unobservable_samples == 2
    u = estimate.weak_directions[:, 0]
    rotation = estimate.ee_rotation if frame == "end_effector" else np.eye(3)
    base = np.concatenate((rotation @ u[:3], rotation @ u[3:]))
    assert np.abs(np.abs(base) - [0, 0, 0, 1, 0, 0]).max() < 1e-9           # a moment about base x
    assert u @ estimate.wrench_cov @ u >= 25.0 * (1.0 - 1e-9)


def test_node_reports_the_wrench_status(ros, make_node):
    """/diagnostics ``wrench``: OK with κ at a regular pose, WARN with the direction at q = 0 (kfmo observer at
    rest; the 1 Hz status shows the newest estimate)."""
    node = make_node(observer="kfmo")
    names = list(node._config.joint_names)
    gravity = node._estimator.robot.gravity

    def rest(q: np.ndarray, start: float, seconds: float) -> list:
        out = []
        for k in range(int(round(seconds * 500))):
            ns = int(round((start + 0.002 * k) * 1e9))
            stamp = ros.builtin.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            state = ros.sensor.JointState(header=ros.std.Header(stamp=stamp), name=names, position=q.tolist(),
                                          velocity=[0.0] * 7, effort=[0.0] * 7)
            command = ros.std.Float64MultiArray(data=gravity(q).tolist())
            out += [(ns, "/joint_states", state), (ns + 100_000, "/effort_commands", command)]
        return out

    feed(ros, rest(REGULAR, 0.0, 1.1))
    status = diagnostics(ros)["wrench"]
    assert status.level == ros.diag.DiagnosticStatus.OK and "observable" in status.message
    assert 1.0 < float(values_of(status)["jacobian_condition"]) < 20.0
    feed(ros, rest(np.zeros(7), 1.1, 1.1))
    status = diagnostics(ros)["wrench"]
    values = values_of(status)
    assert status.level == ros.diag.DiagnosticStatus.WARN and "unobservable" in status.message
    assert values["unobservable_directions"] == "1" and float(values["jacobian_condition"]) > 1e8
    assert "direction 1" in values and int(values["samples_with_unobservable_direction"]) > 0
