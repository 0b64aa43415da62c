"""Stiction-aware intervals (issue 17): a joint at rest holds any friction in its static band, so its interval
widens to that band, the estimate does not change, and a sticking joint does not flag contact."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.stiction import StictionBand
from kvark_ros.core.learning.static_band import identify_band

Q0 = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8])
BAND = 2.0        # N·m, a UR-sized static friction band on every joint


def test_the_band_is_half_the_jump_of_the_friction_across_zero():
    """Coulomb F tanh(q̇/3 mrad/s) + viscous 0.3 q̇ + noise: the band is F to 0.05 N·m (the viscous part adds
    0.3 × ~0.025 rad/s = 0.008 N·m at the slow window's median speed; the noise's median error over ~600
    samples a side is ~0.003). A smooth friction without a jump gives a small band; a joint with nothing
    slower than 0.32 rad/s, none."""
    rng = np.random.default_rng(0)
    qd = rng.uniform(-1.0, 1.0, (40_000, 3))
    coulomb = np.array([0.5, 2.0, 4.0])
    friction = coulomb * np.tanh(qd / 0.003) + 0.3 * qd + 0.05 * rng.standard_normal(qd.shape)
    friction[:, 2] = 0.3 * qd[:, 2]                                   # viscous only: no static friction
    band = identify_band(qd, friction)
    assert band[:2] == pytest.approx(coulomb[:2], abs=0.05)
    assert band[2] < 0.03
    fast = np.sign(qd) * (0.9 + 0.1 * np.abs(qd))                     # nothing slides slower than 0.9 rad/s
    assert identify_band(fast, friction)[:2] == pytest.approx([0.0, 0.0])
    sparse = np.where(np.abs(qd) < 0.15, 0.15 * np.sign(qd), qd)      # the window must double to 0.16 rad/s
    assert identify_band(sparse, friction)[:2] == pytest.approx(coulomb[:2], abs=0.15)


@pytest.fixture(scope="module")
def estimators(panda_config, panda_trained):
    """A model whose static friction band is BAND on every joint, with the band on and off."""
    trained = replace(panda_trained, stiction=StictionBand(np.full(7, BAND)))
    off = replace(panda_config, filter=replace(panda_config.filter, stiction_velocity=0.0))
    return lambda: (Estimator.from_config(panda_config, trained), Estimator.from_config(off, trained))


def _run(estimator, tau_m: np.ndarray, qd: np.ndarray, samples: int = 400):
    estimates = [estimator.step(0.002 * k, Q0 + qd * 0.002 * k, qd, tau_m) for k in range(samples)]
    return [e for e in estimates if e is not None]


def test_at_rest_the_interval_widens_to_the_band_and_the_estimate_stays(estimators, panda_config):
    """At rest Cov τ̂ gains exactly F_s²/3 on the diagonal; τ̂ is the same to the bit; sliding at 0.3 rad/s
    (6 v_s) the widening is exp(−36) F_s²/3 ≈ 3e-16 N²·m², nothing."""
    gravity = RobotModel.from_config(panda_config).gravity(Q0)
    widened, plain = estimators()
    for a, b in zip(_run(widened, gravity, np.zeros(7)), _run(plain, gravity, np.zeros(7))):
        assert np.array_equal(a.tau_ext, b.tau_ext)
        assert np.diag(a.tau_cov) - np.diag(b.tau_cov) == pytest.approx(np.full(7, BAND ** 2 / 3), rel=1e-9)
    widened, plain = estimators()
    sliding = np.full(7, 0.3)
    a, b = _run(widened, gravity, sliding, 50)[-1], _run(plain, gravity, sliding, 50)[-1]
    assert np.array_equal(a.tau_ext, b.tau_ext) and np.allclose(a.tau_cov, b.tau_cov, rtol=0, atol=1e-12)


def test_a_sticking_joint_does_not_flag_contact_and_a_push_still_does(estimators, panda_config):
    """A joint stuck with 1.5 N·m of friction (inside its 2 N·m band) reads like 1.5 N·m of external torque:
    without the band the contact test flags it, with the band it does not; 8 N·m (4× the band) still flags,
    within the 20 ms debounce plus a few samples."""
    gravity = RobotModel.from_config(panda_config).gravity(Q0)
    stuck = gravity - np.array([1.5, 0, 0, 0, 0, 0, 0])
    widened, plain = estimators()
    assert any(e.contact for e in _run(plain, stuck, np.zeros(7)))
    assert not any(e.contact for e in _run(widened, stuck, np.zeros(7)))
    widened, _ = estimators()
    pushed = gravity - np.array([8.0, 0, 0, 0, 0, 0, 0])
    flags = [e.contact for e in _run(widened, pushed, np.zeros(7), 100)]
    assert any(flags[:30])


def test_the_collision_flag_is_not_delayed_by_the_band(panda_config, panda_trained):
    """A 30 N·m hit on a joint at rest whose static band is 20 N·m: the contact test, widened by F_s²/3 (σ_s
    11.5 N·m), would wait; the collision flag (10 N·m threshold here, below the hit) rises on the same sample with
    and without the band, because it keeps the unwidened σ."""
    config = replace(panda_config, contact=replace(panda_config.contact, collision_torque=10.0))
    off = replace(config, filter=replace(config.filter, stiction_velocity=0.0))
    trained = replace(panda_trained, stiction=StictionBand(np.full(7, 20.0)))
    gravity = RobotModel.from_config(panda_config).gravity(Q0)
    hit = gravity - np.array([0.0, 30.0, 0, 0, 0, 0, 0])
    firsts = []
    for settings in (config, off):
        estimator = Estimator.from_config(settings, trained)
        _run(estimator, gravity, np.zeros(7), 200)
        flags = [estimator.step(0.4 + 0.002 * k, Q0, np.zeros(7), hit).collision for k in range(1, 100)]
        firsts.append(flags.index(True))
    assert firsts[0] == firsts[1]


def test_training_reads_the_static_level_through_the_short_filter(panda):
    """A Panda swinging every joint through slow reversals with Stribeck friction (sliding 1.0, static 1.4 N·m,
    v_s 0.05 rad/s) and no other model error: the band read through the 50 ms filter is the static level to 8 %
    (the window's median speed, ~0.025 rad/s, is where the curve has fallen 1 − exp(−0.25) ≈ 22 % of the way
    to sliding, and the filter's edge rounds it), while the residual model's 150 ms filter reads it lower where
    the reversal is quick: on joints 4-7 (0.24-0.3 Hz swings), 43-82 % of the short reading."""
    from kvark_ros.core.estimation.inputs import EstimatorInputs
    from kvark_ros.core.learning.training import band_friction, training_data
    t = np.arange(0.0, 12.0, 0.002)
    omega = 2 * np.pi * np.linspace(0.15, 0.3, 7)
    q = Q0 + 0.4 * np.sin(np.outer(t, omega))
    qd = 0.4 * omega * np.cos(np.outer(t, omega))
    qdd = -0.4 * omega ** 2 * np.sin(np.outer(t, omega))
    friction = (1.0 + 0.4 * np.exp(-np.square(qd / 0.05))) * np.tanh(qd / 0.002)
    tau_m = np.array([panda.inverse_dynamics(a, b, c) for a, b, c in zip(q, qd, qdd)]) + friction
    data = training_data(panda, [EstimatorInputs(t, q, qd, tau_m, "test", 0)])
    short = identify_band(qd, band_friction(panda, data))
    long = identify_band(qd, data.tau_r)
    assert short == pytest.approx(np.full(7, 1.4), rel=0.08)
    assert np.all(long[3:] < 0.85 * short[3:])
