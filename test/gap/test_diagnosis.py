"""Model-gap workflow (issue 6): hidden plant effects are named, fitted and shrink the held-out gap."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("mujoco")

from kvark_ros.core.config import load_config  # noqa: E402
from kvark_ros.core.estimation.robot_model import RobotModel  # noqa: E402
from kvark_ros.gap import diagnose as gap_cli  # noqa: E402
from kvark_ros.gap import selection  # noqa: E402
from kvark_ros.core.estimation.augmentation import load_augmentation, parse_augmentation  # noqa: E402
from kvark_ros.gap.diagnose import diagnose, write_outputs  # noqa: E402
from kvark_ros.gap.diagnosis_report import augmentation  # noqa: E402
from kvark_ros.gap.effects import EFFECT_NAMES, Priors, augmentation_gap  # noqa: E402
from kvark_ros.gap.plausibility import OUTSIDE_TOLERANCE, prior_summary  # noqa: E402
from kvark_ros.io import write_run  # noqa: E402
from kvark_ros.io.recorded_inputs import estimator_inputs  # noqa: E402
from kvark_ros.sim.scenarios import simulate  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DURATION = 7.0
PANDA_ARMATURE = [0.3, 0.3, 0.2, 0.2, 0.1, 0.1, 0.05]
PANDA_COULOMB = [0.5, 0.6, 0.4, 0.5, 0.3, 0.2, 0.2]
PANDA_VISCOUS = [0.3, 0.3, 0.2, 0.2, 0.1, 0.1, 0.1]
PANDA_OFFSET = [0.5, -0.4, 0.3, 0.0, 0.2, 0.0, 0.0]
PANDA_GAIN = [0.9, 1.1, 1.0, 0.92, 1.0, 1.0, 1.0]
PAYLOAD = {"mass": 1.5, "com": [0.0, 0.02, 0.08]}
# Stribeck hump F_s − F_c on the four big Panda / three big UR5 joints only (the others: plain
# Coulomb), so "the right joints" is tested; v_s = 0.3 rad/s from the catalog's v_s grid: at 0.1 rad/s
# the hump lives where the joints mostly stick and is found on some joints only.
STRIBECK_VELOCITY = 0.3
PANDA_STRIBECK = [0.5, 0.5, 0.4, 0.5, 0.0, 0.0, 0.0]
UR5_COULOMB = [1.0, 1.2, 0.8, 0.4, 0.3, 0.3]
UR5_VISCOUS = [0.5, 0.5, 0.4, 0.1, 0.1, 0.1]
UR5_STRIBECK = [0.6, 0.6, 0.5, 0.0, 0.0, 0.0]
UR5_OFFSET = [0.5, -0.6, 0.4, 0.2, 0.0, 0.0]
UR5_GAIN = [0.9, 1.08, 0.92, 1.0, 1.0, 1.0]
# One cycles_per_rev per plant: diagnose fits one ripple order for all joints.
RIPPLE = {"panda": {"amplitude": [0.4, 0.0, 0.3, 0.0, 0.3, 0.0, 0.0], "cycles_per_rev": [8] * 7},
          "ur5": {"amplitude": [0.5, 0.0, 0.4, 0.3, 0.0, 0.0], "cycles_per_rev": [6] * 6}}
# Encoder offsets on gravity-loaded joints (wrist joints see too little gravity to be identified).
JOINT_OFFSET = {"panda": [0.0, 0.03, 0.0, -0.04, 0.0, 0.03, 0.0], "ur5": [0.0, 0.03, -0.04, 0.0, 0.0, 0.0]}


def _stribeck(coulomb, hump):
    return {"friction": {"model": "stribeck", "coulomb": coulomb, "static": [c + h for c, h in zip(coulomb, hump)],
                         "stribeck_velocity": [STRIBECK_VELOCITY] * len(coulomb)}}


PLANTS = {
    ("panda", "none"): {},
    ("panda", "armature"): {"armature": PANDA_ARMATURE},
    ("panda", "payload"): {"payload": PAYLOAD},
    ("panda", "friction"): {"friction": {"model": "coulomb_viscous", "coulomb": PANDA_COULOMB,
                                         "viscous": PANDA_VISCOUS}},
    ("panda", "torque_offset"): {"torque_offset": PANDA_OFFSET},
    ("panda", "drive_gain"): {"drive_gain": PANDA_GAIN},
    ("panda", "payload+torque_offset"): {"payload": PAYLOAD, "torque_offset": PANDA_OFFSET},
    ("ur5", "none"): {},
    ("ur5", "payload"): {"payload": {"mass": 2.0, "com": [0.0, 0.0, 0.05]}},
    ("ur5", "armature"): {"armature": [0.5, 0.5, 0.3, 0.1, 0.1, 0.05]},
    ("ur5", "friction"): {"friction": {"model": "coulomb_viscous", "coulomb": UR5_COULOMB, "viscous": UR5_VISCOUS}},
    ("ur5", "torque_offset"): {"torque_offset": UR5_OFFSET},
    ("ur5", "drive_gain"): {"drive_gain": UR5_GAIN},
    ("panda", "stribeck"): _stribeck(PANDA_COULOMB, PANDA_STRIBECK),
    ("ur5", "stribeck"): _stribeck(UR5_COULOMB, UR5_STRIBECK),
    ("panda", "position_ripple"): {"position_ripple": RIPPLE["panda"]},
    ("ur5", "position_ripple"): {"position_ripple": RIPPLE["ur5"]},
    ("panda", "joint_offset"): {"joint_offset": JOINT_OFFSET["panda"]},
    ("ur5", "joint_offset"): {"joint_offset": JOINT_OFFSET["ur5"]},
    ("panda", "realistic"): yaml.safe_load((ROOT / "kvark_ros/sim/plants/panda_realistic.yaml").read_text()),
    # a link-side torque sensor 7 % off on joint 2 (3.5 × its ±2 % prior) beside Coulomb friction on every joint
    ("panda", "gain_beyond_sensor_prior"): {"drive_gain": [1.0, 0.93, 1.0, 1.0, 1.0, 1.0, 1.0],
                                            "friction": {"model": "coulomb_viscous", "coulomb": PANDA_COULOMB,
                                                         "viscous": [0.0] * 7}},
}
# The plants whose drive gains lie beyond the prior of how their robot measures τ_m (the Panda: link-side sensors,
# ±2 %; the UR5: motor current, ±10 %: its 0.9 sits at the bound), and the joint whose gain explains most (the Panda's
# 1.1 on joint 2, which holds more of the arm's weight than joint 1's 0.9)
GAIN_PLANTS = {("panda", "drive_gain"): "panda_joint2", ("ur5", "drive_gain"): "shoulder_pan_joint",
               ("panda", "gain_beyond_sensor_prior"): "panda_joint2"}


def _robot(name: str, base=None) -> RobotModel:
    c = load_config(ROOT / "config" / f"{name}.yaml")
    return RobotModel(c.urdf, c.joint_names, c.ee_frame, c.flange_frame, augmentation=base)


@pytest.fixture(scope="module")
def robots():
    return {"panda": _robot("panda"), "ur5": _robot("ur5")}


@pytest.fixture(scope="module")
def runs():
    """One short excitation run per hidden-effect plant (simulated once per module)."""
    return {key: simulate(key[0], "excitation", seed=3, duration=DURATION, plant=plant, progress=False)
            for key, plant in PLANTS.items()}


@pytest.fixture(scope="module")
def diagnoses(runs, robots):
    # The test plants' drive gains (0.9-1.1, current-based drives) and encoder offsets (up to 2.3°, incremental
    # encoders) lie outside the default priors (±10 %, ±1°), so the fits get the priors a user of such a robot
    # passes (`--max-gain-error 0.2 --max-joint-offset 5`); the default priors are tested in test_gap_priors. The
    # simulator applies the commanded torque: robot_model.torque_measurement commanded_effort (the widest priors).
    priors = Priors(max_gain_error=0.2, max_joint_offset=float(np.radians(5.0)), torque_measurement="commanded_effort")
    return {key: diagnose(robots[key[0]], [estimator_inputs(run)], log=lambda _: None, priors=priors)
            for key, run in runs.items()}


@pytest.fixture(scope="module")
def own_priors(runs, robots):
    """The gain plants diagnosed as their users would: with the priors of their robot's torque measurement."""
    measurement = {robot: load_config(ROOT / "config" / f"{robot}.yaml").torque_measurement for robot in robots}
    return {key: diagnose(robots[key[0]], [estimator_inputs(runs[key])], log=lambda _: None,
                          priors=Priors(torque_measurement=measurement[key[0]])) for key in GAIN_PLANTS}


