"""Tests of the realistic plants (kvark_ros/sim/plants/*_realistic.yaml): link inertia errors, tool
mismatch, friction and torque-offset drift, and the true rigid body the oracle can load
(kvark_ros.sim.true_model.true_urdf). Short simulations keep the file fast."""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.payload import Payload
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.sim.mujoco_plant import PHYSICS_DT, MujocoPlant, build_model
from kvark_ros.sim.plant import (PLANT_DIR, LinkErrorDraw, OracleResidual, PlantError, friction_drift_factor,
                                 friction_torque, load_plant, torque_offset_drift)
from kvark_ros.sim.robots import RobotSetup, robot_setup, urdf_xml
from kvark_ros.sim.scenarios import SESSION_S, run_scenario
from kvark_ros.sim.true_model import link_errors, links_after, moving_links, true_urdf
from kvark_ros.tools.sim_bags import training_clocks

DRAW = {"seed": 3, "mass_rel": 0.15, "com_m": 0.02, "inertia_rel": 0.3}


def _realistic(robot: str) -> Path:
    return PLANT_DIR / f"{robot}_realistic.yaml"


# Every rigid-body effect at once: generated link errors, the URDF's tool absent, an extra tool with
# products of inertia, and a payload.
RIGID_PLANT = {"link_inertia": DRAW,
               "tool": {"urdf_tool": "absent",
                        "extra": {"mass": 0.7, "com": [0.01, 0.02, 0.05],
                                  "inertia": [0.001, 0.0012, 0.0008, 1e-4, 0.0, 0.0]}},
               "payload": {"mass": 1.5, "com": [0.0, 0.01, 0.1], "inertia": [0.002, 0.002, 0.001, 0.0, 0.0, 0.0]}}


