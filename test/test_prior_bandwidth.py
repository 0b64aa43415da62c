"""The VB variants' free-motion prior bandwidth (``filter.prior_bandwidth``, docs/method.md §4.12)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimator import Estimator
from kvark_ros.core.observers import make_observer
from kvark_ros.core.observers.momentum_observers import MomentumNoise, torque_density_for_bandwidth
from kvark_ros.tools.synthetic import step_torque, synthetic_stream

STEP_JOINT, STEP_SIZE, STEP_AT = 1, 5.0, 3.0          # 5 N·m on joint 2 at t = 3 s
VIBRATION_HZ, VIBRATION_AMPLITUDE = 8.0, 0.5          # unmodelled torque the residual model cannot know, N·m


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


def test_a_slower_prior_passes_less_vibration_and_still_follows_a_contact(panda, panda_config, panda_trained):
    """A vibration the model does not know (8 Hz, 0.5 N·m on every joint) before and after a 5 N·m step."""
    step = np.zeros(panda.n)
    step[STEP_JOINT] = STEP_SIZE
    stream = synthetic_stream(panda, 5.0, seed=11, external=step_torque(STEP_AT, step))
    vibration = VIBRATION_AMPLITUDE * np.sin(2.0 * np.pi * VIBRATION_HZ * stream.stamp)
    stream = replace(stream, tau_m=stream.tau_m + vibration[:, None])
    free = (stream.stamp >= 1.0) & (stream.stamp < STEP_AT)
    errors = {}
    for bandwidth in (50.0, 30.0):
        estimates = _run(panda, _settings(panda_config, bandwidth), panda_trained, stream)
        errors[bandwidth] = np.sqrt(np.mean((estimates[free] - stream.tau_ext[free]) ** 2))
        after = (stream.stamp >= STEP_AT + 0.1) & (stream.stamp < STEP_AT + 0.5)
        # 100 ms after the step the VB and the onset detector have raised Σ_d: within 20 % of the step on average.
        assert abs(np.mean(estimates[after, STEP_JOINT]) - STEP_SIZE) < 0.2 * STEP_SIZE, bandwidth
    # A second-order prior at ω_p passes a tone at ω = 50 rad/s by about 1/(1 + (ω/ω_p)²)-ish: at 30 rad/s it must
    # pass clearly less than at 50 (a quarter less leaves room for the VB's own adaptation to the tone).
    assert errors[30.0] < 0.75 * errors[50.0], errors