def _effect(diag, name):
    found = [e for e in diag.result["effects"] if e["name"] == name]
    assert found, f"{name} not named; found {[e['name'] for e in diag.result['effects']]}"
    return found[0]


def _shrinks(diag, factor=0.5):
    before, after = diag.result["gap_before"]["joint_rmse_mean"], diag.result["gap_after"]["joint_rmse_mean"]
    assert after <= factor * before, (before, after)


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_plant_equal_to_urdf_yields_no_effect(diagnoses, robot):
    assert diagnoses[(robot, "none")].result["effects"] == []


def test_armature_named_with_joints_and_values(diagnoses):
    diag = diagnoses[("panda", "armature")]
    eff = _effect(diag, "armature")
    assert eff["joints"] == list(range(7))
    np.testing.assert_allclose(eff["parameters"]["armature"], PANDA_ARMATURE, rtol=0.1)
    assert [e["name"] for e in diag.result["effects"]] == ["armature"]
    _shrinks(diag)


def test_every_named_effect_states_its_share_of_the_prior_and_none_lies_outside_unwarned(diagnoses):
    """The fit is bounded by the priors, so no named effect uses more than its whole prior (1 + round-off); an effect
    at a bound carries a warning. The armature's share is its largest value over its per-joint bound."""
    for key, diag in diagnoses.items():
        for effect in diag.result["effects"]:
            use = effect["prior_use"]
            assert use is None or 0.0 <= use <= 1.0 + OUTSIDE_TOLERANCE, (key, effect["name"], use)
            assert not effect["at_prior_bound"] or diag.result["warnings"], (key, effect["name"])
        assert prior_summary(diag.result)["unwarned"] == []
    diag = diagnoses[("panda", "armature")]
    armature = _effect(diag, "armature")
    bound = np.array(diag.result["priors"]["effects"]["armature"]["bound"])
    assert armature["prior_use"] == pytest.approx(np.max(np.array(armature["parameters"]["armature"]) / bound))


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_payload_mass_within_ten_percent(diagnoses, robot):
    diag = diagnoses[(robot, "payload")]
    truth = PLANTS[(robot, "payload")]["payload"]
    eff = _effect(diag, "payload")
    assert abs(eff["parameters"]["mass"] - truth["mass"]) <= 0.1 * truth["mass"]
    np.testing.assert_allclose(eff["parameters"]["com"], truth["com"], atol=0.01)
    assert eff["parameters"]["physically_consistent"]
    # The mass is read through the drives' gains, known to ±20 % here (the fixture's max_gain_error): its interval
    # carries at least that share, and on this plant the interval holds the true mass.
    assert eff["ci95"]["mass"] >= 0.2 * eff["parameters"]["mass"]
    assert abs(eff["parameters"]["mass"] - truth["mass"]) <= eff["ci95"]["mass"]
    assert [e["name"] for e in diag.result["effects"]] == ["payload"]
    _shrinks(diag, 0.1)


