"""Joint-level and trajectory-level calibration of the reported covariance (issue 17, scope 3).

Synthetic estimates with known Gaussian errors (seeded numpy) check the figures against their nominal values. Every
margin is 4 binomial standard deviations, √(p(1 − p)/T) for a share p observed on T independent samples: a correct
implementation misses it with probability ~6e-5, and the seeded data make each outcome fixed; a wrong quantile or
a covariance used the wrong way round moves the figures by far more (see each test). The replay and real-benchmark
paths run on the committed bags and model (no training, no simulation).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2, norm

from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.metrics import LEVELS, in_motion, mahalanobis_squared, observer_metrics
from kvark_ros.tools.plots import plot_reliability
from kvark_ros.tools.real_benchmark import evaluate, report, split
from kvark_ros.tools.replay import GroundTruth, ObserverRun, ground_truth, run_observer
from kvark_ros.tools.report import write_replay_report

ROOT = Path(__file__).resolve().parents[2]
N = 7
SAMPLES = 20_000
P95 = 2.0 * norm.cdf(1.96) - 1.0          # coverage of ±1.96 σ: 0.950004


def _margin(p: float, samples: int = SAMPLES) -> float:
    """4 binomial standard deviations of a share ``p`` over ``samples`` independent samples."""
    return 4.0 * np.sqrt(p * (1.0 - p) / samples)


def _covariance(seed: int = 1) -> np.ndarray:
    """A correlated 7×7 SPD covariance, N²·m² (joint σ between ~0.3 and ~1.5 N·m)."""
    a = np.random.default_rng(seed).standard_normal((N, N))
    return a @ a.T / N + 0.1 * np.eye(N)


def _run(name: str, error: np.ndarray, std: np.ndarray | None, cov: np.ndarray | None = None) -> ObserverRun:
    """An ObserverRun whose estimate is ``error`` (the truth is zero) with reported σ ``std`` (T, n) and, with
    ``cov`` (n, n), the Mahalanobis statistic of every sample under it."""
    count = len(error)
    flags = np.zeros(count, dtype=bool)
    distance = None if cov is None else np.array([mahalanobis_squared(e, cov) for e in error])
    return ObserverRun(name, error, std, np.zeros((count, 6)), None, np.ones(count, dtype=bool), 1.0, {}, flags,
                       flags, mahalanobis=distance)


def _metrics(run: ObserverRun, moving: np.ndarray | None = None) -> dict:
    count, n = run.tau_ext.shape
    truth = GroundTruth("synthetic", np.zeros((count, n)), np.zeros((count, 6)))
    return observer_metrics(run, truth, 0.002 * np.arange(count), moving=moving)


@pytest.fixture(scope="module")
def correlated():
    """Errors e = L z with P = L Lᵀ correlated, z (T, n) standard normal; the reported P is the true one."""
    cov = _covariance()
    z = np.random.default_rng(2).standard_normal((SAMPLES, N))
    error = z @ np.linalg.cholesky(cov).T
    return SimpleNamespace(cov=cov, z=z, error=error, std=np.tile(np.sqrt(np.diag(cov)), (SAMPLES, 1)))


# --------------------------------------------------------------------------- figures on known errors

def test_mahalanobis_statistic_is_the_squared_whitened_error_and_nan_when_undefined(correlated):
    run = _run("kvark", correlated.error[:500], correlated.std[:500], correlated.cov)
    np.testing.assert_allclose(run.mahalanobis, (correlated.z[:500] ** 2).sum(axis=1), rtol=1e-9)   # e = L z
    assert np.isnan(mahalanobis_squared(np.array([np.nan, 1.0]), np.eye(2)))
    assert np.isnan(mahalanobis_squared(np.ones(2), np.zeros((2, 2))))                            # singular P


def test_coverage_per_joint_and_of_the_vector_match_nominal_under_the_true_covariance(correlated):
    entry = _metrics(_run("kvark", correlated.error, correlated.std, correlated.cov))
    assert len(entry["coverage95_per_joint"]) == N
    # Each joint's error is N(0, P_jj) whatever the correlation: ±1.96 σ holds 95.0 % of T samples.
    assert entry["coverage95_per_joint"] == pytest.approx([P95] * N, abs=_margin(P95))
    assert entry["coverage95"] == pytest.approx(np.mean(entry["coverage95_per_joint"]), abs=1e-6)
    # eᵀP⁻¹e is χ²_7: 95 % inside χ²_7(0.95) = 14.07. A diagonal-only test (independence assumed) would differ.
    assert entry["vector_coverage95"] == pytest.approx(0.95, abs=_margin(0.95))


def test_a_covariance_half_the_true_one_is_clearly_overconfident(correlated):
    """P reported as 0.5 P_true: every d² doubles, so the ellipsoid holds χ²_7-cdf(14.07 / 2) = 0.575 of the
    samples, and each joint's ±1.96 σ/√2 holds 0.834; both far below 0.95 (the margins are 0.006)."""
    entry = _metrics(_run("kvark", correlated.error, correlated.std * np.sqrt(0.5), 0.5 * correlated.cov))
    vector = chi2.cdf(chi2.ppf(0.95, N) / 2.0, N)
    joint = 2.0 * norm.cdf(1.96 * np.sqrt(0.5)) - 1.0
    assert entry["vector_coverage95"] == pytest.approx(vector, abs=_margin(vector)) and vector < 0.6
    assert entry["coverage95_per_joint"] == pytest.approx([joint] * N, abs=_margin(joint))


