"""Physical priors of every effect, scaled to the robot (issue 28): derived from the URDF and the torque measurement,
an effect at its bound dropped and named with the flag that widens it, never replaced by a look-alike outside its own
prior."""
from __future__ import annotations

import argparse

import numpy as np
import pinocchio as pin
import pytest
import yaml

from kvark_ros.core.config import default_config_path, load_config
from kvark_ros.core.effect_catalog import CHANGES_BETWEEN_RUNS, EFFECT_NAMES
from kvark_ros.core.estimation.augmentation import parse_augmentation
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.gap.admissible import at_bounds, prior_use
from kvark_ros.gap.admissible import consistent
from kvark_ros.gap.diagnose import HOLDOUT, _prior_scale, body_fitter, diagnose, prepare
from kvark_ros.gap.effects import Priors, Term
from kvark_ros.gap.plausibility import plausibility_warnings
from kvark_ros.gap.priors import ACCELERATION_TIME, MEASUREMENT_WIDTHS, PHYSICAL_GAIN_ERROR, robot_priors
from kvark_ros.gap.selection import payload_first


@pytest.fixture(scope="module")
def panda():
    return RobotModel.from_config(load_config(default_config_path("panda")))


@pytest.fixture(scope="module")
def ur5():
    return RobotModel.from_config(load_config(default_config_path("ur5")))


def test_priors_are_the_stated_shares_of_the_urdf_limits(panda, ur5):
    # Panda URDF: effort 87 N·m (joints 1-4), 12 N·m (5-7), velocity 2.175 / 2.61 rad/s; UR5: 150 / 28 N·m, 3.15 rad/s
    sensor = robot_priors(panda, Priors(torque_measurement="link_torque_sensor"))
    assert sensor.limits["torque_offset"][0] == pytest.approx(0.02 * 87.0)
    assert sensor.limits["position_ripple"][6] == pytest.approx(0.01 * 12.0)
    assert sensor.limits["armature"][0] == pytest.approx(87.0 * 0.25 * ACCELERATION_TIME / 2.175)
    assert sensor.gain_bound == 0.02 and "τ_max 87, 87, 87, 87, 12" in sensor.sources["torque_offset"]
    current = robot_priors(ur5, Priors(torque_measurement="motor_current"))
    assert current.limits["position_ripple"][1] == pytest.approx(0.02 * 150.0)
    assert current.limits["viscous_friction"][3] == pytest.approx(0.2 * 28.0 / 3.2)
    assert current.limits["coulomb_friction"][0] == pytest.approx(0.2 * 150.0)
    assert current.gain_bound == 0.1 and "motor_current" in current.sources["position_ripple"]
    # The payload the effort limits hold: the Panda is rated 3 kg, the UR5 5 kg; the bound is what the joints hold
    # beyond their own arm in the worst sampled posture, so at least the rated payload and less than twice it.
    assert 3.0 <= sensor.limits["payload"][0] < 6.0
    assert 5.0 <= current.limits["payload"][0] < 11.0
    # The widths grow from a link-side sensor to motor current to a commanded effort.
    for share in ("gain", "offset", "ripple", "friction", "armature"):
        widths = [MEASUREMENT_WIDTHS[m][share] for m in ("link_torque_sensor", "motor_current", "commanded_effort")]
        assert widths == sorted(widths) and widths[0] < widths[2], share
    # --max-gain-error and --prior EFFECT=FACTOR override the derived bounds.
    wider = robot_priors(ur5, Priors(max_gain_error=0.15, scale=(("armature", 2.0),)))
    assert wider.gain_bound == 0.15 and np.all(wider.limits["drive_gain"] == 0.15)
    np.testing.assert_allclose(wider.limits["armature"], 2.0 * current.limits["armature"])
    assert "--prior" in wider.sources["armature"]


def test_term_bounds_are_the_priors_per_joint(ur5):
    priors = robot_priors(ur5, Priors())
    lo, hi = Term("position_ripple", (1, 4)).bounds(priors)
    np.testing.assert_allclose(hi, [3.0, 3.0, 0.56, 0.56])     # sin and cos of each joint, 2 % of 150 and 28 N·m
    np.testing.assert_allclose(lo, -hi)
    lo, hi = Term("armature", (0,)).bounds(priors)
    assert lo[0] == 0.0 and hi[0] == pytest.approx(priors.limits["armature"][0])
    lo, hi = Term("payload", tuple(range(6))).bounds(priors)
    assert hi[0] == priors.limits["payload"][0] and np.all(np.isinf(hi[1:]))


