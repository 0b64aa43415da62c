"""The compiled step against the numpy references (reference_filter.py, reference_estimator.py), on the committed
bags and at rest, for every observer.

The kernels (``core/estimation/compiled``) do the reference's arithmetic in the same order, but sums run in
another order than BLAS's, ``exp`` is libm's rather than numpy's and the Cholesky factors are the kernel's rather than
LAPACK's: measured on the bags, τ̂, P, F and Σ_F differ by at most 1.5e-14 of each one's largest value over the bag
(1.6e-13 on the UR5's bench stream, whose heavier links give larger momenta, the rounding of which τ̂ differentiates).
RELATIVE leaves a factor ~70 for another machine's libm and BLAS, and is still ~1e-11 N·m on a 10 N·m torque, far
below any physical meaning. The pinocchio passes are the same calls in both paths, so J and R are equal bit for bit.
The onset detector's sums d_θ = Σ ρν/S and C_θ = Σ ρ²/S (observers/onset.py) divide by innovation variances S far
below the momenta whose difference ν is, so they carry more rounding: measured up to 1.1e-12 (d) and 1.7e-12 (C) of
their largest values on an AMD EPYC, where every estimate stays within RELATIVE. GLR_SUMS leaves a factor ~60 on
those; the alarms they decide are compared exactly.
"""
from __future__ import annotations

import ast
import builtins
import enum
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np
import pytest

from kvark_ros.core.config import load_config
from kvark_ros.core.estimation import compiled
from kvark_ros.core.estimation.augmentation import parse_augmentation
from kvark_ros.core.estimation.calibration import IntervalScale
from kvark_ros.core.estimation.compiled import inputs as input_kernels
from kvark_ros.core.estimation.compiled import jit, kvark_filter, layouts, post, residual, wrench
from kvark_ros.core.estimation.compiled.residual import augmentation_torque, kmp_predict, pack_augmentation
from kvark_ros.core.estimation.estimator import Estimator, Status
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.core.estimation.observers.kvark import KVARKFilter, KVARKMomentumFilter
from kvark_ros.core.estimation.observers.kvark_difference import KVARKDifferenceFilter
from kvark_ros.core.learning.kmp_inputs import fit_kmp, second_inputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.stiction import StictionBand
from kvark_ros.core.learning.training import training_data
from kvark_ros.io.recorded_inputs import read_inputs

from reference_estimator import ReferenceEstimator
from reference_filter import ReferenceMomentumFilter, reference_estimator

ROOT = Path(__file__).resolve().parents[2]
BAGS = ("panda_contact", "panda_collision")
RELATIVE = 1e-12          # of each quantity's largest magnitude over the run (module docstring)
GLR_SUMS = 1e-10          # the onset detector's d and c, of their largest magnitude (module docstring)
SPLIT = 1424              # inside the collision's onset alarms (test_state_transfer.COLLISION_SPLITS)
Q0 = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8])          # rad, a regular pose (test_tare)
BIAS = np.array([1.0, -2.0, 1.5, 3.0, -0.5, 0.8, -0.3])       # N·m the nominal model misses at rest (test_tare)
FIELDS = ("tau_ext", "tau_cov", "wrench", "wrench_cov")
FACTORS = np.linspace(0.5, 3.0, 7)                            # interval factors c (test_interval_calibration)
POSE_INPUTS = ("qd_q", "qd", "qd_g", "qd", "qd_q", "qd", "qd")   # KMP inputs per joint (docs/method.md §3.7)
AUGMENTATION = """
joint_names: [panda_joint1, panda_joint2, panda_joint3, panda_joint4, panda_joint5, panda_joint6, panda_joint7]
effects:
- {name: coulomb_friction, joint_indices: [0, 1, 2, 3, 4, 5, 6], variant: {epsilon: 0.05},
   theta: [0.5, 0.6, 0.4, 0.5, 0.2, 0.2, 0.1]}
- {name: viscous_friction, joint_indices: [1, 3], theta: [0.2, 0.1]}
- {name: stribeck_friction, joint_indices: [0, 2], variant: {stribeck_velocity: 0.1, epsilon: 0.02}, theta: [0.3, 0.4]}
- {name: drive_gain, joint_indices: [1], theta: [0.03]}
- {name: torque_offset, joint_indices: [2, 3], theta: [0.1, -0.2]}
- {name: position_ripple, joint_indices: [0, 5], variant: {cycles_per_rev: 6}, theta: [[0.05, -0.03], [0.02, 0.01]]}
"""