def test_any_joint_miss_share_of_independent_joints_is_one_minus_095_to_the_n():
    """7 independent calibrated joints: some joint misses its ±1.96 σ on 1 − 0.95⁷ = 30.2 % of the samples, six
    times the 5 % a single interval suggests."""
    rng = np.random.default_rng(3)
    sigma = np.linspace(0.2, 2.0, N)                       # N·m, a different σ per joint
    error = sigma * rng.standard_normal((SAMPLES, N))
    entry = _metrics(_run("kf", error, np.tile(sigma, (SAMPLES, 1)), np.diag(sigma ** 2)))
    nominal = 1.0 - P95 ** N
    assert entry["any_joint_miss_nominal"] == pytest.approx(1.0 - 0.95 ** N, abs=1e-6)
    assert entry["any_joint_miss_share"] == pytest.approx(nominal, abs=_margin(nominal))


def test_calibration_figures_of_hand_made_errors():
    """3 samples, 2 joints, σ = 1: row 0 inside, row 1 misses on joint 0 (2.0 > 1.96), row 2 on both joints."""
    error = np.array([[0.5, -0.5], [2.0, 0.0], [-3.0, 2.5]])
    entry = _metrics(_run("x", error, np.ones((3, 2)), np.eye(2)))
    assert entry["coverage95_per_joint"] == pytest.approx([1 / 3, 2 / 3], abs=1e-6)
    assert entry["interval95_per_joint"] == pytest.approx([1.96, 1.96], abs=1e-6)      # the mean 1.96 σ
    assert entry["any_joint_miss_share"] == pytest.approx(2 / 3, abs=1e-6)
    # d² = 0.5, 4.0, 15.25 against χ²_2(0.95) = 5.99: one of three outside
    assert entry["vector_coverage95"] == pytest.approx(2 / 3, abs=1e-6)
    # At 50 % (±0.674 σ, χ²_2 1.386) only row 0 is inside on joint 0, rows 0 and 1 on joint 1, row 0 as a vector.
    assert entry["reliability"]["joint"][0] == pytest.approx(0.5, abs=1e-6)
    assert entry["reliability"]["vector"][0] == pytest.approx(1 / 3, abs=1e-6)
    assert entry["coverage95_moving"] is None                          # no motion given


def test_coverage_in_motion_counts_only_the_joint_samples_above_the_stiction_velocity():
    """The hand-made errors above, σ = 1, with q̇ (rad/s) against a 0.01 rad/s stiction velocity: joint 0 moves in
    rows 1 and 2 (both miss), joint 1 in rows 0 and 2 (inside, miss): 1 of 4 moving samples is inside, while every
    sample gives 3 of 6. With no joint in motion the figure is None, not a share of nothing."""
    error = np.array([[0.5, -0.5], [2.0, 0.0], [-3.0, 2.5]])
    qd = np.array([[0.005, -0.2], [0.3, 0.0], [-0.5, 0.011]])
    moving = in_motion(qd, 0.01)
    assert moving.tolist() == [[False, True], [True, False], [True, True]]
    entry = _metrics(_run("x", error, np.ones((3, 2)), np.eye(2)), moving)
    assert entry["coverage95"] == pytest.approx(0.5, abs=1e-6)
    assert entry["coverage95_moving"] == pytest.approx(0.25, abs=1e-6)
    still = _metrics(_run("x", error, np.ones((3, 2)), np.eye(2)), np.zeros((3, 2), dtype=bool))
    assert still["coverage95_moving"] is None and still["coverage95"] == pytest.approx(0.5, abs=1e-6)


