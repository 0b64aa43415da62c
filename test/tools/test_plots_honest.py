"""Plots that do not mislead (issue 27): a truth only where it is measured, one colour per observer in every figure
and in the report's words, bands cut at the panel's edge and marked there, one wording for the 95 % interval, and
``kvark benchmark --real``'s figures.

The figures are checked through their artists (the ``saved`` fixture keeps every saved figure). The wrench-truth
tests replay the committed simulated collision bag (a 20-40 N push on a link the wrist sensor cannot see).
"""
from __future__ import annotations

from itertools import combinations
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from kvark_ros.cli import build_parser
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.observer_catalog import OBSERVER_NAMES
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.colours import OBSERVER_COLOURS, TRUTH_COLOUR, colour_word, observer_colour
from kvark_ros.core.contact_events import CONTACT_TORQUE
from kvark_ros.tools.metrics import observer_metrics, wrench_metrics
from kvark_ros.tools.plots import (BAND_LABEL, BAND_ROOM, CLIPPED_NOTE, UNOBSERVED_LABEL, plot_reliability,
                                   plot_time_histories, plot_training)
from kvark_ros.tools.real_figures import write_real_figures
from kvark_ros.tools.real_pushes import pushed
from kvark_ros.tools.replay import GroundTruth, ground_truth, run_observer, zero_truth
from kvark_ros.tools.report import NOT_AT_SENSOR, metrics_table, write_replay_report, wrench_truth_note
from kvark_ros.tools.wrench_truth import explained_by_wrench

CONFIG = "config/panda.yaml"
MODEL = "models/panda"
COLLISION = "bags/panda_collision"
EXCITATION = "bags/panda_excitation_1"
NAMES = ("arm_shoulder", "arm_elbow", "arm_wrist")


def _lab(colour: str) -> np.ndarray:
    """CIELAB (D65) of a matplotlib colour, for the perceptual distance ΔE (CIE76) between two colours."""
    rgb = np.array(to_rgb(colour))
    linear = np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]) @ linear
    ratio = xyz / np.array([0.95047, 1.0, 1.08883])                  # of the D65 white
    f = np.where(ratio > 0.008856, np.cbrt(ratio), 7.787 * ratio + 16 / 116)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def _panels(fig: Figure) -> list:
    return [ax for ax in fig.axes if ax.get_title(loc="left")]


def _line_colours(fig: Figure) -> dict[str, tuple]:
    """Label → RGB of every labelled line of a figure (the insets' copies carry no label)."""
    return {line.get_label().removesuffix(" (lowest RMSE)").removesuffix(" per joint"): to_rgb(line.get_color())
            for ax in fig.axes for line in ax.get_lines() if not line.get_label().startswith("_")}


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


@pytest.fixture(scope="module")
def collision(config):
    """The collision bag replayed by K-VARK and kf with the committed model: robot, inputs, truth, runs."""
    trained = load_model(MODEL, config.joint_names)
    robot = RobotModel.from_config(config, trained.augmentation)
    run, inputs = read_inputs(COLLISION, config)
    truth = ground_truth(robot, config, run, inputs, None)
    runs = [run_observer(config, trained, inputs, name, truth_tau=truth.tau_ext) for name in ("kvark", "kf")]
    return robot, inputs, truth, runs


# --------------------------------------------------------------------------- one colour per observer

def test_every_catalog_observer_has_its_own_colour_apart_from_the_others_and_from_the_truth():
    assert list(OBSERVER_COLOURS) == list(OBSERVER_NAMES)             # every observer, in catalog order
    colours = [observer_colour(name) for name in OBSERVER_NAMES]
    assert len({to_rgb(c) for c in colours}) == len(colours)          # one-to-one
    assert len({colour_word(name) for name in OBSERVER_NAMES}) == len(OBSERVER_NAMES)
    assert to_rgb(TRUTH_COLOUR) == (0.0, 0.0, 0.0) and TRUTH_COLOUR not in colours
    for a, b in combinations([*colours, TRUTH_COLOUR], 2):            # no near-duplicates (tab20's light twins)
        assert np.linalg.norm(_lab(a) - _lab(b)) >= 25.0, (a, b)
    assert colour_word("kvark") == "blue" and colour_word("kf") == "orange"


def test_an_observer_keeps_its_colour_whatever_else_a_figure_draws(tmp_path, saved):
    stamp = np.arange(500) / 500.0
    truth = np.zeros((500, 3))
    noisy = {name: 0.1 * np.random.default_rng(i).standard_normal((500, 3)) for i, name in enumerate(OBSERVER_NAMES)}
    few = {name: noisy[name] for name in ("kf", "sh_akfmo")}
    plot_time_histories(stamp, truth, few, NAMES, "τ", tmp_path / "a.png")
    plot_time_histories(stamp, truth, noisy, NAMES, "τ", tmp_path / "b.png", best="sh_akfmo")
    few, every = (_line_colours(fig) for fig in saved)
    assert few["kf"] == every["kf"] == to_rgb(observer_colour("kf"))
    assert few["sh_akfmo"] == every["sh_akfmo"] != every["kf"]        # kf and sh_akfmo were both orange
    assert every["ground truth"] == (0.0, 0.0, 0.0)