def test_a_value_at_its_prior_is_a_warning_naming_the_flag(ur5):
    priors = robot_priors(ur5, Priors())
    names = ur5.joint_names
    armature = Term("armature", (0, 3))
    gain = Term("drive_gain", (2,))
    inside = np.array([0.5 * priors.limits["armature"][0], 0.5 * priors.limits["armature"][3]])
    assert plausibility_warnings([armature, gain], [inside, np.array([0.05])], priors, names) == []
    at_bound = np.array([priors.limits["armature"][0], inside[1]])
    warnings = plausibility_warnings([armature, gain], [at_bound, np.array([-0.1])], priors, names)
    assert len(warnings) == 2
    assert names[0] in warnings[0] and "--prior armature=" in warnings[0] and names[3] not in warnings[0]
    assert names[2] in warnings[1] and "--max-gain-error" in warnings[1]
    assert list(at_bounds(armature, at_bound, priors)) == [True, False]


def test_prior_use_is_the_largest_share_of_its_bound_and_ignores_the_physical_ones(ur5):
    """|θ| / bound per parameter, the largest: a symmetric prior counts either sign, a non-negative effect's lower
    bound 0 and a payload's positive-mass bound are physics, not its prior, and a term without a finite prior has
    none."""
    priors = robot_priors(ur5, Priors())
    ripple = Term("position_ripple", (1, 4))        # bounds 3.0 (joint 2) and 0.56 (joint 5) N·m, sin and cos
    assert prior_use(ripple, np.array([0.3, -1.5, 0.0, 0.14]), priors) == pytest.approx(0.5)
    assert prior_use(ripple, np.array([0.3, 0.0, -0.56, 0.0]), priors) == pytest.approx(1.0)
    armature = Term("armature", (0,))
    assert prior_use(armature, np.array([0.0]), priors) == 0.0
    assert prior_use(armature, np.array([2.0 * priors.limits["armature"][0]]), priors) == pytest.approx(2.0)
    payload = Term("payload", tuple(range(6)))
    mass_bound = priors.limits["payload"][0]
    theta = np.zeros(10)
    theta[0], theta[1:4] = -0.5, 5.0                # a lighter tool (its lower bound is the link's mass, physics)
    assert prior_use(payload, theta, priors) == 0.0
    theta[0] = 0.25 * mass_bound
    assert prior_use(payload, theta, priors) == pytest.approx(0.25)
    unbounded = robot_priors(ur5, Priors(scale=(("armature", np.inf),)))
    assert prior_use(armature, np.array([1.0]), unbounded) is None


def test_the_prior_flag_is_parsed_and_refuses_gains_and_typos():
    assert _prior_scale("armature=2.5") == ("armature", 2.5)
    with pytest.raises(argparse.ArgumentTypeError, match="--max-gain-error"):
        _prior_scale("drive_gain=2")
    with pytest.raises(argparse.ArgumentTypeError, match="did you mean 'armature'"):
        _prior_scale("armatur=2")
    with pytest.raises(argparse.ArgumentTypeError, match="positive"):
        _prior_scale("armature=-1")


