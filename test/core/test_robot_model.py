"""The nominal model: momentum identity, sign convention, wrench mapping, URDF handling."""
from __future__ import annotations

import numpy as np
import pytest

from kvark_ros.core.estimation.robot_model import Payload, RobotModel, RobotModelError

G = 9.81


def test_momentum_identity_along_an_aba_trajectory(panda, rng):
    """ṗ = Cᵀq̇ − g + τ (paper v1 eq. 6, no external torque), with the motion from pinocchio's ABA."""
    dt, steps = 1e-4, 3000
    q = np.array([0.1, -0.4, 0.2, -2.0, 0.1, 1.6, 0.7])
    qd = rng.uniform(-0.5, 0.5, 7)

    def torque(t: float) -> np.ndarray:
        return 5.0 * np.sin(3.0 * t + np.arange(7))

    def derivative(t, q, qd):
        return qd, panda.forward_dynamics(q, qd, torque(t))

    momentum, inputs = [], []
    for k in range(steps):
        t = k * dt
        p, u = panda.momentum_terms(q, qd, torque(t))
        momentum.append(p)
        inputs.append(u)
        k1 = derivative(t, q, qd)                                   # RK4
        k2 = derivative(t + dt / 2, q + dt / 2 * k1[0], qd + dt / 2 * k1[1])
        k3 = derivative(t + dt / 2, q + dt / 2 * k2[0], qd + dt / 2 * k2[1])
        k4 = derivative(t + dt, q + dt * k3[0], qd + dt * k3[1])
        q = q + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        qd = qd + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    momentum, inputs = np.array(momentum), np.array(inputs)
    p_dot = (momentum[2:] - momentum[:-2]) / (2 * dt)
    error = np.abs(p_dot - inputs[1:-1])
    assert error.max() < 1e-3 * np.abs(inputs).max()


def test_inverse_dynamics_matches_mass_matrix_and_momentum(panda, rng):
    q, qd, qdd = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
    M = panda.mass_matrix(q)
    assert np.allclose(M, M.T) and np.linalg.eigvalsh(M).min() > 0
    p, _ = panda.momentum_terms(q, qd, np.zeros(7))
    assert np.allclose(p, M @ qd, atol=1e-12)
    tau = panda.inverse_dynamics(q, qd, qdd)
    assert np.allclose(panda.forward_dynamics(q, qd, tau), qdd, atol=1e-9)


def test_hanging_payload_gives_downward_force_in_base_frame(panda_config):
    """A mass hanging at the flange: τ_ext = g_nominal − g_true maps to F_ext = (0, 0, −m g, 0, 0, 0)."""
    c, mass = panda_config, 2.5
    nominal = RobotModel(c.urdf, c.joint_names, "panda_link8", "panda_link8")
    loaded = RobotModel(c.urdf, c.joint_names, "panda_link8", "panda_link8", Payload(mass))
    q = np.array([0.3, -0.3, 0.2, -2.2, 0.1, 1.9, 0.5])
    zero = np.zeros(7)
    tau_m = loaded.inverse_dynamics(q, zero, zero)            # what the motors hold
    tau_ext = nominal.inverse_dynamics(q, zero, zero) - tau_m  # M q̈ + C q̇ + g = τ_m + τ_ext at rest
    wrench, cov = nominal.wrench_from_torque(q, tau_ext, np.eye(7), damping=0.0)
    assert np.allclose(wrench, [0, 0, -mass * G, 0, 0, 0], atol=1e-6)
    assert np.allclose(nominal.jacobian(q).T @ wrench, tau_ext, atol=1e-9)
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0


def test_wrench_in_end_effector_axes_is_the_rotated_base_wrench(panda, rng):
    q = np.array([0.3, -0.3, 0.2, -2.2, 0.1, 1.9, 0.5])
    tau = rng.normal(size=7)
    base, _ = panda.wrench_from_torque(q, tau, np.eye(7), 0.0, "base")
    local, _ = panda.wrench_from_torque(q, tau, np.eye(7), 0.0, "end_effector")
    import pinocchio as pin
    pin.framesForwardKinematics(panda.model, panda.data, q)
    rotation = panda.data.oMf[panda.ee_frame_id].rotation
    assert np.allclose(rotation @ local[:3], base[:3], atol=1e-9)
    assert np.allclose(rotation @ local[3:], base[3:], atol=1e-9)