def test_report_names_the_colour_each_figure_draws_and_the_reliability_legend_has_one_entry_per_observer(
        collision, tmp_path, saved):
    robot, inputs, truth, runs = collision
    metrics = {"bag": COLLISION, "ground_truth": truth.kind, "samples": len(inputs), "duration_s": 5.0,
               "torque_source": inputs.torque_source, "dropped_samples": 0, "decode_seconds": 0.0,
               "observers": {r.name: observer_metrics(r, truth, inputs.stamp) for r in runs}}
    metrics["observers"]["kf"]["joint_rmse_mean"] = 0.0          # kf the best: it is drawn on top, not K-VARK
    figures = write_replay_report(tmp_path, metrics, robot, inputs, truth, runs)
    by_name = dict(zip((path.name for path in figures), saved))
    for name in ("joint_torques.png", "wrench.png", "joint_errors.png", "reliability.png"):
        colours = _line_colours(by_name[name])
        assert colours["kvark"] == to_rgb(observer_colour("kvark")), name
        assert colours["kf"] == to_rgb(observer_colour("kf")), name
    bars = by_name["joint_rmse.png"].axes[0].patches
    assert [to_rgb(bar.get_facecolor()[:3]) for bar in bars] == [to_rgb(observer_colour(r.name)) for r in runs]
    for ax in _panels(by_name["joint_torques.png"]):
        z = {line.get_label(): line.get_zorder() for line in ax.get_lines()}
        assert z["ground truth"] > z["kf (lowest RMSE)"] > z["kvark"]   # the best on top, under the truth only
    legend = by_name["reliability.png"].axes[0].get_legend()
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels[1:3] == ["kvark", "kf"] and len(labels) == 2 + 3    # observers, the diagonal, two line styles
    text = (tmp_path / "report.md").read_text()
    assert "kvark (blue)" in text and "kf (orange)" in text and "lowest joint RMSE, kf," in text
    assert " red" not in text


# --------------------------------------------------------------------------- a truth only where it is measured

def test_the_wrist_sensor_does_not_observe_a_push_on_a_link(collision, config):
    robot, inputs, truth, _ = collision
    known = np.isfinite(truth.wrench).all(axis=1)
    touching = (np.abs(truth.tau_ext) > CONTACT_TORQUE).any(axis=1)
    assert touching.sum() > 50                                         # the push
    assert not known[touching].any()                                   # its 0 N reading is no truth
    assert known[~touching].mean() > 0.99                              # free motion is observed: both zero
    # a wrench at the end effector is observed; the same torque with no wrench is not
    q = inputs.q[:3]
    wrench = np.array([[10.0, -5.0, 20.0, 1.0, 0.5, -0.2]] * 3)
    tau = np.array([robot.jacobian(qk, config.wrench.frame).T @ w for qk, w in zip(q, wrench)])
    assert explained_by_wrench(robot, config.wrench.frame, q, tau, wrench).all()
    assert not explained_by_wrench(robot, config.wrench.frame, q, tau, np.zeros_like(wrench)).any()


def test_force_rmse_counts_only_observed_samples_and_is_na_for_a_push_on_a_link(collision):
    robot, inputs, truth, runs = collision
    kvark = runs[0]
    entry = observer_metrics(kvark, truth, inputs.stamp)
    observed = kvark.valid & np.isfinite(truth.wrench).all(axis=1)
    assert entry["wrench_truth_samples"] == observed.sum() < kvark.valid.sum()
    expected = np.sqrt(np.mean((kvark.wrench[observed, :3] - truth.wrench[observed, :3]) ** 2, axis=0))
    np.testing.assert_allclose(entry["force_rmse"], expected, atol=1e-6)
    # only the push (no true torque elsewhere): no sample with a true wrench, no force RMSE, and the report says why
    push = (np.abs(truth.tau_ext) > CONTACT_TORQUE).any(axis=1)
    push_truth = GroundTruth(truth.kind, np.where(push[:, None], truth.tau_ext, np.nan), truth.wrench)
    only_push = observer_metrics(kvark, push_truth, inputs.stamp)
    none = wrench_metrics(kvark.wrench, np.full_like(truth.wrench, np.nan), kvark.valid)
    assert none == {"wrench_truth_samples": 0, "force_rmse": None, "moment_rmse": None, "force_rmse_mean": None,
                    "moment_rmse_mean": None}
    assert only_push["wrench_truth_samples"] == 0 and only_push["force_rmse_mean"] is None
    assert metrics_table({"kvark": only_push}).count(NOT_AT_SENSOR) == 2       # force and moment cells
    assert f"on none of the {push.sum()} samples" in wrench_truth_note(push_truth)
    assert wrench_truth_note(push_truth).endswith(f"force and moment RMSE {NOT_AT_SENSOR}.")