def test_ur5_armature(diagnoses):
    diag = diagnoses[("ur5", "armature")]
    eff = _effect(diag, "armature")
    truth = np.array(PLANTS[("ur5", "armature")]["armature"])
    assert set(eff["joints"]) >= {0, 1, 2}
    got = dict(zip(eff["joints"], eff["parameters"]["armature"]))
    for j, value in got.items():
        assert abs(value - truth[j]) <= 0.1 * truth[j] + 0.01, (j, value, truth[j])
    _shrinks(diag)


@pytest.mark.parametrize(("robot", "offset"), [("panda", PANDA_OFFSET), ("ur5", UR5_OFFSET)])
def test_torque_offset(diagnoses, robot, offset):
    diag = diagnoses[(robot, "torque_offset")]
    eff = _effect(diag, "torque_offset")
    assert eff["joints"] == [j for j, v in enumerate(offset) if v != 0.0]
    # measured errors < 0.006 N·m (Panda), < 0.001 N·m (UR5): 0.03 N·m
    np.testing.assert_allclose(eff["parameters"]["offset"], [v for v in offset if v], atol=0.03)
    assert [e["name"] for e in diag.result["effects"]] == ["torque_offset"]
    _shrinks(diag)


@pytest.mark.parametrize(("robot", "gain"), [("panda", PANDA_GAIN), ("ur5", UR5_GAIN)])
def test_drive_gain(diagnoses, robot, gain):
    diag = diagnoses[(robot, "drive_gain")]
    eff = _effect(diag, "drive_gain")
    assert eff["joints"] == [j for j, v in enumerate(gain) if v != 1.0]
    # measured errors < 0.001: 0.01
    np.testing.assert_allclose(eff["parameters"]["gain"], [v for v in gain if v != 1.0], atol=0.01)
    _shrinks(diag)


