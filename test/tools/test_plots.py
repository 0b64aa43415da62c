"""Figures people read (issue 15, scope 7): replay time histories with contact-onset insets and error figures,
the diagnosis figures, and the progress lines of the long steps.

The figures are checked through their artists (a ``Figure.savefig`` wrapper keeps every saved figure): the layer
order (z-order) of the lines, the joint names in titles and legends, where the insets go. Everything runs on
synthetic data except the diagnosis progress test (one short simulated run).
"""
from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from kvark_ros.core.learning import training
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.gap.diagnosis_plots import effect_contributions, plot_diagnosis
from kvark_ros.gap.diagnosis_report import Diagnosis
from kvark_ros.gap.effects import Priors, Signals, Term
from kvark_ros.core.contact_events import contact_onsets
from kvark_ros.tools.plots import INSET_HALF_WIDTH, MAX_INSETS, plot_errors, plot_time_histories
from kvark_ros.tools.report import best_observer, write_replay_report
from kvark_ros.tools.synthetic import synthetic_stream

RATE = 500.0
NAMES = ("arm_shoulder", "arm_elbow", "arm_wrist")
INDEX_LABEL = re.compile(r"^(joint\s*)?\d+$")   # a bare or "joint 3"-style index, where a name belongs


def _truth(stamp: np.ndarray, contacts: list[tuple[float, float, int, float]]) -> np.ndarray:
    """A true τ_ext (T, 3): 0.05 N·m noise plus each (start, end, joint, torque) contact."""
    rng = np.random.default_rng(0)
    tau = 0.05 * rng.standard_normal((len(stamp), len(NAMES)))
    for start, end, joint, torque in contacts:
        tau[(stamp >= start) & (stamp < end), joint] += torque
    return tau


def _panels(fig: Figure) -> list[Axes]:
    """The figure's component panels (not the insets, which are children of a panel)."""
    return [ax for ax in fig.axes if ax.get_title(loc="left")]


def _insets(ax: Axes) -> list[Axes]:
    return list(ax.child_axes)


# --------------------------------------------------------------------------- replay figures

def _estimates(stamp: np.ndarray, truth: np.ndarray) -> dict[str, np.ndarray]:
    """kvark close to the truth, kf a lagged copy, momentum noisy."""
    rng = np.random.default_rng(1)
    lag = int(0.03 * RATE)
    return {"kvark": truth + 0.02 * rng.standard_normal(truth.shape),
            "kf": np.vstack((np.zeros((lag, truth.shape[1])), truth[:-lag])),
            "momentum": truth + 0.3 * rng.standard_normal(truth.shape)}


def test_time_histories_draw_the_truth_on_top_of_the_best_on_top_of_kvark_on_top_of_the_baselines(tmp_path, saved):
    stamp = np.arange(int(8 * RATE)) / RATE
    contacts = [(1.0 + 1.5 * i, 1.6 + 1.5 * i, i % 3, 3.0) for i in range(5)]      # five onsets
    truth = _truth(stamp, contacts)
    estimates = _estimates(stamp, truth)
    onsets = contact_onsets(stamp, truth, limit=10)
    assert len(onsets) == 5
    path = plot_time_histories(stamp, truth, estimates, NAMES, "τ_ext (N·m)", tmp_path / "tau.png",
                               stddev={"kvark": np.full(truth.shape, 0.1), "momentum": np.full(truth.shape, 0.1)},
                               best="kf", onsets=onsets, title="External joint torque")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig, = saved
    panels = _panels(fig)
    assert [ax.get_title(loc="left") for ax in panels] == list(NAMES)
    for ax in panels:
        lines = {line.get_label(): line for line in ax.get_lines()}
        truth_z, kvark_z = lines["ground truth"].get_zorder(), lines["kvark"].get_zorder()
        best_z, other_z = lines["kf (lowest RMSE)"].get_zorder(), lines["momentum"].get_zorder()
        assert truth_z > best_z > kvark_z > other_z
        assert lines["kf (lowest RMSE)"].get_linewidth() > lines["kvark"].get_linewidth() \
            > lines["momentum"].get_linewidth()
        assert len(ax.collections) == 1            # the 95 % band of kvark only: a baseline gets none
    legend, = fig.legends
    assert [text.get_text() for text in legend.get_texts()] == ["ground truth", "kvark", "kf (lowest RMSE)",
                                                                 "momentum", "95 % band"]
    texts = [text for ax in fig.axes for text in (ax.get_title(), ax.get_title(loc="left"), ax.get_xlabel(),
                                                   ax.get_ylabel())]
    assert not [text for text in texts if INDEX_LABEL.match(text.strip())]
    # at most MAX_INSETS insets, each in the panel of the joint that carries the contact, spanning ±0.15 s
    insets = [(j, inset) for j, ax in enumerate(panels) for inset in _insets(ax)]
    assert len(insets) == MAX_INSETS
    for (j, inset), (start, _, joint, _) in zip(sorted(insets, key=lambda item: item[1].get_xlim()[0]), contacts):
        assert j == joint
        np.testing.assert_allclose(inset.get_xlim(), [start - INSET_HALF_WIDTH, start + INSET_HALF_WIDTH],
                                   atol=2.0 / RATE)


