"""Tests of the GMM/GMR/KMP residual-torque model (kvark_ros.core.estimation.residual.kmp)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import yaml

from kvark_ros.core.estimation.residual import (
    GMRReference,
    KMPHyperparameters,
    KMPResidualModel,
    ResidualModelError,
    default_hyperparameters,
    fit_gmr_reference,
)
from kvark_ros.core.estimation.residual import kmp as rm

# Hand-built two-joint reference with N = 5 support points; every per-joint quantity differs
# between the joints so that a mix-up of joints shows.
S = np.array([[-1.0, -0.5, 0.0, 0.5, 1.0],
              [-0.3, -0.1, 0.05, 0.2, 0.4]])
MU = np.array([[-0.8, -0.6, 0.1, 0.7, 0.9],
               [0.3, -0.2, 0.0, 0.25, 1.1]])
SIGMA2 = np.array([[0.01, 0.02, 0.05, 0.02, 0.01],
                   [0.002, 0.004, 0.03, 0.001, 0.008]])
HYPER = KMPHyperparameters(
    length_scale=np.array([0.4, 0.15]),
    sigma_f2=np.array([1.5, 0.7]),
    lambda1=np.array([1.0, 3.0]),
    lambda2=np.array([20.0, 5.0]),
)


def _hand_model() -> KMPResidualModel:
    return KMPResidualModel(GMRReference(s=S, mu=MU, sigma2=SIGMA2), HYPER)


def _direct_kmp(j: int, query: float) -> tuple[float, float]:
    """Eqs. 21-23 for joint j written out with full matrices and numpy.linalg.inv, and the far-field
    floor σ_f²(1 − c²), c = maxᵢ k(q̇, sᵢ)/σ_f² (KMPResidualModel.predict)."""
    s, mu, sigma = S[j], MU[j], np.diag(SIGMA2[j])
    ell2 = HYPER.length_scale[j] ** 2  # the paper's l
    sf2, lam1, lam2 = HYPER.sigma_f2[j], HYPER.lambda1[j], HYPER.lambda2[j]

    def k(a: float, b: float) -> float:
        return sf2 * np.exp(-0.5 * (a - b) ** 2 / ell2)

    n_sup = len(s)
    gram = np.array([[k(a, b) for b in s] for a in s])
    k_star = np.array([k(query, b) for b in s])
    mean = k_star @ np.linalg.inv(gram + lam1 * sigma) @ mu
    var = n_sup / lam2 * (k(query, query) - k_star @ np.linalg.inv(gram + lam2 * sigma) @ k_star)
    nearest = k_star.max() / sf2
    return mean, max(var, sf2 * (1.0 - nearest ** 2))  # eq. 23, then the far-field floor


@pytest.mark.parametrize("query", [
    np.array([0.0, 0.05]),  # on support points
    np.array([0.23, -0.17]),  # between support points
    np.array([-1.3, 0.55]),  # just outside the support range
])
def test_predict_matches_direct_evaluation_of_eqs_22_23(query: np.ndarray) -> None:
    model = _hand_model()
    mean, var = model.predict(query)
    assert mean.shape == var.shape == (2,)
    for j in range(2):
        expected_mean, expected_var = _direct_kmp(j, query[j])
        np.testing.assert_allclose(mean[j], expected_mean, rtol=1e-9)
        np.testing.assert_allclose(var[j], expected_var, rtol=1e-9)


def test_far_field_floor_is_inactive_on_the_support_points() -> None:
    """On a support point c = 1, the floor is 0 and eq. 23 alone gives the variance."""
    model = _hand_model()
    _, on_support = model.predict(S[:, 2].copy())
    for j in range(2):
        s, sigma, sf2, lam2 = S[j], np.diag(SIGMA2[j]), HYPER.sigma_f2[j], HYPER.lambda2[j]
        gram = sf2 * np.exp(-0.5 * (s[:, None] - s[None, :]) ** 2 / HYPER.length_scale[j] ** 2)
        eq23 = len(s) / lam2 * (sf2 - gram[2] @ np.linalg.solve(gram + lam2 * sigma, gram[2]))
        np.testing.assert_allclose(on_support[j], eq23, rtol=1e-9)


def test_predict_batch_agrees_with_predict() -> None:
    model = _hand_model()
    queries = np.random.default_rng(3).uniform(-1.5, 1.5, size=(50, 2))
    mean_b, var_b = model.predict_batch(queries)
    assert mean_b.shape == var_b.shape == (50, 2)
    for t, q in enumerate(queries):
        mean, var = model.predict(q)
        np.testing.assert_allclose(mean_b[t], mean, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(var_b[t], var, rtol=1e-12, atol=1e-15)


def test_properties_and_frozen_arrays() -> None:
    model = _hand_model()
    assert (model.n_joints, model.n_support) == (2, 5)
    with pytest.raises(ValueError):
        model.reference.mu[0, 0] = 5.0  # read-only: cannot drift from the precomputed factors


def test_far_from_data_variance_is_asymptote_and_mean_vanishes() -> None:
    model = _hand_model()
    far = S.max(axis=1) + 100.0 * HYPER.length_scale
    for query in (far, -far):
        mean, var = model.predict(query)
        # eq. 23's asymptote N σ_f²/λ₂, unless the far-field floor σ_f² is above it
        np.testing.assert_allclose(var, np.maximum(5 / HYPER.lambda2, 1.0) * HYPER.sigma_f2, rtol=1e-6)
        np.testing.assert_allclose(mean, 0.0, atol=1e-12)


def test_variance_is_positive_even_with_tiny_reference_variance() -> None:
    tiny = GMRReference(s=S, mu=MU, sigma2=np.full_like(SIGMA2, 1e-10))
    hyper = KMPHyperparameters(length_scale=np.array([2.0, 1.0]), sigma_f2=np.ones(2),
                               lambda1=np.ones(2), lambda2=np.ones(2))
    model = KMPResidualModel(tiny, hyper)
    _, var = model.predict_batch(S.T)
    assert np.all(var >= rm.VARIANCE_FLOOR)


def _true_residual(qd: np.ndarray) -> np.ndarray:
    return 0.5 * np.tanh(20.0 * qd) + 0.2 * qd


def test_fit_learns_heteroscedastic_variance_and_mean() -> None:
    # Joint 0: noise std 0.02 N·m for q̇ < 0, 0.2 N·m for q̇ > 0. Joint 1: the mirror image,
    # so a model that mixed up joints would fail one of the two checks.
    rng = np.random.default_rng(7)
    n_samples = 4000
    qd = rng.uniform(-1.0, 1.0, size=(n_samples, 2))
    noise_std = np.column_stack((np.where(qd[:, 0] < 0, 0.02, 0.2),
                                 np.where(qd[:, 1] > 0, 0.02, 0.2)))
    tau_r = _true_residual(qd) + noise_std * rng.standard_normal((n_samples, 2))
    model = KMPResidualModel.fit(qd, tau_r, default_hyperparameters(2), n_components=10,
                                 n_support=30, seed=0)

    _, var_pos = model.predict(np.array([0.5, 0.5]))
    _, var_neg = model.predict(np.array([-0.5, -0.5]))
    assert var_pos[0] > 4.0 * var_neg[0]
    assert var_neg[1] > 4.0 * var_pos[1]

    grid = np.linspace(-0.9, 0.9, 181)
    mean, _ = model.predict_batch(np.column_stack((grid, grid)))
    rmse = np.sqrt(np.mean((mean - _true_residual(grid)[:, None]) ** 2, axis=0))
    assert np.all(rmse < 0.05), rmse


def _saved_model(tmp_path) -> KMPResidualModel:
    model = _hand_model()
    model.save(tmp_path, metadata={"robot": "panda", "joint_names": ["j1", "j2"]})
    return model


def test_save_load_round_trip(tmp_path) -> None:
    model = _saved_model(tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["kmp.npz", "kmp.yaml"]  # no temp files left
    loaded = KMPResidualModel.load(tmp_path)
    queries = np.random.default_rng(0).uniform(-1.5, 1.5, size=(20, 2))
    for got, want in zip(loaded.predict_batch(queries), model.predict_batch(queries)):
        np.testing.assert_array_equal(got, want)
    assert loaded.metadata == {"robot": "panda", "joint_names": ["j1", "j2"]}
    header = yaml.safe_load((tmp_path / "kmp.yaml").read_text())
    assert header["n_joints"] == 2 and header["n_support"] == 5
    assert header["hyperparameters"]["lambda2"] == [20.0, 5.0]


def test_load_uses_allow_pickle_false(tmp_path, monkeypatch) -> None:
    _saved_model(tmp_path)
    calls = []
    real_load = np.load

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real_load(*args, **kwargs)

    monkeypatch.setattr(np, "load", spy)
    KMPResidualModel.load(tmp_path)
    assert calls and all(call.get("allow_pickle") is False for call in calls)


def test_load_refuses_pickled_array(tmp_path) -> None:
    _saved_model(tmp_path)
    arrays = dict(np.load(tmp_path / "kmp.npz"))
    arrays["mu"] = np.array([[object()] * 5] * 2, dtype=object)
    np.savez(tmp_path / "kmp.npz", **arrays)
    with pytest.raises(ResidualModelError, match="kmp.npz"):
        KMPResidualModel.load(tmp_path)


@pytest.mark.parametrize("name", ["kmp.npz", "kmp.yaml"])
def test_load_missing_file(tmp_path, name: str) -> None:
    _saved_model(tmp_path)
    (tmp_path / name).unlink()
    with pytest.raises(ResidualModelError, match=name):
        KMPResidualModel.load(tmp_path)


def test_load_corrupted_npz(tmp_path) -> None:
    _saved_model(tmp_path)
    (tmp_path / "kmp.npz").write_bytes(np.random.default_rng(1).bytes(512))
    with pytest.raises(ResidualModelError, match="kmp.npz"):
        KMPResidualModel.load(tmp_path)


def _rewrite_npz(tmp_path, **changes) -> None:
    arrays = dict(np.load(tmp_path / "kmp.npz"))
    arrays.update(changes)
    arrays = {key: value for key, value in arrays.items() if value is not None}
    np.savez(tmp_path / "kmp.npz", **arrays)


@pytest.mark.parametrize("changes, problem", [
    ({"mu": np.zeros((2, 4))}, "shape"),
    ({"lambda1": np.ones(3)}, "shape"),
    ({"sigma2": None}, "missing array 'sigma2'"),
    ({"s": np.where(S > 0.9, np.nan, S)}, "non-finite"),
])
def test_load_bad_array(tmp_path, changes: dict, problem: str) -> None:
    _saved_model(tmp_path)
    _rewrite_npz(tmp_path, **changes)
    with pytest.raises(ResidualModelError, match=f"kmp.npz.*{problem}"):
        KMPResidualModel.load(tmp_path)


def test_load_unknown_format_version(tmp_path) -> None:
    _saved_model(tmp_path)
    path = tmp_path / "kmp.yaml"
    header = yaml.safe_load(path.read_text())
    header["format_version"] = 99
    path.write_text(yaml.safe_dump(header))
    with pytest.raises(ResidualModelError, match="kmp.yaml.*format_version"):
        KMPResidualModel.load(tmp_path)


def test_load_yaml_hyperparameters_disagreeing_with_npz(tmp_path) -> None:
    _saved_model(tmp_path)
    path = tmp_path / "kmp.yaml"
    header = yaml.safe_load(path.read_text())
    header["hyperparameters"]["lambda1"] = [1.0, 4.0]  # hand-edited: npz still says 3.0
    path.write_text(yaml.safe_dump(header))
    with pytest.raises(ResidualModelError, match="kmp.yaml.*lambda1.*disagrees"):
        KMPResidualModel.load(tmp_path)


def test_invalid_hyperparameters_rejected() -> None:
    with pytest.raises(ValueError, match="lambda2"):
        KMPHyperparameters(length_scale=np.ones(2), sigma_f2=np.ones(2), lambda1=np.ones(2),
                           lambda2=np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="joints"):
        KMPResidualModel(GMRReference(s=S, mu=MU, sigma2=SIGMA2), default_hyperparameters(3))


def test_fit_gmr_reference_shapes_and_support() -> None:
    rng = np.random.default_rng(2)
    qd = rng.uniform(-1.0, 2.0, size=(300, 3))
    tau_r = np.sin(qd) + 0.05 * rng.standard_normal(qd.shape)
    ref = fit_gmr_reference(qd, tau_r, n_components=3, n_support=12, seed=1)
    assert ref.s.shape == ref.mu.shape == ref.sigma2.shape == (3, 12)
    np.testing.assert_allclose(ref.s[:, 0], qd.min(axis=0))
    np.testing.assert_allclose(ref.s[:, -1], qd.max(axis=0))
    assert np.all(ref.sigma2 > 0)


def test_gmr_variance_includes_spread_between_components() -> None:
    # Two parallel branches τ_r = ±1 N·m (e.g. hysteresis): GMR must report mean 0 and
    # variance ≈ 1 N²·m² (law of total variance), not only the within-branch noise.
    # Gaussian velocities, so that EM separates the two branches rather than left and right.
    rng = np.random.default_rng(0)
    qd = rng.normal(0.0, 0.5, size=(2000, 1))
    tau_r = rng.choice([-1.0, 1.0], size=qd.shape) + 0.01 * rng.standard_normal(qd.shape)
    ref = fit_gmr_reference(qd, tau_r, n_components=2, n_support=9, seed=0)
    inner = slice(2, 7)  # the tails hold few samples
    np.testing.assert_allclose(ref.mu[0, inner], 0.0, atol=0.1)
    np.testing.assert_allclose(ref.sigma2[0, inner], 1.0, rtol=0.1)


def test_fit_gmr_reference_rejects_bad_input() -> None:
    rng = np.random.default_rng(0)
    qd = rng.uniform(-1.0, 1.0, size=(100, 2))
    tau_r = 0.1 * qd
    bad = qd.copy()
    bad[10, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_gmr_reference(bad, tau_r, n_components=2)
    tau_bad = tau_r.copy()
    tau_bad[3, 0] = np.inf
    with pytest.raises(ValueError, match="tau_r contains 1 NaN/Inf"):
        fit_gmr_reference(qd, tau_bad, n_components=2)
    with pytest.raises(ValueError, match="too few samples"):
        fit_gmr_reference(qd[:49], tau_r[:49], n_components=10)
    with pytest.raises(ValueError, match="shape"):
        fit_gmr_reference(qd, tau_r[:, :1], n_components=2)