def test_wrench_figure_leaves_the_unobserved_truth_out_shades_it_and_draws_the_best_band(collision, tmp_path,
                                                                                         saved):
    robot, inputs, truth, runs = collision
    metrics = {"bag": COLLISION, "ground_truth": truth.kind, "samples": len(inputs), "duration_s": 5.0,
               "torque_source": inputs.torque_source, "dropped_samples": 0, "decode_seconds": 0.0,
               "observers": {r.name: observer_metrics(r, truth, inputs.stamp) for r in runs}}
    figures = write_replay_report(tmp_path, metrics, robot, inputs, truth, runs)
    wrench = dict(zip((path.name for path in figures), saved))["wrench.png"]
    unobserved = ~np.isfinite(truth.wrench).all(axis=1)
    for ax in _panels(wrench):
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert np.isnan(np.asarray(lines["ground truth"].get_ydata())[unobserved]).all()
        labels = [collection.get_label() for collection in ax.collections]
        assert UNOBSERVED_LABEL in labels and BAND_LABEL in labels      # the shaded span, K-VARK's Σ_F band
    legend = [text.get_text() for text in wrench.legends[0].get_texts()]
    assert legend[0] == "ground truth" and legend[-2:] == [BAND_LABEL, UNOBSERVED_LABEL]
    text = (tmp_path / "report.md").read_text()
    assert f"only over the {int((~unobserved).sum())} of {len(inputs)} samples" in text
    assert "None of the observed samples is in contact" in text


# --------------------------------------------------------------------------- bands cut at the panel's edge

def test_a_band_wider_than_the_lines_is_clipped_to_the_panel_and_marked(tmp_path, saved):
    stamp = np.arange(1000) / 500.0
    truth = np.zeros((1000, 3))
    truth[400:600, 0] = 2.0
    kvark = truth + 0.05
    std = np.full((1000, 3), 0.001)
    std[100:300, 0] = 50.0                       # a sticking joint's static friction band on the first joint
    plot_time_histories(stamp, truth, {"kvark": kvark}, NAMES, "τ", tmp_path / "t.png", stddev={"kvark": std})
    fig, = saved
    first, second, _ = _panels(fig)
    low, high = first.get_ylim()
    span = 2.05                                  # of the lines: the truth 0 to 2, K-VARK 0.05 to 2.05
    assert -BAND_ROOM * span <= low < 0.0 and 2.05 < high <= 2.05 + BAND_ROOM * span   # not the ±98 N·m band
    assert first.get_title(loc="right") == CLIPPED_NOTE and not second.get_title(loc="right")
    marks = [line for line in first.get_lines() if line.get_transform() == first.get_xaxis_transform()]
    assert {float(np.nanmax(line.get_ydata())) for line in marks} == {0.0, 1.0}     # both edges
    assert all(to_rgb(line.get_color()) == to_rgb(observer_colour("kvark")) for line in marks)
    cut = np.isfinite(np.asarray(marks[0].get_ydata(), dtype=float))
    assert cut[100:300].all() and not cut[310:].any()


# --------------------------------------------------------------------------- one wording: 95 %

def test_training_figure_calls_its_band_95_percent_and_nothing_2_sigma(config, tmp_path, saved):
    trained = load_model(MODEL, config.joint_names)
    robot = RobotModel.from_config(config, trained.augmentation)
    inputs = read_inputs(EXCITATION, config)[1]
    plot_training(robot, trained, [inputs.take(np.arange(0, len(inputs), 4))], tmp_path)
    plot_reliability({"kvark": {"reliability": {"nominal": [0.5, 0.95], "joint": [0.5, 0.9], "vector": None}}},
                     tmp_path / "r.png")
    texts = [text.get_text() for fig in saved for ax in fig.axes
             for text in (*ax.texts, ax.title, ax.xaxis.label, ax.yaxis.label,
                          *(ax.get_legend().get_texts() if ax.get_legend() else ()))]
    assert "KMP 95 % band" in texts
    assert not [text for text in texts if "2σ" in text or "2 σ" in text or "± 2" in text]


# --------------------------------------------------------------------------- kvark benchmark --real