@pytest.fixture(scope="module")
def config():
    return replace(load_config(ROOT / "config" / "panda.yaml"), model_dir=str(ROOT / "models" / "panda"))


@pytest.fixture(scope="module")
def trained(config):
    return load_model(config.model_dir, config.joint_names)


@pytest.fixture(scope="module")
def inputs(config):
    return {bag: read_inputs(ROOT / "bags" / bag, config)[1] for bag in BAGS}


def _run(estimator: Estimator, inputs, start: int = 0, stop: int | None = None) -> list:
    """Estimates (None while warming up) of samples start..stop."""
    rows = range(start, len(inputs.stamp) if stop is None else stop)
    return [estimator.step(inputs.stamp[k], inputs.q[k], inputs.qd[k], inputs.tau_m[k]) for k in rows]


def _assert_equal_to_rounding(reference: list, kernel: list) -> None:
    """The same samples accepted, flags, stamps, J and R; τ̂, P, F, Σ_F within RELATIVE of their largest values."""
    assert [e is None for e in reference] == [e is None for e in kernel]
    pairs = [(a, b) for a, b in zip(reference, kernel) if a is not None]
    assert pairs
    for a, b in pairs:
        assert (a.stamp, a.contact, a.collision, a.wrench_frame) == (b.stamp, b.contact, b.collision, b.wrench_frame)
        assert np.array_equal(a.jacobian, b.jacobian) and np.array_equal(a.ee_rotation, b.ee_rotation)
        assert np.array_equal(a.weak_directions, b.weak_directions) or np.allclose(
            np.abs(a.weak_directions.T @ b.weak_directions), np.eye(a.weak_directions.shape[1]), atol=1e-9)
    for field in FIELDS:
        mine, theirs = (np.array([getattr(e, field) for e in side]) for side in zip(*pairs))
        assert np.abs(mine - theirs).max() <= RELATIVE * np.abs(mine).max(), field


def _assert_states_close(reference: dict, kernel: dict, relative: float = RELATIVE) -> None:
    """Equal keys, shapes and (to ``relative`` of each array's largest entry) values, components included."""
    assert set(reference) == set(kernel)
    for name, value in reference.items():
        other = kernel[name]
        if isinstance(value, dict):
            _assert_states_close(value, other, relative)
        elif isinstance(value, tuple):
            for a, b in zip(value, other):
                assert np.allclose(a, b, rtol=0.0, atol=relative * np.abs(a).max()), name
        elif isinstance(value, np.ndarray):
            assert value.shape == other.shape
            onset_sum = name in ("d", "c") and "alarms" in reference       # the onset detector's state
            tolerance = max(relative, GLR_SUMS) if onset_sum else relative
            assert np.allclose(value, other, rtol=0.0, atol=tolerance * np.abs(value).max()), name
        else:
            assert value == other, name


def _pair(config, trained, observer: str = "kvark") -> tuple[Estimator, Estimator]:
    reference = reference_estimator(config, trained, observer)
    kernel = Estimator.from_config(config, trained, observer)
    assert type(reference) is ReferenceEstimator and type(kernel) is Estimator
    return reference, kernel


@pytest.mark.parametrize("bag", BAGS)
def test_kernel_matches_the_numpy_reference_on_the_bags(config, trained, inputs, bag):
    """Default kvark (window VB, onset detector, KMP inside the kernel): every estimate, the onset alarms, the last
    contact statistic and collision excess, and the final filter state."""
    reference, kernel = _pair(config, trained)
    assert type(reference.observer) is ReferenceMomentumFilter and type(kernel.observer) is KVARKFilter
    _assert_equal_to_rounding(_run(reference, inputs[bag]), _run(kernel, inputs[bag]))
    assert kernel.observer.onset.alarms == reference.observer.onset.alarms > 0
    assert kernel.counts == reference.counts
    assert kernel.contact.statistic == pytest.approx(reference.contact.statistic, rel=RELATIVE)
    assert kernel.collision.excess == pytest.approx(reference.collision.excess, rel=RELATIVE)
    _assert_states_close(reference.observer.state(), kernel.observer.state())


