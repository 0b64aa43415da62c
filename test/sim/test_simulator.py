"""Tests of the MuJoCo simulator (kvark_ros.sim): plant files, excitation design, scenarios,
ground truth and bag output. Short simulated durations keep the whole file fast."""
from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from kvark_ros.core.estimation.robot_model import Payload
from kvark_ros.sim.cli import add_simulate_parser
from kvark_ros.sim.controllers import JointTrackingController
from kvark_ros.sim.excitation import (CHECK_RATE_HZ, ExcitationLimits, cloud_rank, log_det_coverage,
                                      optimise_excitation)
from kvark_ros.sim.mujoco_plant import AppliedWrench, MujocoPlant
from kvark_ros.sim.plant import (PlantSpec, default_plant_path, friction_torque, load_plant,
                                 plant_effects, residual_torque)
from kvark_ros.sim.robots import robot_setup
from kvark_ros.sim.scenarios import (ConstantForce, ExternalForce, SimulationOutput, run_scenario,
                                     run_simulation)

G = 9.81
PANDA = robot_setup("panda")
GAZ = {"phi1": [0.54615, 0.87224, 0.64068, 1.2794, 0.83904, 0.30301, 0.56489],
       "phi2": [5.1181, 9.0657, 10.136, 5.5903, 8.3469, 17.133, 10.336],
       "phi3": [0.039533, 0.025882, -0.04607, 0.036194, 0.026226, -0.021047, 0.0035526]}


