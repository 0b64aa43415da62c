"""``kvark benchmark --real``'s figures: what replay draws, on the held-out part of a contact-free recording.

The true external torque there is zero, so an estimate is its own error: per model (nominal, augmented) one figure
of the false τ_ext over time (the zero truth black on top, the observer with the lowest false τ_ext drawn thick
above K-VARK and the baselines, the 95 % bands of those two), the reliability diagram (coverage of zero) and the
RMSE bars, in the observers' colours of every other figure. With ``--pushes``, one more figure: τ_ext over the
held-out part with the pushes superposed, their true τ_ext black on top, a zoomed inset at each push's onset
(augmented model). The observers drawn are stepped once more (the benchmark keeps only their metrics; the same
inputs give the same estimates).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.contact_events import contact_onsets
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.files import write_text_atomically
from kvark_ros.tools.colours import colour_word
from kvark_ros.tools.plots import MAX_INSETS, plot_error_bars, plot_reliability, plot_time_histories
from kvark_ros.tools.real_pushes import Pushes
from kvark_ros.tools.replay import run_observer
from kvark_ros.tools.report import PLOTTED_OBSERVERS, best_observer


def _torque_figure(path: Path, config: EstimatorConfig, inputs: EstimatorInputs, truth: np.ndarray,
                   trained: TrainedModel, observers: Mapping[str, Mapping[str, Any]], ylabel: str, title: str,
                   onsets: Sequence[float] = ()) -> tuple[Path, str | None, list[str]]:
    """τ_ext over ``inputs`` against ``truth`` (T, n) N·m, the best of ``observers`` (their metrics) and the usual few
    stepped once more and drawn (module docstring): the path, the best observer and the observers drawn."""
    best = best_observer(observers)
    drawn = [name for name in observers if name in PLOTTED_OBSERVERS or name == best]
    runs = {name: run_observer(config, trained, inputs, name, truth_tau=truth) for name in drawn}
    return plot_time_histories(
        inputs.stamp, truth, {name: np.where(r.valid[:, None], r.tau_ext, np.nan) for name, r in runs.items()},
        config.joint_names, ylabel, path, stddev={name: r.tau_std for name, r in runs.items() if r.tau_std is not None},
        best=best, onsets=onsets, title=title), best, drawn


def _model_figures(out: Path, config: EstimatorConfig, held: EstimatorInputs, trained: TrainedModel, label: str,
                   observers: Mapping[str, Mapping[str, Any]]) -> tuple[list[Path], str | None, list[str]]:
    """One model's figures (module docstring): the paths, the best observer and the observers drawn over time."""
    torques, best, drawn = _torque_figure(
        out / f"joint_torques_{label}.png", config, held, np.zeros(held.q.shape), trained, observers,
        "false τ_ext (N·m)", f"External joint torque on the held-out part, {label} model (truth: zero, contact-free)")
    figures = [torques, plot_error_bars(observers, "joint_rmse_mean", "false τ_ext RMSE (N·m)",
                                        out / f"joint_rmse_{label}.png")]
    reliability = plot_reliability(observers, out / f"reliability_{label}.png")
    return figures + ([reliability] if reliability is not None else []), best, drawn


def write_real_figures(out: Path, config: EstimatorConfig, held: EstimatorInputs, models: Mapping[str, TrainedModel],
                       results: Mapping[str, Any], pushes: Pushes | None = None) -> list[Path]:
    """The figures of every model in ``models`` (label → trained model; ``results[label]``: its observers'
    metrics) and of the ``pushes`` (``results["pushes"]``, augmented model) under ``out``, and a section naming them
    appended to ``out``/report.md."""
    figures, notes = [], []
    for label, trained in models.items():
        paths, best, drawn = _model_figures(out, config, held, trained, label, results[label])
        figures += paths
        notes.append(f"{label}: {', '.join(f'{name} ({colour_word(name)})' for name in drawn)}"
                     + (f"; lowest false τ_ext RMSE {best}, drawn thickest on top" if best else ""))
    if pushes is not None:
        truth = pushes.truth.tau_ext
        path, best, drawn = _torque_figure(
            out / "joint_torques_pushes.png", config, pushes.inputs, truth, models["augmented"],
            results["pushes"]["observers"], "τ_ext (N·m)",
            "External joint torque on the held-out part with known pushes superposed, augmented model",
            contact_onsets(pushes.inputs.stamp, truth, MAX_INSETS))
        figures.append(path)
        notes.append(f"with the pushes (`joint_torques_pushes.png`, their true τ_ext black on top): "
                     f"{', '.join(f'{name} ({colour_word(name)})' for name in drawn)}"
                     + (f"; lowest τ_ext RMSE {best}, drawn thickest on top" if best else ""))
    text = ["", "## Figures", "",
            "The held-out part, where the true external torque is zero (black, on top): every estimate is error. "
            "Each observer has the same colour in every figure; 95 % bands (±1.96 σ) of the best observer and "
            "K-VARK, cut at the panel's edge (a thick mark of their colour there) where wider than the panel. "
            "`reliability_*.png`: observed against nominal coverage of zero, solid per joint, dashed for the whole "
            "vector; below the diagonal σ is too small. Drawn over time: " + "; ".join(notes) + ".", "",
            *(f"![{path.stem}]({path.name})" for path in figures)]
    report = out / "report.md"
    write_text_atomically(report, report.read_text() + "\n".join(text) + "\n")
    return figures