@pytest.mark.parametrize("name, change", [("gmr_gp", {}), ("kmp_kf_nis", {}), ("kf", {}),
                                          ("kvark", {"vb_variant": "paper", "vb_iterations": 3}),
                                          ("kvark", {"vb_variant": "smoothed", "vb_iterations": 2}),
                                          ("kvark", {"vb_window_source": "prior"})])
def test_kernel_matches_the_reference_in_every_variant(config, trained, inputs, name, change):
    """gmr_gp (its GP evaluated in Python and passed in), the ablations kmp_kf_nis (EWMA, NIS-scaled Σ_d) and kf
    (static residual variance), the per-sample VB readings paper and smoothed with several passes, and the window
    read from its twin at Σ_d0 (with the onset detector's corrections on the filter alone)."""
    config = replace(config, filter=replace(config.filter, **change))
    reference, kernel = _pair(config, trained, name)
    _assert_equal_to_rounding(_run(reference, inputs["panda_collision"]), _run(kernel, inputs["panda_collision"]))
    _assert_states_close(reference.observer.state(), kernel.observer.state())


@pytest.fixture(scope="module")
def posed(config, trained, inputs):
    """models/panda with a KMP taking q̇ with q (joints 1, 5) or with g (joint 3), fitted small on the contact bag's
    residuals, and an augmentation with every torque effect (``AUGMENTATION``)."""
    data = training_data(RobotModel.from_config(config), [inputs["panda_contact"]])
    kmp = fit_kmp(data.qd, second_inputs(POSE_INPUTS, data.q, data.g), data.tau_r, POSE_INPUTS, n_components=6,
                  n_support=30)
    return replace(trained, residual=kmp, augmentation=parse_augmentation(AUGMENTATION, config.joint_names))


@pytest.mark.parametrize("model", ["trained", "posed"])
def test_the_model_kernels_equal_their_references(model, inputs, request):
    """``kmp_predict`` (a q̇-only KMP and one with second inputs) and ``augmentation_torque`` against the numpy
    ``KMPResidualModel.predict_batch`` and ``Augmentation.joint_torque`` on the bag's samples and 1 rad(/s) away from
    them: the means and τ_aug to 1e-12 N·m (measured 1e-14), the variances to 1e-10 relative (measured 2e-12:
    σ_f² − ‖W e‖² cancels digits near the data)."""
    kmp = request.getfixturevalue(model).residual
    augmentation = request.getfixturevalue("posed").augmentation
    packed, entries = kmp.compiled.packed, pack_augmentation(augmentation)
    data, rng = inputs["panda_collision"], np.random.default_rng(4)
    mean, var, torque = np.empty(7), np.empty(7), np.empty(7)
    for k in range(0, len(data.stamp), 25):
        q, qd = data.q[k] + rng.normal(scale=0.5, size=7), data.qd[k] + rng.normal(scale=0.5, size=7)
        g = rng.normal(scale=10.0, size=7)
        kmp_predict(qd, q, g, packed, mean, var)
        reference_mean, reference_var = (values[0] for values in kmp.predict_batch(qd[None], q[None], g[None]))
        assert np.abs(mean - reference_mean).max() < 1e-12
        assert np.abs(var / reference_var - 1.0).max() < 1e-10
        assert all(np.array_equal(a, b) for a, b in zip(kmp.predict(qd, q, g), (mean, var)))
        augmentation_torque(q, qd, data.tau_m[k], entries, torque)
        assert np.abs(torque - augmentation.joint_torque(q, qd, data.tau_m[k])).max() < 1e-12


def test_pose_inputs_and_the_augmentation_are_compiled(config, posed, inputs):
    """A KMP with second inputs and a model augmentation run compiled (``compiled.residual``): the same
    estimates as the reference on the collision bag, and the same final state to 1e-10 of each array's largest entry:
    the two-input variances differ by ~2e-12 relative (the test above), which the onset detector's running sums carry
    to 4e-12 of their size (measured), beyond RELATIVE's 1e-12 but 25 × inside this bound."""
    reference, kernel = _pair(config, posed)
    assert kernel.observer.kmp is not None and kernel.robot.augmentation.torque_effects
    _assert_equal_to_rounding(_run(reference, inputs["panda_collision"]), _run(kernel, inputs["panda_collision"]))
    _assert_states_close(reference.observer.state(), kernel.observer.state(), relative=1e-10)


