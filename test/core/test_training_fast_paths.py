"""The fast paths of training compute what the slow ones computed (issue 16, fast training).

* λ₂ calibration from one eigendecomposition per joint against a KMP model per candidate (docs/method.md §3.5);
* per-joint fits in worker processes against the same fits one after the other (bit for bit);
* the GP hyperparameter fit (``gp_fit``) against scikit-learn's GaussianProcessRegressor.

No timing is asserted: speed is reported from commands, not tested.
"""
from __future__ import annotations

import warnings
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.residual import GMRGPResidualModel, MLPResidualModel, SparseGPResidualModel
from kvark_ros.core.estimation.residual.common import joint_workers
from kvark_ros.core.estimation.residual.gp_fit import _GroupedData, fit_gp
from kvark_ros.core.learning.kmp_inputs import fit_kmp, second_inputs
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import (HOLDOUT, LAMBDA2_GRID, N_COMPONENTS, calibrate_lambda2, train_model,
                                              training_data)
from kvark_ros.io.recorded_inputs import load_recordings

ROOT = Path(__file__).resolve().parents[2]
BAGS = [str(ROOT / "bags" / "panda_excitation_1"), str(ROOT / "bags" / "panda_excitation_2")]
# The committed bags' choice (kvark train --residual-inputs auto): joints 5 and 7 take the gravity torque.
KINDS = ("qd", "qd", "qd", "qd", "qd_g", "qd", "qd_g")


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_config(load_config(ROOT / "config" / "panda.yaml"), None)


@pytest.fixture(scope="module")
def segments() -> list[EstimatorInputs]:
    return load_recordings(BAGS, load_config(ROOT / "config" / "panda.yaml"), "train")


@pytest.fixture(scope="module")
def workers():
    """Two worker processes, whatever the machine's core count."""
    with joint_workers(2, 7) as executor:
        yield executor


def _model_arrays(model) -> dict[str, np.ndarray]:
    arrays = {key: getattr(model.reference, key) for key in ("s", "mu", "sigma2", "s2")}
    arrays.update({key: getattr(model.hyper, key) for key in ("length_scale", "sigma_f2", "lambda1", "lambda2",
                                                              "length_scale2")})
    return arrays


def test_lambda2_sweep_equals_a_model_per_candidate_on_the_committed_bags(robot, segments) -> None:
    """The final KMP of the committed bags (their input choice, the random 80/20 split of train_model): for every
    λ₂ of the grid the sweep's mean is the model's bit for bit, its variance agrees to 10⁻⁹ of the scale N σ_f²/λ₂
    of eq. 23 (which cancels σ_f² against k_*ᵀ(𝒦 + λ₂Σ)⁻¹k_* to 10⁻⁶ of it at λ₂ = 10⁻², so a relative bound on
    the variance itself would test the Cholesky form's rounding, 1e-7 there; measured 9e-13 of the scale), and
    every candidate covers the same held-out samples, so the calibrated λ₂ and its coverage are the same."""
    data = training_data(robot, segments)
    held = np.random.default_rng(0).random(len(data.qd)) < HOLDOUT
    z = second_inputs(KINDS, data.q, data.g)
    model = fit_kmp(data.qd[~held], z[~held], data.tau_r[~held], KINDS, N_COMPONENTS, 80, seed=0)
    qd, tau, q, g = data.qd[held], data.tau_r[held], data.q[held], data.g[held]
    sweep = list(model.lambda2_sweep(qd, q, g, LAMBDA2_GRID))
    sweep_mean = np.concatenate([mean for _, mean, _ in sweep])
    sweep_var = np.concatenate([var for _, _, var in sweep], axis=1)
    coverage = np.empty((len(LAMBDA2_GRID), model.n_joints))
    for index, lambda2 in enumerate(LAMBDA2_GRID):
        candidate = model.with_hyperparameters(replace(model.hyper, lambda2=np.full(7, lambda2)))
        mean, var = candidate.predict_batch(qd, q, g)
        np.testing.assert_array_equal(sweep_mean, mean)
        scale = model.n_support * model.hyper.sigma_f2 / lambda2
        assert np.all(np.abs(sweep_var[index] - var) <= 1e-9 * scale), index
        np.testing.assert_array_equal(np.abs(tau - mean) <= 1.96 * np.sqrt(sweep_var[index]),
                                      np.abs(tau - mean) <= 1.96 * np.sqrt(var))
        coverage[index] = np.mean(np.abs(tau - mean) <= 1.96 * np.sqrt(var), axis=0)
    best = np.argmin(np.abs(coverage - 0.95), axis=0)
    calibrated, calibrated_coverage = calibrate_lambda2(model, qd, tau, q, g)
    np.testing.assert_array_equal(calibrated.hyper.lambda2, LAMBDA2_GRID[best])
    np.testing.assert_array_equal(calibrated_coverage, coverage[best, np.arange(7)])


def test_kmp_fits_in_workers_equal_the_fits_here(segments, robot, workers) -> None:
    """Both kinds of joint (q̇ alone: GMR + GP on its samples; q̇ with g: k-means, GMR, ARD GP) on the bags."""
    data = training_data(robot, segments)
    rows = slice(0, None, 3)             # a third of the samples keeps the fits short
    z = second_inputs(KINDS, data.q, data.g)
    here = fit_kmp(data.qd[rows], z[rows], data.tau_r[rows], KINDS, N_COMPONENTS, 80, seed=2)
    there = fit_kmp(data.qd[rows], z[rows], data.tau_r[rows], KINDS, N_COMPONENTS, 80, seed=2, executor=workers)
    assert here.inputs == there.inputs
    for key, value in _model_arrays(here).items():
        np.testing.assert_array_equal(value, _model_arrays(there)[key], err_msg=key)