def test_no_covariance_means_no_calibration_figures(correlated):
    entry = _metrics(_run("momentum", correlated.error[:100], None))
    for key in ("coverage95_per_joint", "vector_coverage95", "any_joint_miss_share", "any_joint_miss_nominal",
                "reliability"):
        assert entry[key] is None, key
    no_vector = _metrics(_run("kf", correlated.error[:100], correlated.std[:100]))   # σ without the statistic
    assert no_vector["vector_coverage95"] is None and no_vector["reliability"]["vector"] is None
    assert len(no_vector["coverage95_per_joint"]) == N


def test_reliability_table_is_monotone_and_on_the_diagonal_when_calibrated(correlated):
    """Observed coverage at each LEVELS nominal. The pooled joint share averages 7 correlated joints: its
    variance is at most one joint's, so the single-joint margin over T samples bounds it."""
    entry = _metrics(_run("kvark", correlated.error, correlated.std, correlated.cov))
    table = entry["reliability"]
    assert table["nominal"] == list(LEVELS)
    for level, joint, vector in zip(LEVELS, table["joint"], table["vector"]):
        assert joint == pytest.approx(level, abs=_margin(level)), level
        assert vector == pytest.approx(level, abs=_margin(level)), level
    over = _metrics(_run("kf", correlated.error, 0.5 * correlated.std, 0.25 * correlated.cov))["reliability"]
    for calibrated in (table, over):         # nested intervals: never less coverage at a higher level
        assert np.all(np.diff(calibrated["joint"]) >= 0) and np.all(np.diff(calibrated["vector"]) >= 0)
    assert all(o < t for o, t in zip(over["vector"], table["vector"]))


# --------------------------------------------------------------------------- report and reliability diagram

def _replay_inputs(correlated, with_truth: bool) -> tuple:
    """What replay hands write_replay_report: kvark calibrated, kf overconfident, momentum without covariance;
    1 500 samples (3 s at 500 Hz) of the 7-joint errors about a zero truth."""
    count = 1500
    error, std, cov = correlated.error[:count], correlated.std[:count], correlated.cov
    results = [_run("kvark", error, std, cov), _run("kf", error, 0.5 * std, 0.25 * cov),
               _run("momentum", error, None)]
    stamp = 0.002 * np.arange(count)
    truth = GroundTruth("synthetic", np.zeros((count, N)), np.zeros((count, 6))) if with_truth else None
    metrics = {"bag": "synthetic", "ground_truth": "synthetic" if with_truth else "none", "samples": count,
               "duration_s": float(stamp[-1]), "torque_source": "effort_commands", "dropped_samples": 0,
               "decode_seconds": 0.0, "observers": {r.name: observer_metrics(r, truth, stamp) for r in results}}
    robot = SimpleNamespace(joint_names=[f"panda_joint{j + 1}" for j in range(N)])
    return metrics, robot, SimpleNamespace(stamp=stamp), truth, results