def test_end_effector_axes_the_static_friction_band_and_the_interval_factors(config, trained, inputs):
    """wrench.frame end_effector (the kernel rotates F and Σ_F), a model with a 2 N·m static band on every joint
    (Cov τ̂ and the contact test widen, the collision test does not) and interval factors with a floor (the reported
    Cov τ̂ and Σ_F scale, the tests do not)."""
    config = replace(config, wrench=replace(config.wrench, frame="end_effector"))
    floor = np.linspace(0.0, 0.05, 7)                     # N²·m²: above c² P on some joints and samples, not all
    banded = replace(trained, stiction=StictionBand(np.full(7, 2.0)), interval_scale=IntervalScale(FACTORS, floor))
    reference, kernel = _pair(config, banded)
    _assert_equal_to_rounding(_run(reference, inputs["panda_collision"]), _run(kernel, inputs["panda_collision"]))


def test_the_contact_test_on_the_reported_covariance(config, trained, inputs):
    """contact.test_covariance reported (band, factors and floor as above): the kernel equals the reference, its
    contact statistic is τ̂ᵀ Σ⁻¹ τ̂ with Σ the reported Cov τ̂ of the same sample (docs/method.md §7.2; diagonal here),
    and the collision test keeps P + σ²_r: its excess equals the one of a run on the residual S."""
    reported = replace(config, contact=replace(config.contact, test_covariance="reported"))
    banded = replace(trained, stiction=StictionBand(np.full(7, 2.0)),
                     interval_scale=IntervalScale(FACTORS, np.linspace(0.0, 0.05, 7)))
    data = inputs["panda_collision"]
    reference, kernel = _pair(reported, banded)
    runs = _run(reference, data), _run(kernel, data)
    _assert_equal_to_rounding(*runs)
    last = next(e for e in reversed(runs[1]) if e is not None)
    assert kernel.contact.statistic == pytest.approx(float(last.tau_ext @ np.linalg.solve(last.tau_cov, last.tau_ext)),
                                                     rel=1e-12)
    residual = Estimator.from_config(config, banded, "kvark")
    _run(residual, data)
    assert residual.collision.excess == kernel.collision.excess
    assert residual.contact.statistic < kernel.contact.statistic       # σ²_r widens S: the residual test is slower


def test_tare_at_rest(config, trained):
    """A tare averaged at rest (test_tare's scenario: τ_m = g(q0) − BIAS) runs the kernel in two calls around the
    averaging; the estimates before, during and after it and the offset equal the reference's."""
    tau_m = RobotModel.from_config(config).gravity(Q0) - BIAS
    reference, kernel = _pair(config, trained)
    runs = []
    for estimator in (reference, kernel):
        estimates = []
        for k in range(1200):
            if k == 500:
                estimator.start_tare()
            estimates.append(estimator.step(0.002 * k, Q0, np.zeros(7), tau_m))
        runs.append(estimates)
    _assert_equal_to_rounding(*runs)
    assert kernel.tare.state == reference.tare.state == "active" and kernel.tare.samples == reference.tare.samples
    assert np.allclose(kernel.tare.offset, reference.tare.offset, rtol=0.0, atol=RELATIVE * 3.0)   # |BIAS| ≤ 3


