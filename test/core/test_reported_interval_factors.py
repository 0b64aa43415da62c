"""Calibrated reported intervals (core/estimation/calibration.py, docs/method.md §4.13)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.calibration import COVERAGE, IntervalScale
from kvark_ros.core.learning.interval_factors import WARMUP, Z95, interval_scale, needed_factor, variance_floor
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import load_model, save_model
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.core.estimation.residual.files import ResidualModelError
from kvark_ros.tools.synthetic import synthetic_stream

from reference_estimator import scaled_covariance


class _WhiteObserver:
    """Reports σ_j but its τ̂_j is k_j σ_j times a standard normal draw: the factor to find is k."""

    def __init__(self, sigma: np.ndarray, k: np.ndarray, seed: int) -> None:
        self.sigma, self.k, self.seed = sigma, k, seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def step(self, dt, qd, p, p_prev, u_prev, q, g):
        return self.k * self.sigma * self.rng.standard_normal(len(self.sigma)), np.diag(self.sigma ** 2)


def test_apply_scales_rows_and_columns():
    scale = IntervalScale(np.array([2.0, 0.5]))
    P = np.array([[4.0, 1.0], [1.0, 9.0]])
    np.testing.assert_allclose(scaled_covariance(scale, P), np.diag([2.0, 0.5]) @ P @ np.diag([2.0, 0.5]))


def test_the_floor_raises_only_the_variances_below_it_and_keeps_the_covariance_positive_semi_definite():
    """diag(c) P diag(c) = [[16, 1], [1, 2.25]]: the first variance is above its floor 9 and stays, the second is
    raised to 4; the off-diagonal term stays, and a non-negative diagonal added keeps the matrix PSD."""
    scale = IntervalScale(np.array([2.0, 0.5]), np.array([9.0, 4.0]))
    P = np.array([[4.0, 1.0], [1.0, 9.0]])
    reported = scaled_covariance(scale, P)
    np.testing.assert_allclose(reported, [[16.0, 1.0], [1.0, 4.0]])
    assert np.all(np.linalg.eigvalsh(reported) >= 0.0)
    np.testing.assert_array_equal(IntervalScale(np.array([2.0, 0.5])).floor, [0.0, 0.0])     # models without one


def test_in_free_motion_the_floor_is_narrowed_by_its_factor_and_under_a_load_it_is_whole():
    """Floors [9, 4] with factors [0.5, 1]: free motion [0.25·9, 4] = [2.25, 4], so the first variance (16) stays and
    the second (2.25) is raised to 4; under a load the first floor is 9, still below 16. Models without factors keep
    the whole floor everywhere."""
    scale = IntervalScale(np.array([2.0, 0.5]), np.array([9.0, 4.0]), np.array([0.5, 1.0]))
    np.testing.assert_allclose(scale.floor_for(False), [2.25, 4.0])
    np.testing.assert_allclose(scale.floor_for(True), [9.0, 4.0])
    P = np.array([[1.0, 0.0], [0.0, 4.0]])           # c² P = diag(4, 1)
    np.testing.assert_allclose(np.diag(scaled_covariance(scale, P, loaded=False)), [4.0, 4.0])
    np.testing.assert_allclose(np.diag(scaled_covariance(scale, P, loaded=True)), [9.0, 4.0])
    np.testing.assert_array_equal(IntervalScale(np.ones(2), np.array([9.0, 4.0])).floor_for(False), [9.0, 4.0])


@pytest.mark.parametrize("bad", [[1.0, 0.0], [1.0, 1.5], [1.0, np.nan], [1.0]])
def test_a_floor_factor_outside_0_1_is_refused(bad):
    with pytest.raises(ValueError, match="floor factor"):
        IntervalScale(np.ones(2), np.ones(2), np.array(bad))


@pytest.mark.parametrize("bad", [[1.0, -1.0], [1.0, np.inf], [1.0]])
def test_a_negative_non_finite_or_misshaped_floor_is_refused(bad):
    with pytest.raises(ValueError, match="floor"):
        IntervalScale(np.ones(2), np.array(bad))


def test_the_floor_is_the_steady_state_variance_the_kf_reports(panda_config, panda_trained):
    """variance_floor steps a fresh ``kf`` on zero input; its covariance does not depend on the data, so the ``kf``
    stepped 4 s along a synthetic recording ends at the same P (to 1e-9 relative: both are 40+ time constants at
    ω_b = 50 rad/s past the start, where the recursion's remaining change is below 1e-12)."""
    kf = make_observer("kf", panda_trained, panda_config.filter)
    h = panda_trained.sample_period
    floor = variance_floor(kf, h)
    rng = np.random.default_rng(3)
    for _ in range(int(4.0 / h)):
        _, cov = kf.step(h, *(rng.standard_normal(7) for _ in range(6)))
    np.testing.assert_allclose(floor, np.diag(cov), rtol=1e-9)
    assert np.all(floor > 0.0)


def test_training_stores_the_kf_floor_with_the_factors(panda_config, panda_trained):
    """The model's floor is the ``kf``'s steady state (docs/method.md §4.13), so under a load kvark never reports
    τ_ext known better than the fixed-Σ_d filter at the contact bandwidth would; in free motion it is narrowed by
    ``kf``'s own factor, read on the same recordings as kvark's, where that is below 1."""
    expected = variance_floor(make_observer("kf", panda_trained, panda_config.filter), panda_trained.sample_period)
    scale = panda_trained.interval_scale
    np.testing.assert_allclose(scale.floor, expected, rtol=1e-9)
    np.testing.assert_array_equal(scale.floor_factor, np.minimum(panda_trained.info["interval_factors"]["kf"], 1.0))
    assert np.all(scale.free_floor <= scale.floor)


@pytest.mark.parametrize("bad", [[1.0, 0.0], [1.0, np.nan], [[1.0]]])
def test_non_positive_or_non_finite_factors_are_refused(bad):
    with pytest.raises(ValueError, match="positive finite"):
        IntervalScale(np.array(bad))


def test_the_factor_that_covers_95_percent_of_the_contact_free_estimate_is_found():
    n, samples = 3, 6000
    sigma, k = np.array([0.5, 1.0, 2.0]), np.array([0.3, 1.0, 2.5])
    stamp = np.arange(samples) * 0.002
    zeros = np.zeros((samples, n))
    observer = _WhiteObserver(sigma, k, seed=4)
    found = interval_scale(observer, [stamp], [zeros], [zeros], [zeros], [zeros], [zeros]).scale
    # 5750 samples after the warm-up: the 95 % quantile of |N(0, 1)| has a standard error of
    # √(0.95·0.05/5750)/(2φ(1.96)) ≈ 0.025, 1.3 % of 1.96; 5 % is about four of them.
    np.testing.assert_allclose(found, k, rtol=0.05)
    assert WARMUP > 0 and COVERAGE == 0.95 and abs(Z95 - 1.96) < 1e-3


def test_needed_factor_is_the_least_c_that_covers_each_sample():
    tau, sigma, band = np.array([[2.0 * Z95, 1.0, 0.5]]), np.array([[1.0, 1.0, 2.0]]), np.array([[3.0, 1.0, 0.0]])
    found = needed_factor(tau, sigma, band)
    # (2 z / z)² − 3 = 1; 1 N·m is inside the band alone; no band: |τ̂| / (1.96 σ).
    np.testing.assert_allclose(found, [[1.0, 0.0, 0.5 / (Z95 * 2.0)]], rtol=1e-12)
    assert np.all(np.abs(tau) <= Z95 * np.sqrt((found * sigma) ** 2 + band) * (1.0 + 1e-12))     # inside at c_k
    outside = np.abs(tau) > Z95 * np.sqrt((0.99 * found * sigma) ** 2 + band)
    assert outside[0, 0] and outside[0, 2]                                                          # outside below


def test_the_factor_is_read_for_the_interval_with_the_static_band_inside():
    """Half the samples at rest, where a band of σ²_s = 3 N²·m² covers N(0, 1) all but 0.07 % of the time; half
    sliding, where it is gone: the 5 % that may miss are all sliding ones, so c covers 90 % there,
    1.96 c = 1.645 (c = 0.839), where without the band c = 1."""
    samples = 6000
    stamp = np.arange(samples) * 0.002
    qd = np.where(np.arange(samples) % 2 == 0, 0.0, 1.0)[:, None]
    zeros = np.zeros((samples, 1))
    band = lambda v: 3.0 * np.exp(-np.square(v / 0.05))                       # noqa: E731
    observer = _WhiteObserver(np.ones(1), np.ones(1), seed=2)
    found = interval_scale(observer, [stamp], [qd], [zeros], [zeros], [zeros], [zeros], band).scale
    # 2875 sliding samples: the 90 % quantile of |N(0, 1)| has a standard error of √(0.9·0.1/2875)/(2φ(1.645))
    # ≈ 0.027, 1.7 % of 1.645; 5 % is three of them.
    np.testing.assert_allclose(found, 1.6448536 / Z95, rtol=0.05)
    plain = interval_scale(_WhiteObserver(np.ones(1), np.ones(1), seed=2), [stamp], [qd], [zeros], [zeros], [zeros],
                           [zeros]).scale
    np.testing.assert_allclose(plain, 1.0, rtol=0.05)


def test_too_few_samples_are_refused():
    stamp = np.arange(300) * 0.002          # 0.6 s: 50 samples after the warm-up
    zeros = np.zeros((300, 1))
    with pytest.raises(ValueError, match="at least 100"):
        interval_scale(_WhiteObserver(np.ones(1), np.ones(1), 0), [stamp], [zeros], [zeros], [zeros], [zeros],
                       [zeros])


def test_model_round_trip_keeps_the_factors_and_refuses_a_wrong_length(tmp_path, panda_trained):
    trained = replace(panda_trained, interval_scale=IntervalScale(np.linspace(0.5, 2.0, 7)))
    save_model(tmp_path / "model", trained)
    loaded = load_model(tmp_path / "model")
    np.testing.assert_array_equal(loaded.interval_scale.scale, trained.interval_scale.scale)
    floored = replace(panda_trained, interval_scale=IntervalScale(np.ones(7), np.linspace(0.0, 0.6, 7)))
    save_model(tmp_path / "floored", floored)
    np.testing.assert_array_equal(load_model(tmp_path / "floored").interval_scale.floor, floored.interval_scale.floor)
    save_model(tmp_path / "short", replace(panda_trained, interval_scale=IntervalScale(np.ones(6))))
    with pytest.raises(ResidualModelError, match="disagree on the number of joints"):
        load_model(tmp_path / "short")


def _reported(config, panda, trained, stream):
    estimator = Estimator(config, panda, make_observer("kvark", trained, config.filter), trained)
    covariances, flags = [], []
    for k in range(len(stream.stamp)):
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        if estimate is not None:
            covariances.append(estimate.tau_cov)
            flags.append((estimate.contact, estimate.collision))
    return np.array(covariances), flags


def test_the_estimator_reports_the_scaled_covariance_and_its_flags_do_not_move(panda, panda_config, panda_trained):
    c = np.linspace(0.5, 3.0, 7)
    trained = replace(panda_trained, interval_scale=IntervalScale(c))
    push = np.zeros(7)
    push[1] = 15.0                                   # N·m on joint 2 from 0.5 s: the contact test flags it
    stream = synthetic_stream(panda, 1.0, seed=5, external=lambda t: push if t >= 0.5 else 0.0 * push)
    config = replace(panda_config, filter=replace(panda_config.filter, stiction_velocity=0.0))
    scaled, flags = _reported(config, panda, trained, stream)
    off = replace(config, filter=replace(config.filter, interval_calibration="off"))
    raw, raw_flags = _reported(off, panda, trained, stream)
    np.testing.assert_allclose(scaled, raw * np.outer(c, c), rtol=1e-12)
    assert flags == raw_flags
    # A floor between the smallest and the largest reported variance: below it the variance is the floor, above
    # it stays c² P; the flags still do not move.
    variances = np.diagonal(scaled, axis1=1, axis2=2)
    floor = np.median(variances, axis=0)
    floored, floored_flags = _reported(config, panda, replace(trained, interval_scale=IntervalScale(c, floor)),
                                       stream)
    np.testing.assert_allclose(np.diagonal(floored, axis1=1, axis2=2), np.maximum(variances, floor), rtol=1e-12)
    assert floored_flags == raw_flags
    # Narrowed to a quarter in free motion: where the last sample's contact test held a load, the floor is whole.
    variances_floored = np.diagonal(floored, axis1=1, axis2=2)
    narrowed, narrowed_flags = _reported(config, panda, replace(
        trained, interval_scale=IntervalScale(c, floor, np.full(7, 0.5))), stream)
    loaded = np.array([False] + [contact for contact, _ in narrowed_flags[:-1]])
    assert loaded.any() and not loaded.all()
    expected = np.where(loaded[:, None], variances_floored, np.maximum(variances, 0.25 * floor))
    np.testing.assert_allclose(np.diagonal(narrowed, axis1=1, axis2=2), expected, rtol=1e-12)
    assert narrowed_flags == raw_flags
    unfloored = replace(config, filter=replace(config.filter, interval_floor="off"))      # the key switches it off
    np.testing.assert_allclose(_reported(unfloored, panda, replace(trained, interval_scale=IntervalScale(c, floor)),
                                         stream)[0], scaled, rtol=1e-12)


def test_training_calibrates_the_intervals_on_its_own_recordings(panda_trained):
    scale = panda_trained.interval_scale
    assert scale is not None and scale.scale.shape == (7,)
    assert np.all((scale.scale > 0.05) & (scale.scale < 20.0))


def test_each_factor_is_the_larger_of_the_in_sample_one_and_the_one_on_motion_the_model_has_not_seen(panda_trained):
    """Training reads c twice (docs/method.md §4.13): on its own recordings, and on their last 20 % with a model
    refitted without them (the model error a new recording meets); each joint keeps the larger, so an interval is
    never narrower than the in-sample one. The fixture's 20 s recording leaves 4 s unseen, over MIN_UNSEEN (2 s)."""
    read = panda_trained.info["interval_factors"]
    assert read["unseen"] is not None and read["unseen_seconds"] == pytest.approx(4.0, abs=0.01)
    expected = np.clip(np.maximum(read["in_sample"], read["unseen"]), 0.05, 20.0)
    np.testing.assert_allclose(panda_trained.interval_scale.scale, expected, rtol=0, atol=0)


def test_the_factors_are_read_on_the_filter_an_onset_does_not_raise(panda, panda_trained, panda_config):
    """Training reads c with ``filter.onset_contact_bandwidth`` off (docs/method.md §4.7): a false onset in the
    contact-free recordings would raise every joint's P for a while and so shrink c everywhere. At a threshold of 5
    the detector fires often on this stream (so the key would move c if it were read with it on); the factors read
    with the key at 0 and at 100 rad/s are the same."""
    from kvark_ros.core.estimation.inputs import EstimatorInputs
    from kvark_ros.core.learning.training import calibrate_intervals, training_data
    stream = synthetic_stream(panda, 4.0, rate=500.0, seed=7)
    data = training_data(panda, [EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0)])
    settings = replace(panda_config.filter, measurement="momentum", onset_threshold=5.0)
    read = {bandwidth: calibrate_intervals(panda_trained, data, replace(settings, onset_contact_bandwidth=bandwidth),
                                           lambda _line: None).interval_scale.scale for bandwidth in (0.0, 100.0)}
    np.testing.assert_array_equal(read[0.0], read[100.0])