def test_error_figure_shows_estimate_minus_truth_about_zero(tmp_path, saved):
    stamp = np.arange(int(3 * RATE)) / RATE
    truth = _truth(stamp, [(1.0, 2.0, 1, 2.0)])
    estimates = _estimates(stamp, truth)
    plot_errors(stamp, truth, estimates, NAMES, "estimate − truth (N·m)", tmp_path / "errors.png", best="kf",
                onsets=contact_onsets(stamp, truth))
    fig, = saved
    panels = _panels(fig)
    for j, ax in enumerate(panels):
        lines = {line.get_label(): line for line in ax.get_lines()}
        np.testing.assert_allclose(lines["kvark"].get_ydata(), estimates["kvark"][:, j] - truth[:, j])
        assert lines["kf (lowest RMSE)"].get_zorder() > lines["kvark"].get_zorder() > lines["momentum"].get_zorder()
    assert len(_insets(panels[1])) == 1 and not _insets(panels[0]) and not _insets(panels[2])


def _replay_objects(truth_tau: np.ndarray | None, stamp: np.ndarray) -> tuple:
    """What replay hands write_replay_report, built by hand: metrics, robot, inputs, truth, results."""
    estimates = _estimates(stamp, truth_tau if truth_tau is not None else np.zeros((len(stamp), len(NAMES))))
    valid = np.ones(len(stamp), dtype=bool)
    results = [SimpleNamespace(name=name, valid=valid, tau_ext=values, tau_std=None,
                               wrench=np.zeros((len(stamp), 6)), wrench_std=None) for name, values in estimates.items()]
    rmse = {"kvark": 0.2, "kf": 0.1, "momentum": 0.3}
    observers = {name: ({"joint_rmse_mean": rmse[name]} if truth_tau is not None else {}) for name in estimates}
    metrics = {"bag": "synthetic", "ground_truth": "none" if truth_tau is None else "topic", "samples": len(stamp),
               "duration_s": float(stamp[-1]), "torque_source": "effort_commands", "dropped_samples": 0,
               "decode_seconds": 0.0, "observers": observers}
    truth = None if truth_tau is None else SimpleNamespace(tau_ext=truth_tau, wrench=np.zeros((len(stamp), 6)))
    return metrics, SimpleNamespace(joint_names=NAMES), SimpleNamespace(stamp=stamp), truth, results


def test_replay_report_draws_the_error_figure_only_with_ground_truth(tmp_path, saved):
    stamp = np.arange(int(3 * RATE)) / RATE
    truth = _truth(stamp, [(1.0, 2.0, 1, 2.0)])
    with_truth, without = tmp_path / "with", tmp_path / "without"
    with_truth.mkdir()
    without.mkdir()
    metrics, robot, inputs, gt, results = _replay_objects(truth, stamp)
    assert best_observer(metrics["observers"]) == "kf"
    figures = write_replay_report(with_truth, metrics, robot, inputs, gt, results)
    assert [path.name for path in figures] == ["joint_torques.png", "wrench.png", "joint_errors.png",
                                               "joint_rmse.png"]
    text = (with_truth / "report.md").read_text()
    assert "(joint_errors.png)" in text and "1 contact onset(s)" in text and "lowest joint RMSE, kf," in text

    saved.clear()
    metrics, robot, inputs, gt, results = _replay_objects(None, stamp)
    assert best_observer(metrics["observers"]) is None
    figures = write_replay_report(without, metrics, robot, inputs, gt, results)
    assert [path.name for path in figures] == ["joint_torques.png", "wrench.png"]
    assert not (without / "joint_errors.png").exists()
    assert "No ground truth: no error figure" in (without / "report.md").read_text()
    torques = saved[0]
    assert [ax.get_title(loc="left") for ax in _panels(torques)] == list(NAMES)
    assert not any(_insets(ax) for ax in torques.axes)


# --------------------------------------------------------------------------- diagnosis figures

def _diagnosis(n: int = 3, samples: int = 400) -> Diagnosis:
    """A diagnosis by hand: a torque offset on the first two joints explains most of a synthetic gap."""
    rng = np.random.default_rng(2)
    q, qd, qdd, tau = (rng.standard_normal((samples, n)) for _ in range(4))
    held = Signals(q, qd, qdd, tau, np.zeros((samples, n)), np.zeros((samples, n, 10)), np.zeros((samples, n, n)),
                   np.zeros((samples, n, 10 * (n - 1))))
    term = Term("torque_offset", (0, 1))
    theta = np.array([0.4, -0.3])
    gap = term.design(held) @ theta + 0.05 * rng.standard_normal((samples, n))
    held = Signals(q, qd, qdd, tau, gap, held.payload_regressor, held.position_jacobian, held.link_regressor)
    after = gap - term.design(held) @ theta
    rmse = lambda r: np.sqrt(np.mean(np.square(r), axis=0)).tolist()   # noqa: E731
    result = {"gap_before": {"joint_rmse": rmse(gap)}, "gap_after": {"joint_rmse": rmse(after)},
              "gap_filtering": "150 ms Savitzky-Golay", "effects": [{"name": "torque_offset"}]}
    return Diagnosis(result, [term], [theta], held, after, 0.008)