def test_runtime_keys_reach_the_kernel(config, trained, inputs):
    """Run-time keys changed through Estimator.configure mid-run act in the kernel as in the reference."""
    data = inputs["panda_collision"]
    floor = np.full(7, 0.05)                                 # N²·m²: above c² P on some joints and samples
    reference, kernel = _pair(config, replace(trained, interval_scale=IntervalScale(FACTORS, floor)))
    first = _run(reference, data, 0, 500), _run(kernel, data, 0, 500)
    for estimator in (reference, kernel):                    # the floor switched off mid-run, then the factors
        estimator.configure(replace(estimator.config, filter=replace(estimator.config.filter, interval_floor="off")))
    unfloored = _run(reference, data, 500, 1000), _run(kernel, data, 500, 1000)
    variances = [[e.tau_cov[j, j] for e in run if e is not None for j in range(7)] for run in (first[1], unfloored[1])]
    assert min(variances[0]) >= 0.05 - 1e-12 and min(variances[1]) < 0.05     # floored, then not
    for estimator in (reference, kernel):
        changed = estimator.config
        changed = replace(changed, filter=replace(changed.filter, ewma_time=0.05, stiction_velocity=0.1,
                                                  interval_calibration="off"),
                          wrench=replace(changed.wrench, damping=0.1, frame="end_effector"),
                          contact=replace(changed.contact, confidence=0.95, collision_torque=4.0))
        estimator.configure(changed)
    second = _run(reference, data, 1000), _run(kernel, data, 1000)
    _assert_equal_to_rounding(*first)
    _assert_equal_to_rounding(*unfloored)
    _assert_equal_to_rounding(*second)
    assert kernel.observer.ewma_rate == reference.observer.ewma_rate == pytest.approx(0.002 / 0.05)
    assert any(e.collision for e in second[0] if e is not None)


@pytest.mark.parametrize("frame", ["base", "end_effector"])
def test_weak_directions_and_the_damping_bias(config, trained, frame):
    """At the stretched Panda (q = 0: σ₆ = 0, test/ros/test_wrench_near_singular_poses.py) J Jᵀ − δ² I is not positive
    definite: the kernel's weak_wrench gives the reference's weak direction (to its sign, which an SVD leaves open), F
    and Σ_F with the damping bias, in either axes."""
    q = np.zeros(7)
    tau_m = RobotModel.from_config(config).gravity(q) + 0.5
    reference, kernel = _pair(replace(config, wrench=replace(config.wrench, frame=frame)), trained)
    runs = [[estimator.step(0.002 * k, q, np.zeros(7), tau_m) for k in range(50)] for estimator in (reference, kernel)]
    _assert_equal_to_rounding(*runs)
    assert runs[1][-1].weak_directions.shape == (6, 1)
    assert kernel.unobservable_samples == reference.unobservable_samples == 49


def test_rejections_and_restarts(config, trained):
    """Bad samples, a stamp out of order and a long gap give the reference's statuses, counts and estimates."""
    q, qd, tau = Q0, np.zeros(7), np.ones(7)   # at rest: a constant state is consistent
    bad = q.copy()
    bad[3] = np.nan
    samples = [(0.0, q, qd, tau), (0.002, q, qd, tau), (0.004, bad, qd, tau), (0.004, q, qd, np.full(7, np.inf)),
               (0.002, q, qd, tau), (0.004, q[:6], qd, tau), (0.004, q, qd, tau), (0.006, q, qd, tau),
               (1.0, q, qd, tau), (1.002, q, qd, tau), (1.004, q, qd, 1e160 * tau), (1.006, q, qd, tau)]
    reference, kernel = _pair(config, trained)
    runs, statuses = [], []
    for estimator in (reference, kernel):
        runs.append([estimator.step(*sample) for sample in samples])
        statuses.append(estimator.status)
    _assert_equal_to_rounding(*runs)
    assert kernel.counts == reference.counts and statuses[0] == statuses[1] == Status.OK
    assert kernel.counts[Status.NON_FINITE] == 3 and kernel.counts[Status.GAP_RESET] == 1


def test_state_transfer_continues_bit_for_bit(config, trained, inputs):
    """continue_from between two kernel estimators, inside the collision's onset alarms, changes no output."""
    data = inputs["panda_collision"]
    whole = _run(Estimator.from_config(config, trained, "kvark"), data)
    old = Estimator.from_config(config, trained, "kvark")
    _run(old, data, 0, SPLIT)
    new = Estimator.from_config(config, trained, "kvark")
    new.continue_from(old)
    for a, b in zip(whole[SPLIT:], _run(new, data, SPLIT)):
        assert (a is None) == (b is None)
        if a is not None:
            assert all(np.array_equal(getattr(a, field), getattr(b, field)) for field in FIELDS)
            assert (a.contact, a.collision) == (b.contact, b.collision)
    assert new.observer.onset.alarms > 0