FRICTION_SPEEDS = np.array([0.3, 0.6, 1.0])   # rad/s, where the arm spends its moving time


def _friction_curve(diag, n: int) -> np.ndarray:
    """Fitted dry + viscous friction (n, speeds) at FRICTION_SPEEDS: what the model adds to τ_EL.

    The dry-friction width ε is chosen from a grid by the held-out gap; MuJoCo's friction constraint
    and the 0.15 s torque filter round the sign, so a wide ε fits best and trades level against
    the viscous slope. The curve, not the split, is the physical quantity the fit pins down.
    """
    curve = np.zeros((n, len(FRICTION_SPEEDS)))
    coulomb, viscous = _effect(diag, "coulomb_friction"), _effect(diag, "viscous_friction")
    for j, level in zip(coulomb["joints"], coulomb["parameters"]["coulomb"]):
        curve[j] += level * np.tanh(FRICTION_SPEEDS / coulomb["parameters"]["epsilon"])
    for j, slope in zip(viscous["joints"], viscous["parameters"]["viscous"]):
        curve[j] += slope * FRICTION_SPEEDS
    return curve


@pytest.mark.parametrize(("robot", "coulomb", "viscous"), [("panda", PANDA_COULOMB, PANDA_VISCOUS),
                                                             ("ur5", UR5_COULOMB, UR5_VISCOUS)])
def test_coulomb_and_viscous_friction(diagnoses, robot, coulomb, viscous):
    diag = diagnoses[(robot, "friction")]
    n = len(coulomb)
    assert _effect(diag, "coulomb_friction")["joints"] == list(range(n))
    assert len(_effect(diag, "viscous_friction")["joints"]) >= 4
    truth = np.array(coulomb)[:, None] + np.outer(viscous, FRICTION_SPEEDS)
    fitted = _friction_curve(diag, n)
    # measured: fitted/true 0.84-1.11 over both robots, speeds and joints (the Panda's last joint,
    # tiny inertia, sticks much of the time and is the 0.84); stated: 20 %
    assert np.all(np.abs(fitted - truth) <= 0.2 * truth), np.round(fitted / truth, 3)
    # The sharp stick-slip transition at q̇ = 0 may add a Stribeck hump (low v_s) and, through the
    # asymmetric sticking, a small torque offset (measured 0.04 N·m); nothing else.
    for extra in diag.result["effects"]:
        if extra["name"] == "torque_offset":
            assert np.max(np.abs(extra["parameters"]["offset"])) <= 0.1, extra
        else:
            assert extra["name"] in ("coulomb_friction", "viscous_friction", "stribeck_friction"), extra
    _shrinks(diag, 0.25)


@pytest.mark.parametrize(("robot", "coulomb", "hump"), [("panda", PANDA_COULOMB, PANDA_STRIBECK),
                                                         ("ur5", UR5_COULOMB, UR5_STRIBECK)])