def _nominal_id(setup_name: str, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """Nominal inverse dynamics (T, n) of sampled states."""
    model = robot_setup(setup_name).nominal_model()
    return np.array([model.inverse_dynamics(*x) for x in zip(q, qd, qdd)])


# ----------------------------------------------------------------------------- plant files


def test_default_plant_files_load_and_gaz_friction_is_the_formula() -> None:
    panda = load_plant(default_plant_path("panda"), 7)
    ur5 = load_plant(default_plant_path("ur5"), 6)
    assert panda.friction_model == "gaz_sigmoid" and ur5.friction_model == "coulomb_viscous"
    qd = np.linspace(-1.5, 1.5, 31)[:, None] * np.ones(7)
    phi1, phi2, phi3 = (np.array(GAZ[k]) for k in ("phi1", "phi2", "phi3"))
    expected = (phi1 / (1 + np.exp(-phi2 * (qd + phi3))) - phi1 / (1 + np.exp(-phi2 * phi3))
                + panda.viscous * qd)
    np.testing.assert_allclose(friction_torque(panda, qd), expected, atol=1e-12)
    np.testing.assert_allclose(friction_torque(panda, np.zeros(7)), 0.0, atol=1e-15)
    assert np.all(panda.viscous >= 0.05) and np.all(panda.viscous <= 0.2)
    assert panda.encoder_counts_per_rev == 2**19
    np.testing.assert_allclose(friction_torque(ur5, [1.0, -1.0, 0.0, 2.0, 0.1, -0.1]),
                               [8.0, -8.0, 0.0, 2.2, 1.25, -1.25])


def test_plant_effects_collect_offset_ripple_and_friction() -> None:
    spec = load_plant({"friction": {"model": "stribeck", "coulomb": [1.0, 2.0], "static": [1.5, 2.0],
                                    "stribeck_velocity": [0.1, 0.1], "viscous": [0.5, 0.0]},
                       "drive_gain": [0.9, 1.1], "torque_offset": [0.2, -0.3], "armature": [0.1, 0.0],
                       "position_ripple": {"amplitude": [0.05, 0.0], "cycles_per_rev": [6, 0]}}, 2)
    q, qd, qdd, tau = np.array([0.3, -1.0]), np.array([0.1, -2.0]), np.array([1.0, 1.0]), np.array([2.0, 1.0])
    friction = np.array([(1.0 + 0.5 * np.exp(-1.0)) + 0.05, -2.0])
    np.testing.assert_allclose(friction_torque(spec, qd), friction)
    effects = friction - [0.2, -0.3] - [0.05 * np.sin(1.8), 0.0]
    np.testing.assert_allclose(plant_effects(spec, q, qd), effects)
    np.testing.assert_allclose(residual_torque(spec, q, qd, qdd, tau), [0.2, -0.1] + effects + [0.1, 0.0])


@pytest.mark.parametrize(("plant", "key"), [
    ({"fricton": {}}, "fricton"),
    ({"friction": {"model": "gaz"}}, "friction.model"),
    ({"friction": {"model": "gaz_sigmoid", "phi1": [1] * 7, "phi2": [1] * 7}}, "friction.phi3"),
    ({"friction": {"model": "coulomb_viscous", "coulomb": [1] * 7, "phi1": [1] * 7}}, "friction.phi1"),
    ({"friction": {"model": "coulomb_viscous", "coulomb": [1] * 6}}, "friction.coulomb"),
    ({"armature": [-0.1] * 7}, "armature"),
    ({"drive_gain": [0.0] * 7}, "drive_gain"),
    ({"payload": {"mass": -1}}, "payload.mass"),
    ({"payload": {"mass": 1, "inertia": [1, 0, 0, 0, 0, 0]}}, "payload.inertia"),
    ({"position_ripple": {"amplitude": [0.1] * 7}}, "position_ripple"),
    ({"noise": {"encoder_counts_per_rev": 1.5}}, "noise.encoder_counts_per_rev"),
    ({"noise": {"torque_std": "high"}}, "noise.torque_std"),
    ({"control_rate_hz": 250}, "control_rate_hz"),
    ({"joint_offset": [0.01] * 6}, "joint_offset"),
    ({"joint_offset": [float("nan")] * 7}, "joint_offset"),
])
def test_bad_plant_values_name_the_key(plant: dict[str, object], key: str) -> None:
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        load_plant(plant, 7)


# ----------------------------------------------------------------------------- excitation


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_excitation_respects_limits_and_beats_initial_population(robot: str) -> None:
    setup = robot_setup(robot)
    limits = ExcitationLimits.for_robot(setup)
    result = optimise_excitation(limits, duration=6.0, seed=4)
    t = np.arange(int(6.0 * CHECK_RATE_HZ) + 1) / CHECK_RATE_HZ
    q, qd, qdd = result.trajectory.sample(t)
    assert limits.violation(q, qd, qdd).max() <= 1.0
    fine = result.trajectory.sample(np.linspace(0.0, 6.0, 24001))      # 4 kHz: between grid points
    assert limits.violation(*fine).max() <= 1.01
    model = setup.nominal_model().model                                  # the URDF limits themselves
    assert np.all(q >= model.lowerPositionLimit) and np.all(q <= model.upperPositionLimit)
    assert np.all(np.abs(qd) <= model.velocityLimit)
    assert result.logdet > result.initial_best_logdet
    np.testing.assert_allclose([qd[0], qd[-1], qdd[0], qdd[-1]], 0.0, atol=1e-9)   # starts/ends at rest
    again = optimise_excitation(limits, duration=6.0, seed=4, population=8, generations=5)
    assert again.logdet < result.logdet
    again = optimise_excitation(limits, duration=6.0, seed=4)
    np.testing.assert_array_equal(again.trajectory.a, result.trajectory.a)


def test_short_excitation_log_det_is_taken_on_the_directions_the_cloud_spans() -> None:
    """1 s of Panda: whole cycles in [0.1, 2] Hz leave K = 2 harmonics, so the 21 normalised (q, q̇, q̈)
    coordinates combine 6K = 12 signals and Cov has 9 zero eigenvalues (measured ≤ 3e-16 of the largest, the 12
    spanned ones ≥ 6e-10 of it; the test splits them at 1e-12). Cov's full determinant is then rounding noise
    (its sign flipped between numpy 2.2 and 2.4, and with it the optimised trajectory); the log-det on the 12
    spanned directions is finite and moves by < 1e-5 when the samples move by 1e-12 relative, 10⁴ times more
    than a BLAS's rounding (measured 1.3e-7). The optimiser still beats its initial population (measured −84.7
    against −95.3)."""
    limits = ExcitationLimits.for_robot(PANDA)
    result = optimise_excitation(limits, duration=1.0, seed=4)
    trajectory = result.trajectory
    rank = cloud_rank(PANDA.n, trajectory.frequencies.size, trajectory.ramp)
    assert trajectory.frequencies.size == 2 and rank == 12
    q, qd, qdd = trajectory.sample(np.arange(int(CHECK_RATE_HZ) + 1) / CHECK_RATE_HZ)
    cloud = np.hstack([(q - limits.centre) / limits.half_range, qd / limits.velocity, qdd / limits.acceleration])
    eigenvalues = np.linalg.eigvalsh(np.cov(cloud, rowvar=False))
    assert np.sum(eigenvalues > 1e-12 * eigenvalues.max()) == rank
    assert np.isfinite(result.logdet) and result.logdet > result.initial_best_logdet
    rng = np.random.default_rng(0)
    for _ in range(5):
        moved = [x * (1.0 + 1e-12 * rng.standard_normal(x.shape)) for x in (q, qd, qdd)]
        assert abs(float(log_det_coverage(*moved, limits, rank)) - result.logdet) < 1e-5


# ----------------------------------------------------------------------------- determinism


def test_same_seed_gives_identical_runs() -> None:
    first = run_scenario("panda", "collision", seed=3, duration=1.0)
    second = run_scenario("panda", "collision", seed=3, duration=1.0)
    other = run_scenario("panda", "collision", seed=4, duration=1.0)
    for a, b in ((first.run.joint_states, second.run.joint_states),
                 (first.run.external_torque, second.run.external_torque)):
        for key in ("stamp", "position", "velocity", "effort"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    np.testing.assert_array_equal(first.run.commands.effort, second.run.commands.effort)
    assert not np.array_equal(first.run.joint_states.effort, other.run.joint_states.effort)


def test_a_run_repeats_another_seeds_motion_with_its_own_noise() -> None:
    """``motion_seed``: a UR5 excitation with seed 8 on seed 7's motion follows seed 7's trajectory (within the joint
    tracking error: measured 1.7e-4 rad, 2e-3 allowed) with other sensor noise; seed 8 on its own motion is another
    trajectory (measured 0.089 rad away within the first second; 0.05 required)."""
    own = run_scenario("ur5", "excitation", seed=7, duration=1.0).run.joint_states
    repeated = run_scenario("ur5", "excitation", seed=8, duration=1.0, motion_seed=7).run.joint_states
    other = run_scenario("ur5", "excitation", seed=8, duration=1.0).run.joint_states
    assert np.max(np.abs(repeated.position - own.position)) < 2e-3
    assert not np.array_equal(repeated.velocity, own.velocity)           # its own noise
    assert np.max(np.abs(other.position - own.position)) > 0.05


# ----------------------------------------------------------------------------- ground truth


def test_mujoco_external_force_is_jacobian_transpose() -> None:
    """An xfrc_applied wrench moves MuJoCo exactly as τ_ext = Jᵀ F of the nominal model says."""
    plant = MujocoPlant(PANDA, load_plant(None, 7))
    model = PANDA.nominal_model()
    q = PANDA.home_array() + 0.2
    plant.reset(q)
    point, _ = plant.frame_pose(PANDA.ee_frame)
    force, torque = np.array([3.0, -2.0, 5.0]), np.array([0.4, 0.1, -0.2])
    plant.apply([AppliedWrench(PANDA.ee_frame, point, force, torque)])
    mujoco.mj_forward(plant.model, plant.data)
    generalized = np.zeros(7)
    for body in range(plant.model.nbody):
        wrench = plant.data.xfrc_applied[body]
        if np.any(wrench):
            mujoco.mj_applyFT(plant.model, plant.data, wrench[:3], wrench[3:],
                              plant.data.xipos[body], body, generalized)
    np.testing.assert_allclose(generalized, model.jacobian(q, "base").T @ np.r_[force, torque], atol=1e-12)


@pytest.mark.parametrize(("scenario", "duration"), [("payload", 1.5), ("contact", 2.5), ("collision", 2.0)])
def test_ground_truth_closes_the_dynamics(scenario: str, duration: float) -> None:
    """M q̈ + C q̇ + g + τ_f = τ_drive + τ_ext holds sample by sample with the nominal model
    (the default plant has no armature), and the wrist F/T maps to τ_ext where it sees it."""
    out = run_scenario("panda", scenario, seed=2, duration=duration)
    truth = out.truth
    balance = truth.drive_torque + truth.tau_ext - _nominal_id("panda", truth.q, truth.qd, truth.qdd)
    np.testing.assert_allclose(balance, truth.friction, atol=1e-8)
    assert np.abs(truth.tau_ext).max() > 1.0
    model = PANDA.nominal_model()
    from_sensor = np.array([pin.computeFrameJacobian(model.model, model.data, q, model.flange_frame_id,
                                                     pin.LOCAL).T @ np.r_[f, m]
                            for q, f, m in zip(truth.q, truth.wrench_force, truth.wrench_torque)])
    if scenario == "collision":      # a push on a link before the wrist: the F/T sees nothing
        np.testing.assert_array_equal(truth.wrench_force, 0.0)
    else:
        np.testing.assert_allclose(from_sensor, truth.tau_ext, atol=1e-9)
    np.testing.assert_array_equal(out.run.external_torque.effort, truth.tau_ext)
    np.testing.assert_array_equal(out.run.wrench.force, truth.wrench_force)
    assert out.run.wrench.frame_id == PANDA.flange_frame


def _hold(plant_spec: PlantSpec, forces: Sequence[ExternalForce] = ()) -> SimulationOutput:
    """Hold the Panda at home for 1.5 s with the joint controller."""
    home = PANDA.home_array()
    reference = (home, np.zeros(7), np.zeros(7))
    controller = JointTrackingController(PANDA.nominal_model(), lambda t: reference, PANDA.kp, PANDA.kd)
    return run_simulation(PANDA, plant_spec, controller, 1.5, home, np.random.default_rng(0), forces)


def test_payload_at_rest_weighs_m_g_and_matches_an_external_force() -> None:
    mass, com = 2.5, (0.01, -0.02, 0.12)
    payload = Payload(mass, com, (0.004, 0.004, 0.002, 0.0, 0.0, 0.0))
    base = load_plant(default_plant_path("panda"), 7)
    loaded = _hold(load_plant({"payload": {"mass": mass, "com": list(com), "inertia": list(payload.inertia)},
                               "friction": {"model": "gaz_sigmoid", **GAZ}}, 7))
    truth = loaded.truth
    assert np.abs(truth.qd[-1]).max() < 1e-4                       # settled
    force = truth.wrench_force[-1]
    assert abs(np.linalg.norm(force) - mass * G) < 0.01 * mass * G
    model = PANDA.nominal_model()
    q = truth.q[-1]
    pin.framesForwardKinematics(model.model, model.data, q)
    rotation = model.data.oMf[model.flange_frame_id].rotation
    np.testing.assert_allclose(rotation @ force, [0.0, 0.0, -mass * G], atol=0.01 * mass * G)  # docs/method.md §1.2
    jac = pin.computeFrameJacobian(model.model, model.data, q, model.flange_frame_id, pin.LOCAL)
    np.testing.assert_allclose(jac.T @ np.r_[force, truth.wrench_torque[-1]], truth.tau_ext[-1], atol=1e-9)
    # At rest the drives hold gravity minus the external torque: τ_drive = g_nom(q) − τ_ext.
    gravity = model.inverse_dynamics(q, np.zeros(7), np.zeros(7))
    np.testing.assert_allclose(truth.drive_torque[-1], gravity - truth.tau_ext[-1], atol=2e-3)
    # The same weight as an external force (no mass in MuJoCo) is held with the same torques.
    weight = ConstantForce(PANDA.flange_frame, np.array([0.0, 0.0, -mass * G]), np.array(com))
    pushed = _hold(load_plant({"friction": {"model": "gaz_sigmoid", **GAZ}}, 7), [weight]).truth
    np.testing.assert_allclose(pushed.drive_torque[-1], truth.drive_torque[-1], atol=2e-3)
    np.testing.assert_allclose(pushed.tau_ext[-1], truth.tau_ext[-1], atol=1e-3)
    assert base.payload is None                                    # the default plant carries none


# ----------------------------------------------------------------------------- friction


def _binned(qd: np.ndarray, edges: np.ndarray, minimum: int) -> Iterator[np.ndarray]:
    """Boolean masks of the velocity bins holding at least ``minimum`` samples."""
    index = np.digitize(qd, edges)
    for b in np.unique(index):
        members = index == b
        if members.sum() >= minimum:
            yield members


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_friction_shows_in_measured_effort_minus_inverse_dynamics(robot: str) -> None:
    """Regressing (measured effort − nominal ID) on velocity recovers friction_torque of the plant
    file. Tolerance: a bin mean (≥ 80 samples) within 0.05 N·m + 3 standard errors of the mean
    friction of its samples; dry friction only compared while sliding (|q̇| > 0.05 rad/s)."""
    out = run_scenario(robot, "excitation", seed=5, duration=8.0)
    spec, truth = out.plant, out.truth
    residual = out.run.joint_states.effort - _nominal_id(robot, truth.q, truth.qd, truth.qdd)
    predicted = friction_torque(spec, truth.qd)
    if not spec.dry_friction:
        np.testing.assert_allclose(truth.friction, predicted, atol=1e-12)
    checked = 0
    for j in range(spec.n):
        qd = truth.qd[:, j]
        edges = np.linspace(qd.min(), qd.max(), 15)
        for members in _binned(qd, edges, 80):
            if spec.dry_friction and np.abs(qd[members]).min() < 0.05:
                continue
            error = residual[members, j] - predicted[members, j]
            tolerance = 0.05 + 3.0 * error.std() / np.sqrt(members.sum())
            assert abs(error.mean()) < tolerance, (j, qd[members].mean(), error.mean())
            checked += 1
    assert checked >= 5 * spec.n


def test_every_joint_effect_is_simulated_as_the_plant_file_says() -> None:
    """Armature, drive gain, offset, ripple and Stribeck friction: the commanded torque minus the
    nominal inverse dynamics is residual_torque() (dry friction compared while sliding)."""
    spec = load_plant({
        "friction": {"model": "stribeck", "coulomb": [3.0, 3.0, 2.0, 0.8, 0.8, 0.8],
                     "static": [4.0, 4.0, 2.5, 1.0, 1.0, 1.0], "stribeck_velocity": [0.05] * 6,
                     "viscous": [1.0, 1.0, 0.5, 0.2, 0.2, 0.2]},
        "armature": [0.3, 0.3, 0.2, 0.05, 0.05, 0.05], "drive_gain": [0.95, 1.05, 1.0, 0.9, 1.1, 1.0],
        "torque_offset": [0.5, -0.4, 0.3, 0.0, 0.1, -0.1],
        "position_ripple": {"amplitude": [0.3, 0.0, 0.2, 0.0, 0.0, 0.05],
                            "cycles_per_rev": [6, 0, 12, 0, 0, 3]},
        "control_rate_hz": 500}, 6)
    out = run_scenario("ur5", "excitation", seed=7, duration=4.0, plant=spec)
    truth, tau_m = out.truth, out.run.commands.effort
    gap = tau_m - _nominal_id("ur5", truth.q, truth.qd, truth.qdd)
    ripple = np.zeros_like(truth.q)
    ripple[:, 0], ripple[:, 2] = 0.3 * np.sin(6 * truth.q[:, 0]), 0.2 * np.sin(12 * truth.q[:, 2])
    ripple[:, 5] = 0.05 * np.sin(3 * truth.q[:, 5])
    exact = ((1.0 - spec.drive_gain) * tau_m + truth.friction - spec.torque_offset - ripple
             + spec.armature * truth.qdd)
    np.testing.assert_allclose(gap, exact, atol=1e-8)
    sliding = np.abs(truth.qd) > 0.05
    expected = residual_torque(spec, truth.q, truth.qd, truth.qdd, tau_m)
    np.testing.assert_allclose(gap[sliding], expected[sliding], atol=1e-6)
    assert sliding.mean() > 0.5


def test_joint_offset_is_an_encoder_error_only() -> None:
    """The recorded position is the true one plus the offset (quantised); the arm starts where
    the encoders read the trajectory's start, and the dynamics run at the true position."""
    offset = [0.03, -0.05, 0.02, 0.0, 0.0, 0.01]
    counts = 2**16
    spec = load_plant({"joint_offset": offset, "noise": {"encoder_counts_per_rev": counts}}, 6)
    np.testing.assert_array_equal(spec.joint_offset, offset)
    np.testing.assert_array_equal(load_plant({}, 6).joint_offset, 0.0)
    out = run_scenario("ur5", "excitation", seed=7, duration=0.6, plant=spec)
    truth, position = out.truth, out.run.joint_states.position
    np.testing.assert_allclose(position, truth.q + offset, atol=0.5 * 2.0 * np.pi / counts + 1e-12)
    assert np.abs(position - truth.q - offset).max() > 0.0          # quantised, not a copy
    bare = run_scenario("ur5", "excitation", seed=7, duration=0.6,
                        plant={"noise": {"encoder_counts_per_rev": counts}})
    np.testing.assert_allclose(position[0], bare.run.joint_states.position[0], atol=2.0 * np.pi / counts)
    # The dynamics use the true position: τ_m is the nominal inverse dynamics there, not at the reading.
    gap_true = out.run.commands.effort - _nominal_id("ur5", truth.q, truth.qd, truth.qdd)
    gap_read = out.run.commands.effort - _nominal_id("ur5", position, truth.qd, truth.qdd)
    np.testing.assert_allclose(gap_true, 0.0, atol=1e-8)
    assert np.abs(gap_read[:, 1]).max() > 0.1                      # shoulder: g(q) − g(q + δ) ≈ 0.05 rad · ∂g/∂q


# ----------------------------------------------------------------------------- bags and CLI


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_scenario_round_trips_through_a_bag(tmp_path: Path, storage: str) -> None:
    bag = pytest.importorskip("kvark_ros.io")
    run = run_scenario("ur5", "contact", seed=1, duration=0.6).run
    path = tmp_path / "run"
    bag.write_run(path, run, storage=storage)
    back = bag.read_run(path)
    assert back.joint_names == run.joint_names
    for a, b in ((run.joint_states, back.joint_states), (run.external_torque, back.external_torque)):
        np.testing.assert_array_equal(a.stamp, b.stamp)
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.velocity, b.velocity)
        np.testing.assert_array_equal(a.effort, b.effort)
    np.testing.assert_array_equal(run.commands.effort, back.commands.effort)
    np.testing.assert_array_equal(run.wrench.force, back.wrench.force)
    np.testing.assert_array_equal(run.wrench.torque, back.wrench.torque)
    assert back.wrench.frame_id == "tool0"
    topics = set(bag.bag_info(path)["topics"])
    assert topics == {"/joint_states", "/effort_commands", "/ft_sensor/wrench",
                      "/ground_truth/external_joint_torque"}


def test_cli_writes_a_bag_and_reports_the_real_time_factor(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="kvark")
    add_simulate_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "bag"
    args = parser.parse_args(["simulate", "--robot", "panda", "--scenario", "excitation", "--seed", "2",
                              "--duration", "0.6", "--storage", "sqlite3", "--out", str(out)])
    assert args.func(args) == 0
    assert "real-time factor" in capsys.readouterr().out
    assert any(out.glob("*.db3"))
    assert args.func(args) == 1                          # output exists: refused without --force
    bad = parser.parse_args(["simulate", "--scenario", "payload", "--plant", str(tmp_path / "none.yaml"),
                             "--out", str(tmp_path / "x")])
    assert bad.func(bad) == 1
    assert "none.yaml" in capsys.readouterr().err