def test_estimates_are_snapshots(config, trained, inputs):
    """Every estimate holds its own arrays: later steps neither change them nor share their memory."""
    data = inputs["panda_contact"]
    kernel = Estimator.from_config(config, trained, "kvark")
    estimates = [e for e in _run(kernel, data, 0, 20) if e is not None]
    copies = [{field: getattr(e, field).copy() for field in FIELDS} for e in estimates]
    _run(kernel, data, 20, 40)
    for estimate, copy in zip(estimates, copies):
        assert all(np.array_equal(getattr(estimate, field), copy[field]) for field in FIELDS)
    first, second = estimates[-2:]
    assert not any(np.shares_memory(getattr(first, a), getattr(second, b)) for a in FIELDS for b in FIELDS)


OTHER_OBSERVERS = ("momentum", "kfmo", "sh_akfmo", "vbkfmo_q", "eso")


@pytest.mark.parametrize("name", OTHER_OBSERVERS)
def test_every_observer_gets_the_compiled_post_step(config, trained, inputs, name):
    """The residual-free observers (no covariance for momentum and eso: the contact test adds the trained KMP's
    μ_r² + σ²_r, the collision test takes σ = 0 without it) step in numpy between the compiled step's two calls; every
    estimate equals the reference's numpy post-step to rounding, with a static band and interval factors (which
    apply to kvark only) in the model."""
    banded = replace(trained, stiction=StictionBand(np.full(7, 2.0)),
                     interval_scale=IntervalScale(FACTORS, np.linspace(0.0, 0.05, 7)))
    reference, kernel = _pair(replace(config, wrench=replace(config.wrench, frame="end_effector")), banded, name)
    runs = _run(reference, inputs["panda_collision"]), _run(kernel, inputs["panda_collision"])
    for field in ("tau_cov", "wrench_cov"):
        covariances = {getattr(e, field) is None for run in runs for e in run if e is not None}
        assert covariances == {not kernel.observer.reports_covariance}
    if kernel.observer.reports_covariance:
        _assert_equal_to_rounding(*runs)
    else:
        _assert_equal_to_rounding([_without_covariance(e) for e in runs[0]], [_without_covariance(e) for e in runs[1]])
    assert kernel.contact.invalid_covariances == reference.contact.invalid_covariances == 0
    assert kernel.contact.statistic == pytest.approx(reference.contact.statistic, rel=RELATIVE)
    assert kernel.collision.excess == pytest.approx(reference.collision.excess, rel=RELATIVE)


def test_an_observer_without_covariance_or_residual_is_not_tested_for_contact(config, inputs):
    """Without a trained model the contact test has no S for ``momentum`` (no P, no residual): its flag stays as it
    was, nothing is counted invalid, and the collision excess is max_j |τ̂_j| (σ = 0)."""
    robot = RobotModel.from_config(config)
    kernel = Estimator(config, robot, make_observer("momentum", load_model(config.model_dir, config.joint_names),
                                                    config.filter))
    estimates = [e for e in _run(kernel, inputs["panda_collision"]) if e is not None]
    assert not any(e.contact for e in estimates) and kernel.contact.invalid_covariances == 0
    assert math.isnan(kernel.contact.statistic)
    assert kernel.collision.excess == pytest.approx(float(np.abs(estimates[-1].tau_ext).max()), rel=1e-15)


def test_the_difference_form_gets_the_compiled_post_step_of_a_full_covariance(config, trained, inputs):
    """The difference form is the numpy ``KVARKDifferenceFilter`` (its VB couples the joints: P is full); the compiled
    post-step takes its full P (scaled by the interval factors: it reports as kvark) and equals the reference's."""
    settings = replace(config.filter, measurement="difference", vb_variant="paper")
    assert type(make_observer("kvark", trained, settings)) is KVARKDifferenceFilter
    banded = replace(trained, stiction=StictionBand(np.full(7, 2.0)),
                     interval_scale=IntervalScale(FACTORS, np.linspace(0.0, 0.05, 7)))
    reference, kernel = _pair(replace(config, filter=settings), banded)
    runs = _run(reference, inputs["panda_collision"]), _run(kernel, inputs["panda_collision"])
    last = next(e for e in reversed(runs[1]) if e is not None)
    assert np.abs(last.tau_cov - np.diag(np.diagonal(last.tau_cov))).max() > 0.0      # P is full
    _assert_equal_to_rounding(*runs)