def test_stribeck_friction(diagnoses, robot, coulomb, hump):
    diag = diagnoses[(robot, "stribeck")]
    eff = _effect(diag, "stribeck_friction")
    assert eff["joints"] == [j for j, h in enumerate(hump) if h > 0]
    assert eff["parameters"]["stribeck_velocity"] == STRIBECK_VELOCITY
    # F_s − F_c: measured errors ≤ 0.06 N·m (12 %) on the Panda, ≤ 0.14 N·m (23 %) on the UR5, whose
    # larger dry friction holds the joints longer in the low-velocity band that shows the hump: 30 %
    for j, value in zip(eff["joints"], eff["parameters"]["static_minus_coulomb"]):
        assert abs(value - hump[j]) <= 0.3 * hump[j], (j, value, hump[j])
    dry = _effect(diag, "coulomb_friction")
    assert dry["joints"] == list(range(len(coulomb)))
    np.testing.assert_allclose(dry["parameters"]["coulomb"], coulomb, rtol=0.1)   # measured ≤ 4.5 %
    assert sorted(e["name"] for e in diag.result["effects"]) == ["coulomb_friction", "stribeck_friction"]
    _shrinks(diag, 0.25)


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_position_ripple(diagnoses, robot):
    diag = diagnoses[(robot, "position_ripple")]
    truth = RIPPLE[robot]
    eff = _effect(diag, "position_ripple")
    assert eff["joints"] == [j for j, a in enumerate(truth["amplitude"]) if a]
    assert eff["parameters"]["cycles_per_rev"] == truth["cycles_per_rev"][0]
    # the plant's ripple is amplitude·sin(k q): measured amplitude errors ≤ 0.005 N·m, phase (cos
    # part) ≤ 0.002 N·m: 0.02 N·m (5 % of the smallest amplitude)
    expected = [a for a in truth["amplitude"] if a]
    np.testing.assert_allclose(eff["parameters"]["sin_amplitude"], expected, atol=0.02)
    np.testing.assert_allclose(eff["parameters"]["cos_amplitude"], 0.0, atol=0.02)
    assert [e["name"] for e in diag.result["effects"]] == ["position_ripple"]
    _shrinks(diag, 0.25)


@pytest.mark.parametrize("robot", ["panda", "ur5"])
def test_joint_offset(diagnoses, robot):
    diag = diagnoses[(robot, "joint_offset")]
    truth = JOINT_OFFSET[robot]
    eff = _effect(diag, "joint_offset")
    assert eff["joints"] == [j for j, d in enumerate(truth) if d]
    # The regressor is the first-order sensitivity −∂τ_EL/∂q δ (gravity, inertia and Coriolis);
    # measured errors ≤ 0.002 rad: 0.01 rad, a quarter of the offsets
    np.testing.assert_allclose(eff["parameters"]["offset"], [d for d in truth if d], atol=0.01)
    _shrinks(diag)


def test_two_hidden_effects_both_named(diagnoses):
    diag = diagnoses[("panda", "payload+torque_offset")]
    # the backward pass removes the small position ripple forward selection picks up first
    assert [e["name"] for e in diag.result["effects"]] == ["payload", "torque_offset"]
    payload = _effect(diag, "payload")
    offset = _effect(diag, "torque_offset")
    assert abs(payload["parameters"]["mass"] - PAYLOAD["mass"]) <= 0.1 * PAYLOAD["mass"]
    # Every offset joint is named; a joint without one may join with a value inside the 0.03 N·m tolerance (the
    # screening threshold is 0.005 N·m of held-out gap, and which side of it a 0.007 N·m fit lands on is rounding).
    assert {0, 1, 2, 4} <= set(offset["joints"])
    np.testing.assert_allclose(offset["parameters"]["offset"], [PANDA_OFFSET[j] for j in offset["joints"]], atol=0.03)
    for eff in diag.result["effects"]:      # leave-one-out reductions of the remaining effects
        assert eff["gap_reduction"] > 0.5
        assert np.all(np.less(eff["held_out_rmse_after"], eff["held_out_rmse_before"])), eff
    _shrinks(diag, 0.1)


