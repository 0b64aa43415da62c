"""Rate independence (issue 15): the config's filter times mean the same at 100 Hz, 500 Hz and 1 kHz, a model
records the rate it was trained at, and data at another rate are warned about."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.config import ConfigError, config_from_parameters, flatten_parameters
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_checks import (RATE_TOLERANCE, data_source, measured_rate, model_warnings,
                                                    rate_warning)
from kvark_ros.core.estimation.model_store import load_model, save_model
from kvark_ros.core.estimation.observers.base import PerSample
from kvark_ros.tools.synthetic import step_torque, synthetic_stream, train_synthetic

RATES = (100.0, 500.0, 1000.0)


@pytest.mark.parametrize("rate", RATES)
def test_filter_times_become_the_same_durations_at_every_rate(panda_config, rate):
    """Windows of L samples last vb_window_time (to half a sample), the forgetting remembers vb_memory seconds
    (1/(1 − ρ) samples) and the EWMA rates are t_s/T, at each rate."""
    settings, t_s = panda_config.filter, 1.0 / rate
    per_sample = PerSample.of(settings, t_s)
    assert abs(per_sample.vb_window * t_s - settings.vb_window_time) <= t_s / 2
    assert abs(per_sample.onset_window * t_s - settings.onset_window_time) <= t_s / 2
    assert t_s / (1.0 - per_sample.vb_forgetting) == pytest.approx(settings.vb_memory, rel=1e-12)
    assert per_sample.ewma_rate * settings.ewma_time / t_s == pytest.approx(1.0, rel=1e-12)
    assert per_sample.nis_rate * settings.nis_time / t_s == pytest.approx(1.0, rel=1e-12)


def test_the_defaults_at_500_hz_are_the_sample_counts_the_results_were_measured_with(panda_config):
    """The README's figures were measured with vb_window 25, onset_window 10, ρ 0.99 and rates 0.01 at 500 Hz."""
    per_sample = PerSample.of(panda_config.filter, 0.002)
    assert (per_sample.vb_window, per_sample.onset_window) == (25, 10)
    assert per_sample.vb_forgetting == 0.99 and per_sample.ewma_rate == 0.01 and per_sample.nis_rate == 0.01


def test_windows_keep_their_minimum_length_at_low_rates(panda_config):
    """At 20 Hz a 50 ms window would be one sample; the VB needs at least 5 and the onset test 2."""
    per_sample = PerSample.of(panda_config.filter, 0.05)
    assert (per_sample.vb_window, per_sample.onset_window) == (5, 2)
    with pytest.raises(ValueError, match="sample period"):
        PerSample.of(panda_config.filter, 0.0)


def test_an_old_sample_count_key_names_its_replacement():
    """A config written for the sample-count keys gets the new key and the conversion, not 'unknown key'."""
    parameters = flatten_parameters({"robot": "panda", "robot_model": {
        "urdf": "example-robot-data:panda", "joint_names": ["a"], "ee_frame": "e", "flange_frame": "f"},
        "residual_model": {"model_dir": "m"}, "filter": {"vb_window": 25}})
    with pytest.raises(ConfigError, match=r"'filter.vb_window' is now 'filter.vb_window_time'.*25 at 500 Hz is 0.05"):
        config_from_parameters(parameters)


@pytest.fixture(scope="module")
def trained_at(panda):
    """Models trained on 6 s of synthetic free motion at each rate (q̇ residual only, no baselines): 600-6000
    samples, each rate's windows many times over (12 s gave the same errors below to 0.01 N·m, in 1.6 × the time)."""
    return {rate: train_synthetic(panda, "panda", seed=3, duration=6.0, baselines=False, rate=rate)
            for rate in RATES}


@pytest.mark.parametrize("rate", RATES)
def test_the_estimator_tracks_a_step_at_every_rate(panda_config, panda, trained_at, tmp_path, rate):
    """Trained and run at 100 Hz, 500 Hz or 1 kHz, the model records its rate, survives a save, and K-VARK
    follows a 2 N·m step on every joint. Measured joint RMSE before/after the step: 0.014-0.10 N·m at the
    three rates; the bound 0.2 N·m is 10 % of the step, which an estimator on wrong windows misses (a 5 s
    EWMA or a one-sample window VB at 1 kHz)."""
    trained = trained_at[rate]
    assert trained.sample_rate == pytest.approx(rate, rel=1e-9)
    save_model(tmp_path / "model", trained)
    trained = load_model(tmp_path / "model", panda_config.joint_names)
    assert trained.sample_rate == pytest.approx(rate, rel=1e-9)
    stream = synthetic_stream(panda, 3.0, rate=rate, seed=7, external=step_torque(1.0, np.full(7, 2.0)))
    estimator = Estimator.from_config(panda_config, trained)
    assert estimator.observer.window.stride * 5 * (1.0 / rate) == pytest.approx(0.05, abs=0.5 / rate + 1e-12)
    estimates = np.full(stream.tau_ext.shape, np.nan)
    for k in range(len(stream.stamp)):
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        if estimate is not None:
            estimates[k] = estimate.tau_ext
    error = estimates - stream.tau_ext
    for part in ((stream.stamp > 0.2) & (stream.stamp < 1.0), stream.stamp > 1.5):
        assert np.sqrt(np.mean(error[part] ** 2)) < 0.2
    assert model_warnings(trained, "panda", measured_rate(stream.stamp), simulated=False) == []


def test_data_at_another_rate_are_warned_about(panda_trained):
    """20 % either way is tolerated (a driver's jitter, a dropped-sample rate); 1 kHz data on a 500 Hz model is not."""
    assert panda_trained.sample_rate == pytest.approx(500.0)
    stamp = np.arange(200) / 1000.0
    [line] = model_warnings(panda_trained, "panda", measured_rate(stamp), simulated=False)
    assert "1000 Hz" in line and "500 Hz" in line
    assert model_warnings(panda_trained, "panda", float("nan"), simulated=False) == []
    assert rate_warning(500.0, 500.0 * (1 + RATE_TOLERANCE) - 1e-6) is None
    assert rate_warning(500.0, 500.0 * (1 - RATE_TOLERANCE) - 1e-3) is not None
    assert np.isnan(measured_rate(np.zeros(1)))


def test_a_model_for_another_robot_or_from_the_simulator_is_warned_about(panda_trained):
    """The model's robot name and its training data's source are checked against the data it runs on."""
    rate = measured_rate(np.arange(100) / 500.0)
    simulated = replace(panda_trained, info={**panda_trained.info, "data_source": "simulator"})
    assert model_warnings(simulated, "panda", rate, simulated=True) == []
    [line] = model_warnings(simulated, "panda", rate, simulated=False)
    assert "simulated" in line
    [line] = model_warnings(panda_trained, "panda_left", rate, simulated=False)
    assert "'panda'" in line and "'panda_left'" in line
    assert (data_source([True, True]), data_source([False]), data_source([True, False])) == (
        "simulator", "recorded", "mixed")