def test_diagnosis_figures_are_written_with_joint_names(tmp_path, saved):
    diag = _diagnosis()
    paths = plot_diagnosis(diag, SimpleNamespace(joint_names=NAMES), tmp_path)
    assert [path.name for path in paths] == ["gap_per_joint.png", "gap_over_time.png", "effect_contributions.png",
                                             "residual_vs_velocity.png", "residual_vs_position.png"]
    assert all(path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for path in paths)
    bars, over_time, contributions = saved[:3]
    for fig in (bars, contributions):
        assert [label.get_text() for label in fig.axes[0].get_xticklabels()] == list(NAMES)
    assert [ax.get_title(loc="left") for ax in _panels(over_time)] == list(NAMES)
    for j, ax in enumerate(_panels(over_time)):
        before, after = ax.get_lines()[:2]
        np.testing.assert_allclose(before.get_ydata(), diag.held.gap[:, j])
        np.testing.assert_allclose(after.get_ydata(), diag.held_after[:, j])
        assert after.get_zorder() > before.get_zorder()
    np.testing.assert_allclose(over_time.axes[-1].get_lines()[0].get_xdata()[-1], 0.008 * (len(diag.held) - 1))
    # the contribution bars: the offset's RMS on the joints it acts on, nothing on the third
    heights = [patch.get_height() for patch in contributions.axes[0].patches]
    np.testing.assert_allclose(heights, [0.4, 0.3, 0.0])
    np.testing.assert_allclose(sum(effect_contributions(diag).values()), diag.held.gap - diag.held_after)


def test_a_diagnosis_without_effects_has_no_contribution_figure(tmp_path):
    diag = _diagnosis()
    diag = Diagnosis({**diag.result, "effects": []}, [], [], diag.held, diag.held.gap)
    names = [path.name for path in plot_diagnosis(diag, SimpleNamespace(joint_names=NAMES), tmp_path)]
    assert "effect_contributions.png" not in names and "gap_over_time.png" in names


# --------------------------------------------------------------------------- progress lines

class _InstantBaseline:
    """A learned baseline that predicts zero, so the trainer's baseline loop runs in no time."""

    @classmethod
    def fit(cls, qd: np.ndarray, tau_r: np.ndarray, seed: int = 0, **_options) -> "_InstantBaseline":
        return cls()

    def predict_batch(self, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros_like(qd), np.ones_like(qd)


def test_training_prints_one_line_per_step_with_counts(panda, monkeypatch):
    monkeypatch.setattr(training, "LEARNED_BASELINES", {"first": _InstantBaseline, "second": _InstantBaseline})
    stream = synthetic_stream(panda, 3.0, seed=4)
    segment = EstimatorInputs(stream.stamp, stream.q, stream.qd, stream.tau_m, "synthetic", 0)
    lines: list[str] = []
    training.train_model(panda, "panda", [segment], baselines=True, residual_inputs="qd", log=lines.append)
    assert all(line.startswith("[train] ") for line in lines)
    text = "\n".join(lines)
    assert "[train] robot model along 1 recording(s): 1500 samples" in text
    assert "[train] KMP residual of 7 joints" in text
    assert re.search(r"\[train\] baselines 1/2: first fitted and tuned \(\d+\.\d s\)", text)
    assert re.search(r"\[train\] baselines 2/2: second fitted and tuned", text)
    assert len(lines) < 15          # one line per step, never per sample


def test_diagnose_prints_its_rounds_with_joint_names(panda):
    pytest.importorskip("mujoco")
    from kvark_ros.gap.diagnose import diagnose
    from kvark_ros.io.recorded_inputs import estimator_inputs
    from kvark_ros.sim.scenarios import simulate
    offsets = [0.6, -0.5, 0.0, 0.4, 0.0, 0.0, 0.0]
    run = simulate("panda", "excitation", seed=3, duration=4.0, plant={"torque_offset": offsets}, progress=False)
    lines: list[str] = []
    diag = diagnose(panda, [estimator_inputs(run)], effects=("torque_offset", "armature"), log=lines.append,
                    priors=Priors())
    text = "\n".join(lines)
    assert "[diagnose] start 1/3: round 1: 2 of 2 effects to try on top of []" in text
    assert "[diagnose] start 1/3: round 2: 1 of 2 effects to try on top of ['torque_offset']" in text
    accepted = [line for line in lines if "accepted torque_offset" in line]
    assert accepted and "panda_joint1" in accepted[0] and "[0," not in accepted[0]
    assert re.search(r"held-out gap per joint before \(N·m\): panda_joint1 \d", text)
    assert len(lines) < 60
    np.testing.assert_allclose(sum(effect_contributions(diag).values()), diag.held.gap - diag.held_after,
                               atol=1e-9)
    assert diag.sample_interval == pytest.approx(0.008)