def test_reliability_diagram_and_calibration_section_only_with_ground_truth(correlated, tmp_path, saved):
    with_truth, without = tmp_path / "with", tmp_path / "without"
    with_truth.mkdir()
    without.mkdir()
    figures = write_replay_report(with_truth, *_replay_inputs(correlated, True))
    assert figures[-1].name == "reliability.png"
    assert (with_truth / "reliability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (with_truth / "report.md").read_text()
    assert "(reliability.png)" in text and "`reliability.png`: observed against nominal coverage" in text
    assert "Calibration of the reported covariance" in text and "any-joint miss (nominal)" in text
    calibration = text[text.index("Calibration of the reported covariance"):]
    assert "| kvark |" in calibration and "| kf |" in calibration and "| momentum |" not in calibration
    assert "vector coverage95" in text and "coverage95 per joint min–max" in text      # the metrics table
    diagram = saved[-1]
    ax, = diagram.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert set(lines) == {"perfect calibration", "kvark per joint", "kvark vector", "kf per joint", "kf vector"}
    np.testing.assert_allclose(lines["perfect calibration"].get_xdata(), lines["perfect calibration"].get_ydata())
    np.testing.assert_allclose(lines["kvark per joint"].get_xdata(), LEVELS)
    assert lines["kvark vector"].get_linestyle() == "--"
    assert lines["kvark per joint"].get_linewidth() > lines["kf per joint"].get_linewidth()
    assert ax.get_xlim()[0] <= min(lines["kf vector"].get_ydata())        # the overconfident one stays in view

    figures = write_replay_report(without, *_replay_inputs(correlated, False))
    assert "reliability.png" not in [path.name for path in figures] and not (without / "reliability.png").exists()
    text = (without / "report.md").read_text()
    assert "no reliability diagram" in text and "Calibration of the reported covariance" not in text
    assert plot_reliability({"momentum": {"reliability": None}}, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


# --------------------------------------------------------------------------- real data paths

@pytest.fixture(scope="module")
def committed():
    """The committed Panda model (models/panda) and its config."""
    from kvark_ros.core.config import load_config
    config = replace(load_config(ROOT / "config" / "panda.yaml"), model_dir=str(ROOT / "models" / "panda"))
    return config, load_model(config.model_dir, config.joint_names)


def test_run_observer_keeps_the_mahalanobis_statistic_of_the_full_covariance(committed):
    """On the committed contact bag: with the truth, every estimate has eᵀP⁻¹e ≥ max_j e_j² / P_jj (the whole
    vector's statistic bounds every one-joint one, an identity of the full P that the diagonal alone cannot
    give), metrics' vector coverage is its share under χ²_7(0.95); without a covariance or a truth, None."""
    config, trained = committed
    run, inputs = read_inputs(ROOT / "bags" / "panda_contact", config)
    truth = ground_truth(RobotModel.from_config(config), config, run, inputs, None)
    result = run_observer(config, trained, inputs, "kvark", truth_tau=truth.tau_ext)
    rows = result.valid & np.isfinite(truth.tau_ext).all(axis=1)
    distance = result.mahalanobis[rows]
    assert np.isfinite(distance).all() and np.isnan(result.mahalanobis[~result.valid]).all()
    one_joint = (((result.tau_ext - truth.tau_ext) / result.tau_std)[rows] ** 2).max(axis=1)
    assert np.all(distance >= one_joint * (1.0 - 1e-9))
    entry = observer_metrics(result, truth, inputs.stamp)
    assert entry["vector_coverage95"] == pytest.approx(np.mean(distance <= chi2.ppf(0.95, N)), abs=1e-6)
    assert run_observer(config, trained, inputs, "momentum", truth_tau=truth.tau_ext).mahalanobis is None
    assert run_observer(config, trained, inputs, "kvark").mahalanobis is None


def test_real_benchmark_reports_per_joint_and_vector_coverage_of_zero(committed):
    """The --real path's evaluate and report on the held-out 30 % of a committed contact-free bag with the
    committed model (the benchmark's own training is test_real_benchmark's): the new figures per observer and
    model, in results' entries and in report.md."""
    config, trained = committed
    inputs = read_inputs(ROOT / "bags" / "panda_excitation_2", config)[1]
    held = split(inputs, 0.7, 500.0)[1]
    entries = evaluate(config, trained, held, ["kvark", "kf", "momentum"], lambda _line: None)
    for name in ("kvark", "kf"):
        entry = entries[name]
        assert len(entry["coverage95_per_joint"]) == N and 0.0 <= entry["vector_coverage95"] <= 1.0, name
        assert 0.0 <= entry["any_joint_miss_share"] <= 1.0 and entry["reliability"]["vector"] is not None, name
    assert entries["momentum"]["vector_coverage95"] is None
    results = {"bag": "panda_excitation_2", "train_share": 0.7, "torque_source": held.torque_source,
               "joint_names": list(config.joint_names), "rate_hz": 500.0,
               "samples": {"train": 0, "held_out": len(held)}, "nominal": entries, "augmented": entries,
               "augmentation": {"effects": [], "gap_before": 0.0, "gap_after": 0.0}}
    text = report(results)
    assert "| vector coverage95 of 0 | any-joint miss of 0 |" in text
    assert text.count("| kvark |") == 1 and "| kvark, nominal |" in text and "| kf, augmented |" in text
    assert "| momentum, nominal |" not in text and "| observer, model | panda_joint1 |" in text
    kvark = entries["kvark"]
    assert f"{kvark['vector_coverage95']:.3f} / {kvark['vector_coverage95']:.3f}" in text
    assert "1 − 0.95^7 = 0.302" in text