def _without_covariance(estimate):
    return None if estimate is None else estimate._replace(tau_cov=np.zeros(1), wrench_cov=np.zeros(1))


@pytest.mark.parametrize("name", ["kvark", "kf", "kmp_kf", "kmp_kf_ewma", "kmp_kf_nis", "gmr_gp"])
def test_the_momentum_form_is_only_ever_the_compiled_filter(config, trained, name):
    """make_observer builds every momentum-form K-VARK filter compiled; the base class, which holds the settings
    and state but has no step, cannot be built at all."""
    observer = make_observer(name, trained, config.filter)
    assert type(observer) is KVARKFilter
    with pytest.raises(TypeError, match="abstract"):
        KVARKMomentumFilter("kvark", observer.residual, observer.tuning, observer.noise, config.filter)


KERNEL_MODULES = (input_kernels, residual, kvark_filter, wrench, post)


@pytest.mark.parametrize("model", ["trained", "posed"])
def test_nothing_compiles_after_construction(config, inputs, model, request):
    """The kernels compile (or load from the cache) when the estimator is built, never while it steps."""
    kernel = Estimator.from_config(config, request.getfixturevalue(model), "kvark")
    dispatchers = [value for module in KERNEL_MODULES for value in vars(module).values()
                   if isinstance(value, numba.core.dispatcher.Dispatcher)]
    before = {dispatcher: len(dispatcher.signatures) for dispatcher in dispatchers}
    _run(kernel, inputs["panda_contact"])
    assert {dispatcher: len(dispatcher.signatures) for dispatcher in dispatchers} == before


def test_every_kernel_file_pins_what_its_kernels_read():
    """numba's cache is keyed on a kernel's own file alone (``compiled.jit``), so every global a kernel reads is
    defined in its file (or is numba, numpy, math or a builtin), or comes from a file its ``PINS`` name with that
    file's current sha256: a layout of ``layouts`` (an enum whose members the kernels read as constants) or a kernel
    of another kernel file. No other module's function or constant can go stale in the cache."""
    here = Path(compiled.__file__).parent
    files = sorted(path.name for path in here.glob("*.py") if "@jit" in path.read_text())
    assert files == sorted(f"{module.__name__.rsplit('.', 1)[1]}.py" for module in KERNEL_MODULES)
    stale = {module.__name__: {name: jit.digest(name) for name in module.PINS if module.PINS[name] != jit.digest(name)}
             for module in KERNEL_MODULES}
    assert not any(stale.values()), f"update PINS to these digests: {stale}"
    for module in KERNEL_MODULES:
        pinned = [vars(compiled)[name[:-3]] if name != "layouts.py" else layouts for name in module.PINS]
        tree = ast.parse(Path(module.__file__).read_text())
        defined = {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}
        defined |= {target.id for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign))
                    for target in ast.walk(node) if isinstance(target, ast.Name) and isinstance(target.ctx, ast.Store)}
        allowed = {"np", "math", "numba"} | set(vars(builtins))
        kernels = [value for value in vars(module).values() if isinstance(value, numba.core.dispatcher.Dispatcher)
                   and value.py_func.__module__ == module.__name__]
        assert kernels, module.__name__
        for kernel in kernels:
            read = {name for name in kernel.py_func.__code__.co_names if name in vars(module)}
            for name in read - defined - allowed:
                value = vars(module)[name]
                source = next((other for other in pinned if getattr(other, name, None) is value), None)
                assert source is not None, (module.__name__, kernel.py_func.__name__, name)
                assert isinstance(value, (numba.core.dispatcher.Dispatcher, enum.EnumMeta, int)), (name, value)


def test_kernels_import_without_a_writable_cache():
    """With no cache directory numba can use (here: only the zip-file locator, which applies to none of our files)
    the kernels compile without the cache instead of failing at import."""
    environment = dict(os.environ, NUMBA_CACHE_LOCATOR_CLASSES="ZipCacheLocator")
    code = ("from kvark_ros.core.estimation.compiled import post\n"
            "assert type(post.estimate_step._cache).__name__ == 'NullCache'\n")
    subprocess.run([sys.executable, "-c", code], check=True, env=environment, cwd=ROOT, timeout=120)