@pytest.mark.parametrize("axes", ["base", "end_effector"])
def test_wrist_wrenches_move_to_the_end_effector_as_pinocchio_moves_a_force(panda, rng, axes):
    """The batched re-expression of a wrist F/T reading equals pinocchio's SE3 action sample by sample
    (f_b = R_s f, m_b = R_s m + p_s × f_b, then about the ee origin), 1e-12 being rounding on N and N·m of order
    10; a non-finite reading gives a NaN row, not a number."""
    import pinocchio as pin
    q = np.array([0.3, -0.3, 0.2, -2.2, 0.1, 1.9, 0.5]) + rng.normal(scale=0.3, size=(5, 7))
    wrench = rng.normal(scale=10.0, size=(5, 6))
    wrench[3, 4] = np.nan
    moved = panda.wrenches_at_end_effector(q, "panda_link7", wrench, axes)
    for k in (0, 1, 2, 4):
        pin.framesForwardKinematics(panda.model, panda.data, q[k])
        at_sensor = panda.data.oMf[panda.model.getFrameId("panda_link7")]
        ee = panda.data.oMf[panda.ee_frame_id]
        target = pin.SE3(np.eye(3), ee.translation) if axes == "base" else ee
        expected = target.actInv(at_sensor.act(pin.Force(wrench[k, :3], wrench[k, 3:]))).vector
        assert np.allclose(moved[k], expected, rtol=0.0, atol=1e-12)
    assert np.isnan(moved[3]).all()
    assert np.linalg.norm(moved[0, 3:] - wrench[0, 3:]) > 0.1      # the frames differ: the moment does move


def test_damping_shrinks_the_wrench_near_a_singularity(panda):
    q = np.zeros(7)                                   # stretched-out arm: J is rank deficient
    tau = np.ones(7)
    small, _ = panda.wrench_from_torque(q, tau, np.eye(7), 1e-3)
    large, _ = panda.wrench_from_torque(q, tau, np.eye(7), 0.5)
    assert np.isfinite(small).all() and np.linalg.norm(large) < np.linalg.norm(small)


def test_payload_hook_replaces_rather_than_accumulates(panda_config):
    c = panda_config
    model = RobotModel(c.urdf, c.joint_names, c.ee_frame, c.flange_frame)
    q, zero = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8]), np.zeros(7)
    bare = model.inverse_dynamics(q, zero, zero)
    model.set_payload(Payload(1.0))
    once = model.inverse_dynamics(q, zero, zero)
    model.set_payload(Payload(1.0))
    assert np.allclose(model.inverse_dynamics(q, zero, zero), once)
    model.set_payload(None)
    assert np.allclose(model.inverse_dynamics(q, zero, zero), bare)
    with pytest.raises(RobotModelError, match="mass"):
        model.set_payload(Payload(-1.0))


def test_urdf_from_xml_string_equals_urdf_from_package(panda_config):
    from kvark_ros.core.estimation.robot_model import resolve_urdf
    c = panda_config
    from_string = RobotModel(resolve_urdf(c.urdf), c.joint_names, c.ee_frame)
    from_spec = RobotModel(c.urdf, c.joint_names, c.ee_frame)
    q = np.linspace(-0.5, 0.5, 7)
    assert np.allclose(from_string.mass_matrix(q), from_spec.mass_matrix(q))


@pytest.mark.parametrize("names, frame, message", [
    (["panda_joint1", "no_such_joint"], "panda_hand_tcp", "no_such_joint"),
    ([f"panda_joint{i}" for i in range(1, 8)], "no_such_frame", "no_such_frame"),
    ([f"panda_joint{i}" for i in range(7, 0, -1)], "panda_hand_tcp", "chain order"),
])
def test_bad_joint_or_frame_names_are_named_in_the_error(panda_config, names, frame, message):
    with pytest.raises(RobotModelError, match=message):
        RobotModel(panda_config.urdf, names, frame)


def test_missing_urdf_file_error_says_what_to_do(tmp_path):
    with pytest.raises(RobotModelError, match="not found"):
        RobotModel(str(tmp_path / "missing.urdf"), ["a"], "b")


def test_ur5_model_has_six_joints():
    names = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
             "wrist_3_joint"]
    ur5 = RobotModel("example-robot-data:ur5", names, "tool0")
    assert ur5.n == 6 and ur5.jacobian(np.zeros(6)).shape == (6, 6)
