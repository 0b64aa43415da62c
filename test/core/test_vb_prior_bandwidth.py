"""The VB variants' free-motion prior bandwidth (``filter.prior_bandwidth``, docs/method.md §4.12)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise, torque_density_for_bandwidth
from kvark_ros.core.learning.training import train_model
from kvark_ros.tools.synthetic import step_torque, synthetic_stream

STEP_JOINT, STEP_SIZE, STEP_AT = 1, 5.0, 3.0          # 5 N·m on joint 2 at t = 3 s
TORQUE_NOISE = 2.0                                    # N·m per sample at 500 Hz (q_p ≈ 0.008 N²·m²·s)
MISFIT_STD, MISFIT_TIME = 0.3, 0.03                   # coloured torque the residual model cannot know: N·m, s


def _settings(config, bandwidth: float):
    return replace(config, filter=replace(config.filter, prior_bandwidth=bandwidth))


def test_vb_variants_take_the_prior_bandwidth_and_fixed_ones_keep_the_trained_density(panda_config, panda_trained):
    noise = panda_trained.momentum_noise
    expected = torque_density_for_bandwidth(noise.momentum_variance, noise.model_density,
                                            panda_trained.sample_period, 12.0)
    config = _settings(panda_config, 12.0)
    kvark = make_observer("kvark", panda_trained, config.filter)
    np.testing.assert_allclose(kvark.q_tau, expected, rtol=1e-12)
    np.testing.assert_allclose(kvark.window.q0, expected, rtol=1e-12)      # the windowed VB's prior mean too
    for fixed in ("kf", "kmp_kf_nis"):
        np.testing.assert_array_equal(make_observer(fixed, panda_trained, config.filter).q_tau, noise.torque_density)


def test_with_bandwidth_follows_the_training_rule_and_refuses_a_non_positive_one():
    noise = MomentumNoise(np.array([1e-6, 4e-6]), np.array([1.0, 1.0]), np.array([0.0, 2e-6]))
    w, h = 30.0, 0.002
    # q_τ = ω² (ω² R h + q_p), docs/method.md §6.4
    np.testing.assert_allclose(noise.with_bandwidth(w, h).torque_density,
                               [w ** 2 * (w ** 2 * 1e-6 * h), w ** 2 * (w ** 2 * 4e-6 * h + 2e-6)], rtol=1e-12)
    with pytest.raises(ValueError, match="positive"):
        noise.with_bandwidth(0.0, h)


def _run(panda, config, trained, stream) -> np.ndarray:
    estimator = Estimator(config, panda, make_observer("kvark", trained, config.filter))
    estimates = np.zeros_like(stream.tau_ext)
    for k in range(len(stream.stamp)):
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        if estimate is not None:
            estimates[k] = estimate.tau_ext
    return estimates


def _coloured(shape: tuple[int, int], std: float, time_constant: float, dt: float, seed: int) -> np.ndarray:
    """AR(1) noise of standard deviation ``std`` and correlation time ``time_constant`` s, sampled every dt s."""
    rng = np.random.default_rng(seed)
    phi = np.exp(-dt / time_constant)
    drive = std * np.sqrt(1.0 - phi * phi) * rng.standard_normal(shape)
    out = np.zeros(shape)
    for k in range(1, shape[0]):
        out[k] = phi * out[k - 1] + drive[k]
    return out


def test_a_slower_prior_passes_less_misfit_and_still_follows_a_contact(panda, panda_config):
    """Torque noise as large as the real Panda's (2 N·m per sample), a coloured misfit the residual model cannot
    know (0.3 N·m, 30 ms) before and after a 5 N·m step on joint 2."""
    segments = []
    for offset in range(2):
        free = synthetic_stream(panda, 10.0, seed=3 + 1000 * offset, torque_noise_std=TORQUE_NOISE)
        segments.append(EstimatorInputs(free.stamp, free.q, free.qd, free.tau_m, "synthetic", 0))
    trained = train_model(panda, "panda", segments, baselines=False, residual_inputs="qd", log=lambda _line: None)
    step = np.zeros(panda.n)
    step[STEP_JOINT] = STEP_SIZE
    stream = synthetic_stream(panda, 5.0, seed=11, external=step_torque(STEP_AT, step), torque_noise_std=TORQUE_NOISE)
    misfit = _coloured(stream.tau_m.shape, MISFIT_STD, MISFIT_TIME, stream.stamp[1] - stream.stamp[0], seed=7)
    stream = replace(stream, tau_m=stream.tau_m + misfit)
    free = (stream.stamp >= 1.0) & (stream.stamp < STEP_AT)
    after = (stream.stamp >= STEP_AT + 0.1) & (stream.stamp < STEP_AT + 0.5)
    errors = {}
    for bandwidth in (50.0, 30.0):
        estimates = _run(panda, _settings(panda_config, bandwidth), trained, stream)
        errors[bandwidth] = np.sqrt(np.mean((estimates[free] - stream.tau_ext[free]) ** 2))
        # 100 ms after the step the VB and the onset detector have raised Σ_d: within 10 % of it on average
        # (measured 2.4 % and 2.7 %: the misfit and the noise are about 8 % of the step within a sample).
        assert abs(np.mean(estimates[after, STEP_JOINT]) - STEP_SIZE) < 0.1 * STEP_SIZE, bandwidth
    # Measured 0.389 against 0.457 N·m (0.85): the bound leaves 0.07 for other BLAS/libm roundings of the same draws.
    assert errors[30.0] < 0.92 * errors[50.0], errors