def _motion(robot: RobotModel, duration: float = 12.0, rate: float = 250.0) -> tuple:
    """A smooth multi-sine motion about a mid posture (q, q̇, q̈ analytic) and the rigid-body torque τ_EL."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, duration, 1.0 / rate)
    n = robot.n
    w = 2 * np.pi * rng.uniform(0.15, 0.45, (n, 3))
    amp, phase = rng.uniform(0.15, 0.35, (n, 3)), rng.uniform(0.0, 2 * np.pi, (n, 3))
    center = np.array([0.0, 0.3, 0.0, -1.8, 0.0, 1.8, 0.8])[:n]
    arg = w[None] * t[:, None, None] + phase[None]
    q = center + np.einsum("jk,tjk->tj", amp, np.sin(arg))
    qd = np.einsum("jk,tjk->tj", amp * w, np.cos(arg))
    qdd = np.einsum("jk,tjk->tj", -amp * w ** 2, np.sin(arg))
    tau = np.array([pin.rnea(robot.model, robot.data, q[k], qd[k], qdd[k]) for k in range(len(t))])
    return t, q, qd, qdd, tau, rng


def test_a_gain_beyond_its_prior_is_named_with_the_flag_and_no_look_alike_stands_in(panda):
    """A Panda joint whose drive applies 0.87 τ_m (|1 − g| = 0.13 against motor current's ±10 %) with Coulomb friction:
    the gain is not accepted, the warning names it with |1 − g| ≈ 0.13 and ``--max-gain-error 0.15``, and nothing
    accepted sits at its own prior's bound (the armature, ripple and offset that stood in for it before)."""
    t, q, qd, _, tau, rng = _motion(panda)
    coulomb = np.array([0.5, 0.6, 0.4, 0.5, 0.3, 0.2, 0.2])
    gain = np.ones(7)
    gain[1] = 0.87
    tau_m = (tau + coulomb * np.tanh(qd / 0.02)) / gain + 0.02 * rng.standard_normal(tau.shape)
    diag = diagnose(panda, [EstimatorInputs(t, q, qd, tau_m, "synthetic", 0, True)], log=lambda _: None,
                    priors=Priors(torque_measurement="motor_current"))
    gains = [record for record in diag.result["beyond_priors"] if record["effect"] == "drive_gain"]
    assert [record["joint"] for record in gains] == [1]
    assert gains[0]["wanted"] == pytest.approx(0.13, abs=0.01)      # noise-free model: measured 0.130
    assert any("--max-gain-error 0.15" in warning and "panda_joint2" in warning for warning in diag.result["warnings"])
    priors = robot_priors(panda, Priors(torque_measurement="motor_current"))
    for term, theta in zip(diag.terms, diag.theta):
        assert not np.any(at_bounds(term, theta, priors)), term.name
        lo, hi = term.bounds(priors)
        assert np.all((theta >= lo) & (theta <= hi)), term.name
    assert "drive_gain" not in [term.name for term in diag.terms]


def _loaded(robot: RobotModel, body: int, mass: float, com: tuple[float, float, float]) -> pin.Model:
    """``robot``'s model with a point mass at ``com`` (m) in the frame of the flange (``body`` None) or of joint
    ``body``."""
    model = pin.Model(robot.model)
    frame = model.frames[robot.flange_frame_id]
    joint, placement = (frame.parentJoint, frame.placement) if body is None else (body, pin.SE3.Identity())
    model.inertias[joint] += placement.act(pin.Inertia(mass, np.array(com), np.zeros((3, 3))))
    return model


def _calibrated(panda: RobotModel, truth: pin.Model) -> tuple:
    """A Panda calibrated for a 0.2 N·m torque offset on joint 1 (the base augmentation of ``--against``) and the
    training and held-out signals of a motion whose torques are ``truth``'s rigid-body ones with that offset."""
    config = load_config(default_config_path("panda"))
    base = parse_augmentation(yaml.safe_dump({"joint_names": list(config.joint_names), "effects": [
        {"name": "torque_offset", "joint_indices": [0], "theta": [0.2]}]}), config.joint_names)
    calibrated = RobotModel(config.urdf, config.joint_names, config.ee_frame, config.flange_frame, augmentation=base)
    t, q, qd, qdd, _, rng = _motion(panda)
    data = truth.createData()
    tau = np.array([pin.rnea(truth, data, q[k], qd[k], qdd[k]) for k in range(len(t))])
    tau_m = tau - 0.2 * np.eye(7)[0] + 0.02 * rng.standard_normal(tau.shape)   # the drive applies τ_m + 0.2
    segment = EstimatorInputs(t, q, qd, tau_m, "synthetic", 0, True)
    return calibrated, segment, prepare(calibrated, [segment], HOLDOUT)


@pytest.mark.parametrize("body, named, mass", [(None, "payload", 1.0), (4, "link_inertia", 0.5)])
def test_against_a_calibrated_model_a_new_load_at_the_flange_is_a_payload(panda, body, named, mass):
    """Against a calibrated model, link-inertia changes that a payload explains as well are replaced by the payload
    (one body at the flange, the simplest explanation of a new load): a 1 kg mass 5 cm along the flange's z is a
    payload; 0.5 kg more on panda_link4 (14 % of its 3.59 kg, inside link_inertia's prior) is not, and link_inertia
    stays."""
    calibrated, segment, (train, held) = _calibrated(panda, _loaded(panda, body, mass, (0.0, 0.0, 0.05)))
    priors = robot_priors(calibrated, Priors(torque_measurement="commanded_effort"))
    fitter = body_fitter(calibrated, train, held, priors)
    links = [Term("link_inertia", tuple(range(7)))]
    terms, fit = payload_first(fitter, links, consistent(fitter, links, *fitter.fit(links)), panda.joint_names,
                               lambda _: None)
    assert [term.name for term in terms] == [named]
    if named == "payload":
        assert fit[0][0] == pytest.approx(1.0, abs=0.1)      # its mass: measured 1.00 kg on noise-free dynamics
        diag = diagnose(calibrated, [segment], log=lambda _: None, priors=Priors(torque_measurement="commanded_effort"))
        found = [e["name"] for e in diag.result["effects"]]
        assert "payload" in found and "link_inertia" not in found, found


def test_against_a_calibrated_model_only_what_changes_between_runs_is_named(panda):
    """Against a calibrated model the library is what changes between runs of one robot (a load, friction, torque
    offsets): a 1 kg payload seen through drives 5 % weak on joints 2 and 4 is named a payload of 1 kg within 10 %
    (measured 1.00 kg: the two gains pull the mass opposite ways along this motion), and no drive gain is named, the
    robot's construction being calibrated; ``effects`` given, the whole library is searched and the gains named."""
    calibrated, segment, _ = _calibrated(panda, _loaded(panda, None, 1.0, (0.0, 0.0, 0.05)))
    gain = np.array([1.0, 0.95, 1.0, 0.95, 1.0, 1.0, 1.0])
    weak = EstimatorInputs(segment.stamp, segment.q, segment.qd, segment.tau_m / gain, "synthetic", 0, True)
    priors = Priors(torque_measurement="motor_current")
    diag = diagnose(calibrated, [weak], log=lambda _: None, priors=priors)
    assert diag.result["library"] == list(CHANGES_BETWEEN_RUNS)
    assert set(CHANGES_BETWEEN_RUNS) == {"payload", "coulomb_friction", "viscous_friction", "stribeck_friction",
                                         "torque_offset"}
    named = {effect["name"]: effect for effect in diag.result["effects"]}
    assert set(named) <= set(CHANGES_BETWEEN_RUNS) and "payload" in named, list(named)
    assert named["payload"]["parameters"]["mass_change"] == pytest.approx(1.0, rel=0.1)
    whole = diagnose(calibrated, [weak], log=lambda _: None, priors=priors, effects=EFFECT_NAMES)
    assert "drive_gain" in [effect["name"] for effect in whole.result["effects"]]


def test_a_gain_outside_physics_is_never_offered(panda):
    """Joint 7 of a Panda carries 0.4 N·m of Coulomb friction and almost no rigid-body torque: offered only drive gains
    (the library restricted to them, priors of a commanded effort, ±20 %), its gap is read as a gain at the prior's
    bound and, beyond it, as one near zero (the drive applies almost none of τ_m): a joint with no torque, beyond
    physics (|1 − g| ≤ 0.5), so it is not offered. Joint 2's drive applies 0.7 τ_m: 1.5 × the prior, inside physics,
    offered with the flag that allows it."""
    t, q, qd, _, tau, rng = _motion(panda)
    gain = np.ones(7)
    gain[1] = 0.7
    friction = np.zeros(7)
    friction[6] = 0.4
    tau_m = (tau + friction * np.tanh(qd / 0.02)) / gain + 0.02 * rng.standard_normal(tau.shape)
    diag = diagnose(panda, [EstimatorInputs(t, q, qd, tau_m, "synthetic", 0, True)], log=lambda _: None,
                    priors=Priors(torque_measurement="commanded_effort"), effects=("drive_gain",))
    offered = {record["joint"]: record for record in diag.result["beyond_priors"]}
    assert 6 not in offered and 1 in offered
    assert offered[1]["wanted"] == pytest.approx(0.3, abs=0.01)      # noise-free model: measured 0.300
    assert "--max-gain-error 0.35" in diag.result["warnings"][0]
    assert all(record["wanted"] < PHYSICAL_GAIN_ERROR for record in diag.result["beyond_priors"])
    assert not any("panda_joint7" in warning and "needs" in warning for warning in diag.result["warnings"])