def _mujoco_id(model: mujoco.MjModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """MuJoCo's rigid-body inverse dynamics M(q) q̈ + c(q, q̇) (mj_rne: no armature, no constraints)."""
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = q, qd
    mujoco.mj_forward(model, data)
    data.qacc[:] = qdd
    out = np.zeros(model.nv)
    mujoco.mj_rne(model, data, 1, out)
    return out


def _model(setup: RobotSetup, urdf: str) -> RobotModel:
    return RobotModel(urdf, setup.joint_names, setup.ee_frame, setup.flange_frame)


# ----------------------------------------------------------------------------- plant files


def test_realistic_plant_files_hold_what_they_promise() -> None:
    panda = load_plant(_realistic("panda"), 7)
    ur5 = load_plant(_realistic("ur5"), 6)
    for spec in (panda, ur5):
        assert spec.friction_model == "stribeck" and isinstance(spec.link_inertia, LinkErrorDraw)
        assert spec.friction_drift > 0.0 and np.abs(spec.offset_drift_amplitude).max() > 0.0
        assert spec.tool is not None and spec.payload is None
        np.testing.assert_array_equal(spec.armature, 0.0)          # the oracle could not represent these
        np.testing.assert_array_equal(spec.torque_offset, 0.0)
    assert np.all((panda.static[:4] >= 0.5) & (panda.static[:4] <= 1.5))   # a real Panda's breakaway levels
    assert np.all((panda.static[4:] >= 0.3) & (panda.static[4:] <= 0.8))
    assert panda.tool_absent and 0.5 <= panda.tool.mass <= 0.7 and panda.control_rate_hz == 1000.0
    np.testing.assert_array_equal(ur5.coulomb, load_plant(PLANT_DIR / "ur5_default.yaml", 6).coulomb)
    assert np.all(np.abs(ur5.drive_gain - 1.0) <= 0.04 + 1e-12) and np.any(ur5.drive_gain != 1.0)  # 1.04 − 1 rounds
    assert not ur5.tool_absent and ur5.tool.mass == pytest.approx(1.0) and ur5.control_rate_hz == 500.0


@pytest.mark.parametrize(("plant", "key"), [
    ({"link_inertia": [1, 2]}, "link_inertia"),
    ({"link_inertia": {"seed": -1}}, "link_inertia.seed"),
    ({"link_inertia": {"seed": 1, "mass_rel": 1.5}}, "link_inertia.mass_rel"),
    ({"link_inertia": {"seed": 1, "inertia_rel": 1.0}}, "link_inertia.inertia_rel"),
    ({"link_inertia": {"seed": 1, "com": 0.1}}, "link_inertia.com"),
    ({"link_inertia": {"panda_link1": {"mass_scale": 0}}}, "link_inertia.panda_link1.mass_scale"),
    ({"link_inertia": {"panda_link1": {"com_shift": [0.0, 0.01]}}}, "link_inertia.panda_link1.com_shift"),
    ({"link_inertia": {"panda_link1": {"inertia_scale": [1.0, -1.0, 1.0]}}},
     "link_inertia.panda_link1.inertia_scale"),
    ({"link_inertia": {"panda_link1": {"scale": 1.0}}}, "link_inertia.panda_link1.scale"),
    ({"tool": {"urdf_tool": "maybe"}}, "tool.urdf_tool"),
    ({"tool": {"gripper": {"mass": 1.0}}}, "tool.gripper"),
    ({"tool": {"extra": {"mass": -1.0}}}, "tool.extra.mass"),
    ({"tool": {"extra": {"mass": 1.0, "inertia": [1e-3, 1e-3, 3e-3, 0, 0, 0]}}}, "tool.extra.inertia"),
    ({"friction_drift": {"relative_amplitude": 0.1}}, "friction_drift.time_constant_s"),
    ({"friction_drift": {"relative_amplitude": -0.1, "time_constant_s": 60}}, "friction_drift.relative_amplitude"),
    ({"friction_drift": {"relative_amplitude": 0.1, "time_constant_s": 0}}, "friction_drift.time_constant_s"),
    ({"friction_drift": {"relative_amplitude": 0.1, "time_constant_s": 60, "tau": 1}}, "friction_drift.tau"),
    ({"torque_offset_drift": {"amplitude": [0.1, 0.2], "period_s": 60}}, "torque_offset_drift.amplitude"),
    ({"torque_offset_drift": {"amplitude": [0.1] * 7, "period_s": "slow"}}, "torque_offset_drift.period_s"),
    ({"torque_offset_drift": {"period_s": 60}}, "torque_offset_drift.amplitude"),
])
def test_bad_new_keys_name_the_file_and_key(plant: dict[str, Any], key: str, tmp_path: Path) -> None:
    import yaml
    path = tmp_path / "bad_plant.yaml"
    path.write_text(yaml.safe_dump(plant))
    with pytest.raises(PlantError, match=rf"^{re.escape(str(path))}: {re.escape(key)} "):
        load_plant(path, 7)


@pytest.mark.parametrize(("plant", "key"), [
    ({"link_inertia": {"panda_hand": {"mass_scale": 1.1}}}, "link_inertia.panda_hand"),          # not a moving link
    ({"link_inertia": {"panda_link2": {"inertia_scale": [1.0, 1.0, 3.0]}}},                     # I3 > I1 + I2
     "link_inertia.panda_link2.inertia_scale"),
])
def test_link_errors_the_urdf_refuses_name_the_file_and_key(plant: dict[str, Any], key: str,
                                                             tmp_path: Path) -> None:
    import yaml
    path = tmp_path / "bad_links.yaml"
    path.write_text(yaml.safe_dump(plant))
    spec = load_plant(path, 7)
    with pytest.raises(PlantError, match=rf"^{re.escape(str(path))}: {re.escape(key)}"):
        build_model(robot_setup("panda"), spec)


# ----------------------------------------------------------------------------- link inertia


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_generated_link_errors_are_bounded_physical_and_seeded(robot: str) -> None:
    setup = robot_setup(robot)
    spec = load_plant({"link_inertia": DRAW}, setup.n)
    errors = link_errors(setup, spec)
    assert tuple(errors) == moving_links(urdf_xml(setup.urdf), setup.joint_names)   # every moving link
    # 1e-12: the bounds are exact by construction; only the division I'/I rounds.
    for error in errors.values():
        assert abs(error.mass_scale - 1.0) <= DRAW["mass_rel"]
        assert np.linalg.norm(error.com_shift) <= DRAW["com_m"]
        assert np.all(np.abs(np.array(error.inertia_scale) - 1.0) <= DRAW["inertia_rel"] + 1e-12)
    assert len({e.mass_scale for e in errors.values()}) == len(errors)                # drawn per link
    assert true_urdf(setup, spec) == true_urdf(setup, load_plant({"link_inertia": DRAW}, setup.n))
    assert true_urdf(setup, spec) != true_urdf(setup, load_plant({"link_inertia": {**DRAW, "seed": 4}}, setup.n))
    # Physically valid even at the edge (inertia ±95 %): pinocchio's inertia about the centre of mass
    # is positive definite and obeys the triangle inequality, and MuJoCo (balanceinertia off) compiles it.
    nominal = setup.nominal_model()
    for seed in range(10):
        edge = load_plant({"link_inertia": {"seed": seed, "mass_rel": 0.5, "com_m": 0.05, "inertia_rel": 0.95}},
                          setup.n)
        model = _model(setup, true_urdf(setup, edge))
        for joint in range(1, model.model.njoints):
            principal = np.linalg.eigvalsh(model.model.inertias[joint].inertia)
            assert principal[0] > 0.0 and principal[2] <= principal[0] + principal[1]
            assert model.model.inertias[joint].mass != nominal.model.inertias[joint].mass
        build_model(setup, edge)


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_true_urdf_inverse_dynamics_is_mujocos(robot: str) -> None:
    """pinocchio's RNEA on true_urdf equals MuJoCo's on the plant it simulates: the oracle's model
    is the plant's. Tolerance 1e-9 relative: both engines read the same 17-digit inertias, so only
    round-off differs (~1e-15 seen), while the URDF's own model is off by ~25 %."""
    setup = robot_setup(robot)
    spec = load_plant(RIGID_PLANT, setup.n)
    plant_model = build_model(setup, spec)
    true_model = _model(setup, true_urdf(setup, spec, with_payload=True))
    without_payload = _model(setup, true_urdf(setup, spec))
    nominal, loaded = setup.nominal_model(), setup.nominal_model(spec.payload)
    rng = np.random.default_rng(5)
    for _ in range(4):
        q, qd, qdd = rng.uniform(-2.0, 2.0, setup.n), rng.uniform(-2.0, 2.0, setup.n), rng.uniform(-5.0, 5.0, setup.n)
        mujoco_tau = _mujoco_id(plant_model, q, qd, qdd)
        scale = np.abs(mujoco_tau).max()
        np.testing.assert_allclose(true_model.inverse_dynamics(q, qd, qdd), mujoco_tau, rtol=0.0, atol=1e-9 * scale)
        assert np.abs(nominal.inverse_dynamics(q, qd, qdd) - mujoco_tau).max() > 0.05 * scale
        # The payload the ground truth counts as τ_ext (nominal with minus without) is what separates
        # the oracle's model (no payload) from the plant: RNEA is linear in the inertias.
        payload_tau = loaded.inverse_dynamics(q, qd, qdd) - nominal.inverse_dynamics(q, qd, qdd)
        np.testing.assert_allclose(without_payload.inverse_dynamics(q, qd, qdd) + payload_tau, mujoco_tau,
                                   rtol=0.0, atol=1e-9 * scale)


def test_oracle_estimator_builds_on_the_true_urdf(panda_config) -> None:
    """The call the benchmark makes: Estimator.from_config with urdf=true_urdf and the oracle residual;
    its robot model is the plant's rigid body (1e-9 relative, as above)."""
    setup = robot_setup("panda")
    spec = load_plant(_realistic("panda"), 7)
    trained = load_model(panda_config.model_dir, panda_config.joint_names)
    estimator = Estimator.from_config(panda_config, trained, observer="oracle", urdf=true_urdf(setup, spec),
                                      oracle=OracleResidual(spec, 7))
    q, qd, qdd = setup.home_array(), np.full(7, 0.3), np.full(7, -1.0)
    mujoco_tau = _mujoco_id(build_model(setup, spec), q, qd, qdd)
    np.testing.assert_allclose(estimator.robot.inverse_dynamics(q, qd, qdd), mujoco_tau, rtol=0.0,
                               atol=1e-9 * np.abs(mujoco_tau).max())


# ----------------------------------------------------------------------------- tool


def test_absent_urdf_tool_removes_the_hand_mass_and_keeps_its_frames() -> None:
    setup = robot_setup("panda")
    urdf = urdf_xml(setup.urdf)
    after = links_after(urdf, setup.flange_frame)
    assert set(after) == {"panda_hand", "panda_hand_tcp", "panda_leftfinger", "panda_rightfinger"}
    hand_mass = 0.73 + 2 * 0.015                                    # example-robot-data's panda.urdf, kg
    present = MujocoPlant(setup, load_plant({}, 7))
    absent = MujocoPlant(setup, load_plant({"tool": {"urdf_tool": "absent"}}, 7))
    swapped = MujocoPlant(setup, load_plant({"tool": {"urdf_tool": "absent", "extra": {"mass": 0.6}}}, 7))
    flange = present.body_id(setup.flange_frame)
    subtree = [p.model.body_subtreemass[flange] for p in (present, absent, swapped)]
    # 1e-12 kg: masses are copied, only summed
    assert subtree[0] - subtree[1] == pytest.approx(hand_mass, abs=1e-12)
    assert subtree[1] == pytest.approx(0.0, abs=1e-12) and subtree[2] == pytest.approx(0.6, abs=1e-12)
    for name in after:                                              # wrenches can still be applied there
        assert absent.in_flange_subtree(name)
    _model(setup, true_urdf(setup, load_plant({"tool": {"urdf_tool": "absent"}}, 7)))   # frames load in pinocchio


# ----------------------------------------------------------------------------- drifts


def test_friction_drift_is_a_warm_up_applied_to_every_friction_term() -> None:
    drift = {"relative_amplitude": 0.15, "time_constant_s": 300.0}
    spec = load_plant({"friction": {"model": "stribeck", "coulomb": [1.0] * 7, "static": [1.5] * 7,
                                    "stribeck_velocity": [0.05] * 7, "viscous": [0.2] * 7},
                       "friction_drift": drift}, 7)
    assert friction_drift_factor(spec, 0.0) == pytest.approx(1.15, abs=1e-15)          # cold: 1 + a
    assert friction_drift_factor(spec, 300.0) == pytest.approx(1.0 + 0.15 / math.e, abs=1e-15)
    assert friction_drift_factor(spec, 3000.0) == pytest.approx(1.0, abs=0.15 * math.exp(-10.0) + 1e-15)
    assert friction_drift_factor(load_plant({}, 7), 0.0) == 1.0
    setup = robot_setup("panda")
    qd = np.array([0.5, -0.4, 0.3, -0.6, 0.8, -0.7, 0.9])                            # every joint sliding
    for model in ("stribeck", "gaz_sigmoid"):
        if model == "gaz_sigmoid":
            spec = load_plant({"friction": {"model": "gaz_sigmoid", "phi1": [0.5] * 7, "phi2": [8.0] * 7,
                                            "phi3": [0.02] * 7, "viscous": [0.2] * 7},
                               "friction_drift": drift}, 7)
        plant = MujocoPlant(setup, spec)
        for t in (0.0, 300.0, 5000.0):
            plant.reset(setup.home_array(), qd, time=t)
            _, friction, _ = plant.step(np.zeros(7))
            # 1e-9 N·m: a sliding dry-friction constraint sits at its level up to the solver's round-off
            np.testing.assert_allclose(friction, friction_drift_factor(spec, t) * friction_torque(spec, qd),
                                       atol=1e-9)
            assert plant.time == pytest.approx(t + PHYSICS_DT, abs=1e-12)


def test_torque_offset_drift_has_its_amplitude_and_period() -> None:
    amplitude = [0.2, -0.3, 0.1, 0.0, 0.05, 0.05, -0.02]
    spec = load_plant({"torque_offset_drift": {"amplitude": amplitude, "period_s": 120}}, 7)
    t = np.linspace(0.0, 240.0, 24001)
    drift = np.array([torque_offset_drift(spec, s) for s in t])
    # 1e-6: the sampled peak of a sine with 0.01 s steps lies within (2π·0.005/120)²/2 ≈ 3e-8 of it
    np.testing.assert_allclose(np.abs(drift).max(axis=0), np.abs(amplitude), atol=1e-6)
    np.testing.assert_allclose(torque_offset_drift(spec, 30.0), amplitude, atol=1e-15)          # quarter period
    np.testing.assert_allclose(torque_offset_drift(spec, 150.0), amplitude, atol=1e-12)         # one period later
    np.testing.assert_allclose(drift.mean(axis=0), 0.0, atol=1e-4)                              # zero mean
    np.testing.assert_array_equal(torque_offset_drift(load_plant({}, 7), 30.0), 0.0)


# ----------------------------------------------------------------------------- simulation


@pytest.mark.parametrize(("robot", "scenario", "duration"),
                         [("ur5", "collision", 2.0), ("panda", "contact", 1.5), ("panda", "payload", 1.0)])
def test_realistic_plant_ground_truth_closes_with_the_true_model(robot: str, scenario: str, duration: float) -> None:
    """With the realistic plant, drive + τ_ext − ID_true(q, q̇, q̈) is the friction the plant applied,
    sample by sample (1e-8 N·m, as for the nominal plant: the same state, only round-off), the drive
    is drive_gain ⊙ τ_m plus the offset drift at the plant clock (1e-9), and sliding friction is the
    drifted friction law (1e-6: the dry-friction constraint at its level, as in test_sim)."""
    setup = robot_setup(robot)
    out = run_scenario(robot, scenario, seed=3, duration=duration, plant=_realistic(robot), progress=False)
    spec, truth = out.plant, out.truth
    assert 0.0 <= out.start_time <= SESSION_S
    model = _model(setup, true_urdf(setup, spec))
    true_id = np.array([model.inverse_dynamics(*x) for x in zip(truth.q, truth.qd, truth.qdd)])
    np.testing.assert_allclose(truth.drive_torque + truth.tau_ext - true_id, truth.friction, atol=1e-8)
    clock = out.start_time + out.run.joint_states.stamp
    offset = np.array([torque_offset_drift(spec, t) for t in clock])
    np.testing.assert_allclose(truth.drive_torque - spec.drive_gain * out.run.commands.effort, offset, atol=1e-9)
    factor = np.array([friction_drift_factor(spec, t) for t in clock])[:, None]
    sliding = np.abs(truth.qd) > 0.05
    np.testing.assert_allclose(truth.friction[sliding], (factor * friction_torque(spec, truth.qd))[sliding],
                               atol=1e-6)
    assert sliding.sum() > 100
    if scenario == "payload":
        assert isinstance(spec.payload, Payload)      # the scenario's payload is τ_ext, not in the oracle's model


def test_a_given_plant_clock_is_used_and_a_bad_one_refused() -> None:
    """``start_time`` sets the plant clock the drifts read (the drive's offset at start_time + stamp, 1e-9 N·m as
    above); a negative or non-finite clock is an error."""
    spec = load_plant(_realistic("ur5"), 6)
    out = run_scenario("ur5", "collision", seed=3, duration=0.2, plant=spec, progress=False, start_time=1234.5)
    assert out.start_time == 1234.5
    clock = 1234.5 + out.run.joint_states.stamp
    offset = np.array([torque_offset_drift(out.plant, t) for t in clock])
    np.testing.assert_allclose(out.truth.drive_torque - out.plant.drive_gain * out.run.commands.effort, offset,
                               atol=1e-9)
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="start_time"):
            run_scenario("ur5", "collision", seed=3, duration=0.2, plant=spec, progress=False, start_time=bad)


def test_the_benchmark_spreads_its_training_recordings_over_the_session() -> None:
    """Five training clocks at the middles of five equal parts of the session: with the plants' 300 s offset
    period they meet the drift at five phases a fifth of a period apart (the seeds' draws met one phase)."""
    clocks = training_clocks(5)
    np.testing.assert_allclose(clocks, SESSION_S * (np.arange(5) + 0.5) / 5)
    phases = np.sort(np.mod(np.array(clocks) / 300.0, 1.0))
    np.testing.assert_allclose(np.diff(phases), 0.2, atol=1e-12)


def test_kvark_simulate_takes_the_plant_clock_and_refuses_a_negative_one(tmp_path, capsys) -> None:
    """``--start-time`` reaches the simulation: a negative clock is a one-line error and no bag."""
    from kvark_ros.cli import main
    out = tmp_path / "bag"
    assert main(["simulate", "--robot", "ur5", "--scenario", "collision", "--duration", "0.1", "--start-time",
                 "-5", "--out", str(out)]) == 1
    assert "start_time must be a finite time ≥ 0 s" in capsys.readouterr().err and not out.exists()