def test_cli_writes_outputs_from_a_bag(runs, robots, tmp_path_factory):
    bag = tmp_path_factory.mktemp("gap") / "payload.mcap"
    write_run(bag, runs[("panda", "payload")])
    out = tmp_path_factory.mktemp("gap_out")
    parser = argparse.ArgumentParser()
    gap_cli.add_parser(parser.add_subparsers())
    args = parser.parse_args(["diagnose", "--config", str(ROOT / "config" / "panda.yaml"), "--bags", str(bag),
                              "--out", str(out)])
    assert args.run(args) == 0
    result = json.loads((out / "diagnosis.json").read_text())
    assert set(result) >= {"gap_before", "gap_after", "effects"}
    assert len(result["gap_before"]["joint_rmse"]) == 7
    assert {"name", "joints", "parameters", "ci95", "gap_reduction"} <= set(result["effects"][0])
    assert result["effects"][0]["name"] in EFFECT_NAMES
    for name in ("report.md", "gap_per_joint.png", "residual_vs_velocity.png", "residual_vs_position.png"):
        assert (out / name).is_file()
    # The named payload's mass regroups with link 6 (the flange is on joint 7's axis): the report says so.
    assert result["flange_mass"]["identified"] is False
    assert "The flange link's mass is not identified on its own" in (out / "report.md").read_text()
    # The augmentation reproduces the fitted gap: applied to the held-out samples it leaves the after-gap.
    aug = yaml.safe_load((out / "augmentation.yaml").read_text())
    assert aug["effects"][0]["name"] == "payload"
    robot = robots["panda"]
    diag = diagnose(robot, [estimator_inputs(runs[("panda", "payload")])], log=lambda _: None, priors=Priors())
    h = diag.held
    predicted = augmentation_gap(aug, robot, h.q, h.qd, h.qdd, h.tau_m)
    after = np.sqrt(np.mean(np.square(h.gap - predicted), axis=0))
    np.testing.assert_allclose(after, diag.result["gap_after"]["joint_rmse"], rtol=1e-6, atol=1e-9)
    _ = write_outputs  # public for programmatic use


def test_against_a_corrected_model_only_the_new_effect_is_named(runs, robots, tmp_path):
    """A robot whose torque offsets are already known (the base augmentation) gets a payload: diagnosed against
    the corrected model, the payload is named alone, and the written augmentation holds both."""
    names = load_config(ROOT / "config" / "panda.yaml").joint_names
    joints = [j for j, v in enumerate(PANDA_OFFSET) if v]
    base_path = tmp_path / "base.yaml"
    base_path.write_text(yaml.safe_dump({"joint_names": list(names), "effects": [
        {"name": "torque_offset", "joint_indices": joints, "theta": [PANDA_OFFSET[j] for j in joints]}]}))
    corrected = _robot("panda", load_augmentation(base_path, names))
    run = runs[("panda", "payload+torque_offset")]
    diag = diagnose(corrected, [estimator_inputs(run)], log=lambda _: None, priors=Priors())
    assert [e["name"] for e in diag.result["effects"]] == ["payload"]
    assert abs(_effect(diag, "payload")["parameters"]["mass"] - PAYLOAD["mass"]) <= 0.1 * PAYLOAD["mass"]
    assert diag.result["against"] == str(base_path)
    document = augmentation(diag, corrected, "panda")
    assert [e["name"] for e in document["effects"]] == ["torque_offset", "payload"]
    combined = _robot("panda", parse_augmentation(yaml.safe_dump(document), names))
    assert combined.augmentation.payload is not None
    np.testing.assert_allclose(combined.augmentation.torque_effects[0].theta[:, 0], [PANDA_OFFSET[j] for j in joints])
    # what is left is as small as when the nominal model is diagnosed for both effects at once (20 % margin: the
    # two fits differ only in how the offsets were obtained)
    both = diagnose(robots["panda"], [estimator_inputs(run)], log=lambda _: None, priors=Priors())
    assert diag.result["gap_after"]["joint_rmse_mean"] <= 1.2 * both.result["gap_after"]["joint_rmse_mean"]


def test_a_known_payload_com_is_kept_and_the_mass_found(runs, robots):
    """`--payload-com`: with the CoM given, only mass and inertia are fitted; the written θ has the 10 parameters
    with first moments m·c."""
    from kvark_ros.gap.diagnosis_report import augmentation as document_of
    com = PAYLOAD.get("com", [0.0, 0.0, 0.0])
    priors = Priors(max_gain_error=0.2, max_joint_offset=float(np.radians(5.0)), payload_com=tuple(com))
    diag = diagnose(robots["panda"], [estimator_inputs(runs[("panda", "payload")])], log=lambda _: None, priors=priors)
    eff = _effect(diag, "payload")
    assert abs(eff["parameters"]["mass"] - PAYLOAD["mass"]) <= 0.1 * PAYLOAD["mass"]
    np.testing.assert_allclose(eff["parameters"]["com"], com, atol=1e-12)      # fixed, not fitted
    entry = [e for e in document_of(diag, robots["panda"])["effects"] if e["name"] == "payload"][0]
    assert len(entry["theta"]) == 10
    np.testing.assert_allclose(entry["theta"][1:4], np.array(com) * entry["theta"][0], atol=1e-12)