def test_real_benchmark_figures_draw_the_zero_truth_and_the_best_on_top_and_are_named_in_the_report(
        config, tmp_path, saved):
    trained = load_model(MODEL, config.joint_names)
    inputs = read_inputs(EXCITATION, config)[1]
    held = inputs.take(np.arange(len(inputs) // 2, len(inputs)))
    truth = zero_truth(held, "contact-free")
    entries = {name: observer_metrics(run_observer(config, trained, held, name, truth_tau=truth.tau_ext), truth,
                                      held.stamp) for name in ("kvark", "kf", "momentum")}
    best = min(entries, key=lambda name: entries[name]["joint_rmse_mean"])
    (tmp_path / "report.md").write_text("# Real recording\n")
    figures = write_real_figures(tmp_path, config, held, {"nominal": trained}, {"nominal": entries})
    assert [path.name for path in figures] == ["joint_torques_nominal.png", "joint_rmse_nominal.png",
                                               "reliability_nominal.png"]
    assert all(path.is_file() for path in figures)
    torques = saved[0]
    for ax in _panels(torques):
        lines = {line.get_label().removesuffix(" (lowest RMSE)"): line for line in ax.get_lines()
                 if not line.get_label().startswith("_")}          # not the marks of a clipped band
        np.testing.assert_array_equal(lines["ground truth"].get_ydata(), 0.0)
        others = [line.get_zorder() for name, line in lines.items() if name not in (best, "ground truth")]
        assert lines["ground truth"].get_zorder() > lines[best].get_zorder() > max(others)
    text = (tmp_path / "report.md").read_text()
    assert text.startswith("# Real recording\n") and "![joint_torques_nominal](joint_torques_nominal.png)" in text
    assert f"{best} ({colour_word(best)})" in text
    args = build_parser("benchmark").parse_args(["benchmark", "--real", "bag", "--out", "out", "--no-plots"])
    assert args.no_plots


def test_the_push_figure_draws_the_pushes_true_torque_on_top_and_is_named_in_the_report(config, tmp_path, saved):
    trained = load_model(MODEL, config.joint_names)
    inputs = read_inputs(EXCITATION, config)[1]
    held = inputs.take(np.arange(len(inputs) // 2, len(inputs)))           # 4 s: one push
    pushes = pushed(RobotModel.from_config(config), config.wrench.frame, held, 20.0)
    truth = pushes.truth
    entries = {name: observer_metrics(run_observer(config, trained, pushes.inputs, name, truth_tau=truth.tau_ext),
                                      truth, held.stamp) for name in ("kvark", "kf")}
    zero = zero_truth(held, "contact-free")
    free = {name: observer_metrics(run_observer(config, trained, held, name, truth_tau=zero.tau_ext), zero, held.stamp)
            for name in ("kvark", "kf")}
    (tmp_path / "report.md").write_text("# Real recording\n")
    figures = write_real_figures(tmp_path, config, held, {"augmented": trained},
                                 {"augmented": free, "pushes": {"observers": entries}}, pushes)
    assert figures[-1].name == "joint_torques_pushes.png" and figures[-1].is_file()
    for ax, joint_truth in zip(_panels(saved[-1]), truth.tau_ext.T):
        lines = {line.get_label().removesuffix(" (lowest RMSE)"): line for line in ax.get_lines()
                 if not line.get_label().startswith("_")}
        np.testing.assert_array_equal(lines["ground truth"].get_ydata(), joint_truth)   # the pushes' τ_ext, not 0
        assert lines["ground truth"].get_zorder() > max(line.get_zorder() for name, line in lines.items()
                                                        if name != "ground truth")
    assert "![joint_torques_pushes](joint_torques_pushes.png)" in (tmp_path / "report.md").read_text()

def test_replay_report_without_a_wrench_truth_note_when_every_sample_is_observed(tmp_path, saved):
    stamp = np.arange(500) / 500.0
    runs = [SimpleNamespace(name="kvark", valid=np.ones(500, bool), tau_ext=np.zeros((500, 3)), tau_std=None,
                            wrench=np.zeros((500, 6)), wrench_std=np.full((500, 6), 0.1))]
    truth = GroundTruth("zero", np.zeros((500, 3)), np.zeros((500, 6)))
    metrics = {"bag": "b", "ground_truth": "zero", "samples": 500, "duration_s": 1.0, "torque_source": "x",
               "dropped_samples": 0, "decode_seconds": 0.0, "observers": {"kvark": {"joint_rmse_mean": 0.0}}}
    write_replay_report(tmp_path, metrics, SimpleNamespace(joint_names=NAMES), SimpleNamespace(stamp=stamp), truth,
                        runs)
    assert "only over the" not in (tmp_path / "report.md").read_text()
    wrench = saved[1]
    assert all(UNOBSERVED_LABEL not in [c.get_label() for c in ax.collections] for ax in _panels(wrench))
