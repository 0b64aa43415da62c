"""Markdown reports with tables and figures for replays and benchmarks."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from kvark_ros.core.contact_events import contact_onsets, touching
from kvark_ros.core.files import write_text_atomically
from kvark_ros.tools.colours import colour_word
from kvark_ros.tools.plots import (
    HIGHLIGHTED,
    INSET_HALF_WIDTH,
    MAX_INSETS,
    UNOBSERVED_LABEL,
    plot_error_bars,
    plot_errors,
    plot_reliability,
    plot_time_histories,
)

PLOTTED_OBSERVERS = ("kvark", "kf", "momentum", "oracle")   # time histories stay readable with a few lines
AXES = ("Fx (N)", "Fy (N)", "Fz (N)", "Mx (N·m)", "My (N·m)", "Mz (N·m)")
NOT_AT_SENSOR = "n/a (contact not at the sensor)"


def _cell(value: Any, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _span(values: Sequence[float] | None) -> str:
    """'min–max' of per-joint values, '–' without them."""
    return "–" if not values else f"{min(values):.3f}–{max(values):.3f}"


def metrics_table(observers: Mapping[str, Mapping[str, Any]]) -> str:
    """One row per observer: joint RMSE, force/moment RMSE (NOT_AT_SENSOR without a true wrench on any sample),
    |error| statistics, coverage (all joint samples, the worst and best joint, the whole vector), speed."""
    keys = ("joint_rmse_mean", "force_rmse_mean", "moment_rmse_mean", "mean_abs", "p95", "max", "temporal_std",
            "coverage95")
    header = ("| observer | joint RMSE (N·m) | force RMSE (N) | moment RMSE (N·m) | mean abs | p95 | max | "
              "temporal std | coverage95 | coverage95 per joint min–max | vector coverage95 | µs/step |")
    lines = [header, "|" + "---|" * (len(keys) + 4)]
    for name, entry in observers.items():
        cells = [_cell(entry.get(key)) for key in keys]
        if entry.get("wrench_truth_samples") == 0:       # a true wrench on no sample: nothing to compare with
            cells[1:3] = [NOT_AT_SENSOR] * 2
        cells += [_span(entry.get("coverage95_per_joint")), _cell(entry.get("vector_coverage95")),
                  _cell(entry.get("us_per_step"))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def calibration_table(observers: Mapping[str, Mapping[str, Any]]) -> str:
    """One row per observer with a covariance and ground truth: coverage95 per joint, of the whole vector, the
    share of samples with a miss on any joint against its nominal, and the reliability table; '' without any."""
    rows = [(name, entry) for name, entry in observers.items() if entry.get("coverage95_per_joint")]
    if not rows:
        return ""
    levels = " / ".join(f"{level:g}" for level in rows[0][1]["reliability"]["nominal"])
    lines = ["| observer | coverage95 per joint | vector coverage95 | any-joint miss (nominal) | "
             f"joint coverage at {levels} | vector coverage at {levels} |", "|---|---|---|---|---|---|"]
    for name, entry in rows:
        table = entry["reliability"]
        lines.append(f"| {name} | {' '.join(_cell(v) for v in entry['coverage95_per_joint'])} | "
                     f"{_cell(entry['vector_coverage95'])} | {_cell(entry['any_joint_miss_share'])} "
                     f"({_cell(entry['any_joint_miss_nominal'])}) | {' / '.join(_cell(v) for v in table['joint'])} | "
                     + (" / ".join(_cell(v) for v in table["vector"]) if table["vector"] else "–") + " |")
    return "\n".join(lines)


def contact_table(observers: Mapping[str, Mapping[str, Any]]) -> str:
    """One row per observer: the contact flag against the truth (metrics' ``contact``), or '' without truth."""
    rows = [(name, entry["contact"]) for name, entry in observers.items() if entry.get("contact")]
    if not rows:
        return ""
    lines = ["| observer | false contact share | contact-free samples | onsets | missed | mean delay (s) |",
             "|---|---|---|---|---|---|"]
    for name, c in rows:
        lines.append(f"| {name} | {_cell(c['false_contact_share'], 4)} | {c['contact_free_samples']} | "
                     f"{c['onsets']} | {c['missed_onsets']} | {_cell(c['detection_delay_mean'])} |")
    return "\n".join(lines)


def best_observer(observers: Mapping[str, Mapping[str, Any]]) -> str | None:
    """The observer with the lowest mean joint RMSE, the oracle aside (it runs on the plant's own model); None
    without ground truth."""
    scored = {name: entry["joint_rmse_mean"] for name, entry in observers.items()
              if name != "oracle" and entry.get("joint_rmse_mean") is not None}
    return min(scored, key=scored.get) if scored else None


def wrench_truth_note(truth: Any) -> str:
    """What the force and moment RMSE are over, for the report: '' when the true wrench is known on every sample
    with a true τ_ext, else how many samples the wrist sensor observes and how many of those are in contact."""
    if truth is None or truth.wrench is None:
        return ""
    known = np.isfinite(truth.tau_ext).all(axis=1)
    observed = known & np.isfinite(truth.wrench).all(axis=1)
    if observed.sum() == known.sum():
        return ""
    why = (f"a push on a link before the flange, which the sensor cannot see; shaded \"{UNOBSERVED_LABEL}\" in "
           "`wrench.png`")
    if not observed.any():
        return (f"The wrist F/T sensor observes the external wrench on none of the {int(known.sum())} samples ({why}): "
                f"no true wrench, force and moment RMSE {NOT_AT_SENSOR}.")
    in_contact = int((observed & touching(truth.tau_ext)).sum())
    return (f"Force and moment RMSE only over the {int(observed.sum())} of {int(known.sum())} samples where the "
            f"wrist F/T sensor observes the external wrench: on the other {int(known.sum() - observed.sum())} ({why}) "
            "there is no true wrench. " + (f"{in_contact} of the observed samples are in contact." if in_contact else
                                           "None of the observed samples is in contact: the force RMSE is the false "
                                           "force in free motion."))


def write_replay_report(out: Path, metrics: Mapping[str, Any], robot: Any, inputs: Any, truth: Any,
                        results: Sequence[Any]) -> list[Path]:
    """report.md and figures for one replay: τ_ext and wrench time histories (the wrench's 95 % band from Σ_F; its
    truth left out and shaded where the wrist sensor does not observe the contact), and with ground truth the τ_ext
    error over time and the RMSE bars; insets zoom on the first contact onsets of the truth."""
    best = best_observer(metrics["observers"])
    plotted = ({r.name: r for r in results if r.name in PLOTTED_OBSERVERS or r.name == best}
               or {results[0].name: results[0]})
    tau = {n: np.where(r.valid[:, None], r.tau_ext, np.nan) for n, r in plotted.items()}
    onsets = contact_onsets(inputs.stamp, truth.tau_ext, MAX_INSETS) if truth is not None else np.zeros(0)
    names = robot.joint_names
    wrench_truth = None if truth is None or truth.wrench is None else truth.wrench
    unobserved = (None if wrench_truth is None else
                  np.isfinite(truth.tau_ext).all(axis=1) & ~np.isfinite(wrench_truth).all(axis=1))
    figures = [
        plot_time_histories(inputs.stamp, None if truth is None else truth.tau_ext, tau, names, "τ_ext (N·m)",
                            out / "joint_torques.png", stddev={n: r.tau_std for n, r in plotted.items()
                                                               if r.tau_std is not None},
                            best=best, onsets=onsets, title="External joint torque"),
        plot_time_histories(inputs.stamp, wrench_truth,
                            {n: np.where(r.valid[:, None], r.wrench, np.nan) for n, r in plotted.items()},
                            AXES, "external wrench", out / "wrench.png", best=best, onsets=onsets,
                            stddev={n: r.wrench_std for n, r in plotted.items() if r.wrench_std is not None},
                            title="External wrench", unobserved=unobserved),
    ]
    if truth is not None:
        figures.append(plot_errors(inputs.stamp, truth.tau_ext, tau, names, "estimate − truth (N·m)",
                                   out / "joint_errors.png", best=best, onsets=onsets,
                                   title="Error of the external joint torque"))
        figures.append(plot_error_bars(metrics["observers"], "joint_rmse_mean", "joint RMSE (N·m)",
                                       out / "joint_rmse.png"))
        reliability = plot_reliability(metrics["observers"], out / "reliability.png")
        figures += [reliability] if reliability is not None else []
    text = [f"# Replay of `{metrics['bag']}`", "",
            f"- ground truth: {metrics['ground_truth']}",
            f"- {metrics['samples']} samples over {metrics['duration_s']} s; τ_m from {metrics['torque_source']}; "
            f"{metrics['dropped_samples']} samples without a fresh command dropped",
            f"- bag decoding: {metrics['decode_seconds']} s", "",
            metrics_table(metrics["observers"]), ""]
    note = wrench_truth_note(truth)
    text += [note, ""] if note else []
    contact = contact_table(metrics["observers"])
    if contact:
        text += ["Contact flag (true contact: |τ_ext| > 0.5 N·m on a joint; contact-free: none, and 0.2 s after "
                 "the last):", "", contact, ""]
    calibration = calibration_table(metrics["observers"])
    if calibration:
        text += ["Calibration of the reported covariance (coverage95: share of samples inside ±1.96 σ; vector: "
                 "inside the χ²_n 95 % ellipsoid of the full covariance; any-joint miss: share of samples with a "
                 "miss on some joint, nominal 1 − 0.95ⁿ for independent joints):", "", calibration, ""]
    text += [figure_notes(list(plotted), best, truth is not None, len(onsets),
                          any(path.name == "reliability.png" for path in figures)), ""]
    text += [f"![{path.stem}]({path.name})" for path in figures]
    write_text_atomically(out / "report.md", "\n".join(text) + "\n")
    return figures


def figure_notes(plotted: Sequence[str], best: str | None, has_truth: bool, onsets: int,
                 reliability: bool = False) -> str:
    """What the figures show, for the report, each observer's colour named from the one mapping the figures use
    (``colours``); ``reliability``: whether reliability.png was drawn."""
    highlighted = list(dict.fromkeys(name for name in (best, HIGHLIGHTED) if name in plotted))
    notes = (f"Figures: {', '.join(f'{name} ({colour_word(name)})' for name in plotted)}, each in the same colour "
             "in every figure; "
             + (f"the observer with the lowest joint RMSE, {best}, thickest and on top, " if best else "")
             + (("K-VARK under it, " if best else "K-VARK above the others, ")
                if HIGHLIGHTED in plotted and HIGHLIGHTED != best else "")
             + f"the others thin underneath; 95 % bands (±1.96 σ) of {' and '.join(highlighted) or 'none'} where "
             "they report a covariance, cut at the panel's edge (a thick mark of their colour there) where wider "
             "than the panel.")
    if not has_truth:
        return notes + (" No ground truth: no error figure, no RMSE bars, no reliability diagram, no contact-onset "
                        "insets.")
    notes += (" The ground truth is black, drawn on top. `joint_errors.png`: the estimate minus the truth "
              f"over time. {onsets} contact onset(s) zoomed in insets (±{INSET_HALF_WIDTH} s, at most {MAX_INSETS}).")
    if reliability:
        notes += (" `reliability.png`: observed against nominal coverage of every observer with a covariance, solid "
                  "per joint (±z σ), dashed for the whole vector (χ²_n ellipsoid); on the dotted diagonal the "
                  "reported uncertainty is honest, below it too confident, above it too cautious.")
    return notes