def test_baseline_fits_in_workers_equal_the_fits_here(workers) -> None:
    """GMR-GP, sparse GP and MLP with light settings: predictions and fit records equal bit for bit."""
    rng = np.random.default_rng(4)
    qd = rng.uniform(-1.5, 1.5, (1200, 3))
    tau = 0.4 * np.tanh(15.0 * qd) + 0.1 * qd + 0.03 * rng.standard_normal(qd.shape)
    fits = {"gmr_gp": lambda **kw: GMRGPResidualModel.fit(qd, tau, n_support=20, samples_per_support=3, **kw),
            "gpadkf": lambda **kw: SparseGPResidualModel.fit(qd, tau, n_inducing=15, n_hyper_subset=200, **kw),
            "nnadkf": lambda **kw: MLPResidualModel.fit(qd, tau, max_epochs=15, batch_size=128, **kw)}
    for name, fit in fits.items():
        here, there = fit(seed=1), fit(seed=1, executor=workers)
        for a, b in zip(here.predict_batch(qd[:200]), there.predict_batch(qd[:200])):
            np.testing.assert_array_equal(a, b, err_msg=name)
        assert here.metadata == there.metadata, name


def test_train_model_with_workers_is_the_sequential_model_bit_for_bit(robot, segments) -> None:
    """Input selection, final KMP, λ₂ and filter tuning on the first 1 s of each committed bag (500 samples, 25 per
    GMM component: enough for every fit, and the selection still gives joints of both kinds, q̇ alone and q̇ with a
    pose input; 2 s took 1.2 × as long)."""
    short = [replace(seg, stamp=seg.stamp[:500], q=seg.q[:500], qd=seg.qd[:500], tau_m=seg.tau_m[:500])
             for seg in segments]
    one = train_model(robot, "panda", short, baselines=False, log=lambda _line: None, jobs=1)
    two = train_model(robot, "panda", short, baselines=False, log=lambda _line: None, jobs=2)
    assert one.residual.inputs == two.residual.inputs and {"qd"} < set(one.residual.inputs)     # both kinds
    for key, value in _model_arrays(one.residual).items():
        np.testing.assert_array_equal(value, _model_arrays(two.residual)[key], err_msg=key)
    for field in fields(one.tuning):
        np.testing.assert_array_equal(getattr(one.tuning, field.name), getattr(two.tuning, field.name))
    drop = {"training_seconds"}
    assert {k: v for k, v in one.info.items() if k not in drop} == {k: v for k, v in two.info.items() if k not in drop}


def _sklearn_cases() -> list[tuple]:
    rng = np.random.default_rng(0)
    support = np.repeat(np.linspace(-1.0, 1.0, 30), 8)[:, None]          # GMR samples: 8 per support point
    repeated = np.tanh(5.0 * support[:, 0]) + 0.1 * rng.standard_normal(len(support))
    two_d = rng.standard_normal((300, 2))
    smooth = np.sin(two_d[:, 0]) * np.cos(0.3 * two_d[:, 1]) + 0.1 * rng.standard_normal(300)
    se = ConstantKernel(1.0, (1e-4, 1e4)) * RBF(0.2, (0.05, 20.0)) + WhiteKernel(1e-2, (1e-8, 10.0))
    ard = ConstantKernel(1.0, (1e-4, 1e2)) * RBF(np.ones(2), (0.05, 20.0)) + WhiteKernel(1e-2, (1e-6, 10.0))
    return [(support, repeated, se, 2), (two_d, smooth, ard, 0)]


@pytest.mark.parametrize("case", range(2), ids=["repeated inputs, restarts", "two inputs (ARD)"])
def test_gp_fit_is_scikit_learns_gaussian_process_fit(case) -> None:
    """Same objective: log marginal likelihood and gradient equal scikit-learn's to 1e-9 relative at the start and at
    a displaced point (measured ≤ 1e-13 and ≤ 1e-11; the grouped form of repeated inputs is exact, the rest is
    rounding). Same fit: L-BFGS-B from the same starts reaches the same optimum, hyperparameters to 1e-5 relative
    and the likelihood to 1e-6 nats (measured 1e-9 and 1e-10; both paths stop within L-BFGS-B's tolerance)."""
    x, y, kernel, restarts = _sklearn_cases()[case]
    gpr = GaussianProcessRegressor(kernel=kernel, alpha=1e-10, n_restarts_optimizer=restarts, random_state=3)
    fixed = GaussianProcessRegressor(kernel=kernel, alpha=1e-10, optimizer=None).fit(x, y)   # the data, no fit
    data = _GroupedData(x, y)
    for theta in (kernel.theta, kernel.theta + np.linspace(-0.7, 0.9, len(kernel.theta))):
        want, want_gradient = fixed.log_marginal_likelihood(theta, eval_gradient=True)
        value, gradient = data.log_marginal_likelihood(theta)
        np.testing.assert_allclose(value, want, rtol=1e-9)
        np.testing.assert_allclose(gradient, want_gradient, rtol=1e-9, atol=1e-9 * np.abs(want_gradient).max())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)      # a length scale at its bound, expected
        gpr.fit(x, y)
    fit = fit_gp(x, y, kernel.theta, kernel.bounds, restarts, 3)
    np.testing.assert_allclose([fit.sigma_f2, *fit.length_scale, fit.noise_var], np.exp(gpr.kernel_.theta), rtol=1e-5)
    np.testing.assert_allclose(fit.log_marginal_likelihood, gpr.log_marginal_likelihood_value_, atol=1e-6)

