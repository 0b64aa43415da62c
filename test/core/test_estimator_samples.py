"""The Estimator: one call per sample, bad samples rejected with a status, model directories."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kvark_ros.core.estimation.estimator import Estimator, Status
from kvark_ros.core.estimation.model_store import load_model, save_model
from kvark_ros.core.estimation.residual import ResidualModelError
from kvark_ros.tools.synthetic import step_torque, synthetic_stream


@pytest.fixture
def estimator(panda_config, panda_trained):
    return Estimator.from_config(panda_config, panda_trained)


def test_wrench_of_a_step_torque_matches_the_pseudo_inverse(estimator, panda):
    stream = synthetic_stream(panda, 3.0, seed=5, external=step_torque(0.5, np.full(7, 1.0)))
    for k in range(len(stream.stamp)):
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
    J = panda.jacobian(stream.q[-1])
    delta = estimator.config.wrench.damping
    expected = np.linalg.solve(J @ J.T + delta ** 2 * np.eye(6), J @ estimate.tau_ext)   # eq. 39
    assert np.allclose(estimate.wrench, expected)
    assert estimate.wrench_cov.shape == (6, 6) and np.linalg.eigvalsh(estimate.wrench_cov).min() > 0
    assert estimator.counts[Status.OK] == len(stream.stamp) - 1


def test_bad_samples_are_rejected_and_never_reach_the_filter(panda_config, panda_trained):
    """Bad samples in between leave the estimates exactly as without them."""
    clean = Estimator.from_config(panda_config, panda_trained)
    dirty = Estimator.from_config(panda_config, panda_trained)
    q, qd, tau = np.array([0, -0.5, 0, -2, 0, 1.5, 0.8]), np.zeros(7), np.ones(7)   # at rest
    assert dirty.step(0.0, q, qd, tau) is None and dirty.status == Status.WARMUP
    clean.step(0.0, q, qd, tau)
    assert np.array_equal(dirty.step(0.002, q, qd, tau).tau_ext, clean.step(0.002, q, qd, tau).tau_ext)
    bad = np.array(q)
    bad[3] = np.nan
    assert dirty.step(0.004, bad, qd, tau) is None and dirty.status == Status.NON_FINITE
    assert dirty.step(0.004, q, qd, np.full(7, np.inf)) is None and dirty.status == Status.NON_FINITE
    assert dirty.step(0.002, q, qd, tau) is None and dirty.status == Status.STAMP_NOT_INCREASING
    assert dirty.step(0.004, q[:6], qd, tau) is None and dirty.status == Status.BAD_SHAPE
    expected = clean.step(0.004, q, qd, tau)
    estimate = dirty.step(0.004, q, qd, tau)
    assert np.array_equal(estimate.tau_ext, expected.tau_ext) and np.isfinite(estimate.tau_ext).all()
    assert dirty.counts[Status.NON_FINITE] == 2 and dirty.counts[Status.BAD_SHAPE] == 1


def test_a_long_gap_resets_the_filter(panda_config, panda_trained):
    """After a gap longer than input.max_gap the estimator restarts as if new."""
    q, qd = np.array([0, -0.5, 0, -2, 0, 1.5, 0.8]), np.zeros(7)
    estimator = Estimator.from_config(panda_config, panda_trained)
    for k in range(50):
        estimator.step(0.002 * k, q, qd, np.full(7, 5.0))
    assert estimator.step(1.0, q, qd, np.zeros(7)) is None and estimator.status == Status.GAP_RESET
    fresh = Estimator.from_config(panda_config, panda_trained)
    fresh.step(1.0, q, qd, np.zeros(7))
    assert np.array_equal(estimator.step(1.002, q, qd, np.zeros(7)).tau_ext,
                          fresh.step(1.002, q, qd, np.zeros(7)).tau_ext)


def test_configure_applies_run_time_keys_as_if_built_with_them(panda_config, panda_trained, panda):
    """Run-time keys changed through configure act exactly as in an estimator built with them;
    a key that shapes the filter (filter.vb_window_time) is refused by name and changes nothing."""
    changed = replace(panda_config, filter=replace(panda_config.filter, ewma_time=0.04, nis_time=0.01),
                      wrench=replace(panda_config.wrench, damping=0.1))
    estimator = Estimator.from_config(panda_config, panda_trained)
    estimator.configure(changed)
    assert estimator.config is changed and estimator.observer.settings.ewma_time == 0.04
    built = Estimator.from_config(changed, panda_trained)
    stream = synthetic_stream(panda, 0.5, seed=4, external=step_torque(0.2, np.full(7, 1.0)))
    for k in range(len(stream.stamp)):
        sample = (stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        estimate, expected = estimator.step(*sample), built.step(*sample)
        if expected is not None:
            assert np.array_equal(estimate.tau_ext, expected.tau_ext)
            assert np.array_equal(estimate.wrench, expected.wrench)
    with pytest.raises(ValueError, match="filter.vb_window_time"):
        estimator.configure(replace(changed, filter=replace(changed.filter, vb_window_time=0.1)))
    assert estimator.config is changed and estimator.observer.settings is changed.filter


def test_uses_the_actual_time_step(panda_config, panda_trained, panda):
    """Dropping every third sample (steps alternate 2 and 4 ms) must not bias the estimate."""
    stream = synthetic_stream(panda, 3.0, seed=2, external=step_torque(0.5, np.full(7, 2.0)))
    keep = np.arange(len(stream.stamp)) % 3 != 2
    estimator = Estimator.from_config(panda_config, panda_trained)
    errors = []
    for k in np.flatnonzero(keep):
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        if estimate is not None and stream.stamp[k] > 1.5:
            errors.append(np.abs(estimate.tau_ext - stream.tau_ext[k]).mean())
    assert np.mean(errors) < 0.1


def test_model_directory_round_trip_and_mismatched_joints(tmp_path, panda_trained, panda_config):
    save_model(tmp_path / "model", panda_trained)
    loaded = load_model(tmp_path / "model", panda_config.joint_names)
    assert np.array_equal(loaded.tuning.measurement_variance, panda_trained.tuning.measurement_variance)
    qd = np.linspace(-1, 1, 7)
    assert np.array_equal(loaded.residual.predict(qd)[0], panda_trained.residual.predict(qd)[0])
    with pytest.raises(ResidualModelError, match="differ from the configured"):
        load_model(tmp_path / "model", tuple(reversed(panda_config.joint_names)))
    with pytest.raises(ResidualModelError, match="model file not found"):
        load_model(tmp_path / "absent")


def test_failed_save_keeps_the_previous_model(tmp_path, panda_trained, monkeypatch):
    target = tmp_path / "model"
    save_model(target, panda_trained)
    before = (target / "model.yaml").read_text()

    def explode(*_args, **_kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(type(panda_trained.residual), "save", explode)
    with pytest.raises(RuntimeError):
        save_model(target, replace(panda_trained, robot="other"))
    assert (target / "model.yaml").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_an_overflowing_input_is_rejected_without_a_warning(panda_config, panda_trained):
    """|x| ~ 1e200 overflows the finiteness check's sum of squares: a counted rejection, nothing on stderr."""
    import warnings
    estimator = Estimator.from_config(panda_config, panda_trained)
    q = np.zeros(7)
    estimator.step(0.0, q, q, q)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert estimator.step(0.002, np.full(7, 1e200), q, q) is None
    assert estimator.status == Status.NON_FINITE