def test_a_realistic_plant_gives_an_augmentation_the_robot_model_accepts(diagnoses):
    """Link inertial errors, a tool mismatch, stiction and drifts (panda_realistic.yaml): whatever is named, the
    written augmentation leaves every link physically consistent (the robot model refuses it otherwise), and the
    gap shrinks."""
    diag = diagnoses[("panda", "realistic")]
    names = load_config(ROOT / "config" / "panda.yaml").joint_names
    document = augmentation(diag, _robot("panda"), "panda")
    _robot("panda", parse_augmentation(yaml.safe_dump(document), names))     # raises RobotModelError if not
    _shrinks(diag, 0.6)


def test_every_start_begins_from_the_urdf_priors_and_the_result_is_the_chosen_starts(runs, robots, monkeypatch):
    """A candidate that comes out physically inconsistent tightens its bodies' priors (``admissible.consistent``).
    Those priors were kept on the fitter for every later candidate, start and the final refit: on the realistic
    Panda's benchmark bags the final refit of start 1's effects then had a held-out gap of 0.56 N·m where start 1
    itself had 0.23.
    Every start must begin from the URDF's priors, and the final fit must be the chosen start's."""
    starts, ends = [], []
    greedy = selection.greedy

    def recording(fitter, *args, **kwargs):
        starts.append(dict(fitter.prior_scale))
        found = greedy(fitter, *args, **kwargs)
        ends.append((found, dict(fitter.prior_scale)))
        return found

    monkeypatch.setattr(selection, "greedy", recording)
    diag = diagnose(robots["panda"], [estimator_inputs(runs[("panda", "realistic")])], log=lambda _: None,
                    priors=Priors())
    assert len(starts) == selection.STARTS
    tightened = [any(not np.array_equal(end[name], starts[0][name]) for name in end) for _, end in ends]
    assert any(tightened)                    # some start did tighten a prior: the case this test is about
    for begun in starts[1:]:
        assert begun.keys() == starts[0].keys()
        assert all(np.array_equal(begun[name], starts[0][name]) for name in begun)
    chosen = [found for found, _ in ends if found is not None and [t.name for t in found[0]] ==
              [t.name for t in diag.terms] and all(a.joints == b.joints for a, b in zip(found[0], diag.terms))]
    assert chosen, "the final effects are not those of any start"
    # the final refit of the chosen start's effects under its own priors reproduces its held-out residual
    # (the same bounded least squares from the same data: round-off only)
    assert any(np.allclose(found[4], diag.held_after, rtol=0.0, atol=1e-6) for found in chosen)


@pytest.mark.parametrize("key", list(GAIN_PLANTS))
def test_a_drive_gain_beyond_its_prior_leads_the_report(own_priors, key):
    """Where a drive gain beyond the prior of the robot's torque measurement explains the gap, the report's first
    warning is that gain (the explanation that explains most, however far beyond its prior), saying how far beyond
    and what to change; look-alikes that explain less follow it."""
    diag = own_priors[key]
    first = diag.result["warnings"][0]
    assert first.startswith("drive_gain") and GAIN_PLANTS[key] in first, diag.result["warnings"]
    assert "× its prior" in first or "at the bound of its prior" in first
    assert "--max-gain-error" in first
    beyond = diag.result["beyond_priors"]
    assert [record["explained"] for record in beyond] == sorted((record["explained"] for record in beyond),
                                                                reverse=True)
    if key == ("panda", "gain_beyond_sensor_prior"):
        assert beyond[0]["effect"] == "drive_gain" and beyond[0]["joint"] == 1
        assert beyond[0]["wanted"] == pytest.approx(0.07, abs=0.01)    # |1 − 0.93|; measured 0.070
        assert beyond[0]["ratio"] > 3.0 and "far beyond it" in first


def test_a_payload_is_stated_consistent_only_as_what_it_is_checked_on(diagnoses):
    """The payload plants' payloads are bodies: the flange link and the payload itself are checked and consistent."""
    for robot in ("panda", "ur5"):
        params = _effect(diagnoses[(robot, "payload")], "payload")["parameters"]
        assert params["flange_link_consistent"] and params["payload_consistent"] and params["physically_consistent"]
        assert min(params["inertia_eigenvalues"]) >= -1e-6        # inertia_problem's tolerance, kg·m²
