"""``kvark diagnose``'s figures, all on the held-out samples of the selection's filtered basis:

* ``gap_per_joint.png``: held-out gap RMSE per joint before and after the augmentation;
* ``gap_over_time.png``: the gap τ_m − τ_EL over time per joint, before (the nominal model) and after;
* ``effect_contributions.png``: each named effect's torque contribution, as its RMS per joint (grouped bars)
  beside the gap before and after, so what each effect explains reads off one figure;
* ``residual_vs_velocity.png``, ``residual_vs_position.png``: the gap before/after against q̇ and q.

Built with ``matplotlib.figure.Figure`` (no pyplot, no display), rendered by Agg.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from kvark_ros.core.estimation.robot_model import RobotModel

Diagnosis = Any   # a diagnosis_report.Diagnosis (not imported: diagnosis_report imports this module)

DPI = 90
BEFORE = {"color": "0.55", "lw": 0.8}
AFTER = {"color": "C3", "lw": 1.0, "label": "after augmentation"}
PANEL_HEIGHT = 1.5     # in, one time-history panel


def effect_contributions(diag: Diagnosis) -> dict[str, np.ndarray]:
    """Each accepted effect's torque on the held-out samples (T, n) N·m: its regressor times its θ (the sum of all
    of them is the gap before minus the gap after)."""
    return {term.name: term.design(diag.held) @ theta for term, theta in zip(diag.terms, diag.theta)}


def _before(diag: Diagnosis) -> str:
    """Legend label of the gap before: of the nominal model, or of the base model diagnose ran --against."""
    return "before (nominal model)" if not diag.result.get("against") else "before (the --against model)"


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    return path


def _gap_bars(diag: Diagnosis, names: list[str], path: Path) -> Path:
    """Held-out gap RMSE per joint, before and after, side by side."""
    r = diag.result
    fig = Figure(figsize=(1.2 * len(names) + 3, 3.8))
    ax = fig.subplots()
    x = np.arange(len(names))
    ax.bar(x - 0.2, r["gap_before"]["joint_rmse"], 0.4, color=BEFORE["color"], label=_before(diag))
    ax.bar(x + 0.2, r["gap_after"]["joint_rmse"], 0.4, color=AFTER["color"], label=AFTER["label"])
    ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("held-out gap RMSE (N·m)")
    ax.set_title("Model gap per joint", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def _gap_over_time(diag: Diagnosis, names: list[str], path: Path) -> Path:
    """One panel per joint on a shared time axis (held-out parts of the recordings end to end)."""
    n = len(names)
    dt = diag.sample_interval
    t = np.arange(len(diag.held)) * (dt or 1.0)
    height = PANEL_HEIGHT * n + 1.1
    fig = Figure(figsize=(11.0, height))
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    fig.subplots_adjust(left=0.08, right=0.985, top=1.0 - 0.8 / height, bottom=0.5 / height, hspace=0.25)
    fig.suptitle(f"Model gap τ_m − τ_EL on the held-out samples; {diag.result['gap_filtering']}",
                 y=1.0 - 0.08 / height, fontsize=10)
    fig.supylabel("gap (N·m)", fontsize=10)
    for j, ax in enumerate(axes):
        ax.plot(t, diag.held.gap[:, j], zorder=2, label=_before(diag), **BEFORE)
        ax.plot(t, diag.held_after[:, j], zorder=3, **AFTER)
        ax.axhline(0.0, color="k", lw=0.5, zorder=1)
        ax.set_title(names[j], fontsize=9, loc="left", pad=2)
        ax.tick_params(labelsize=8)
        ax.yaxis.set_major_locator(MaxNLocator(4))
        if j < n - 1:
            ax.xaxis.set_visible(False)
    axes[-1].set_xlabel("held-out time (s), recordings end to end" if dt else "held-out sample")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=2, fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - 0.3 / height))
    return _save(fig, path)


def _contribution_bars(diag: Diagnosis, names: list[str], path: Path) -> Path:
    """RMS of each effect's torque per joint, grouped by joint, with the gap before and after as markers."""
    contributions = effect_contributions(diag)
    n, k = len(names), len(contributions)
    width = 0.8 / k
    x = np.arange(n)
    fig = Figure(figsize=(max(6.0, 1.3 * n + 2), 4.2))
    ax = fig.subplots()
    for i, (effect, torque) in enumerate(contributions.items()):
        ax.bar(x - 0.4 + (i + 0.5) * width, np.sqrt(np.mean(np.square(torque), axis=0)), width,
               color=f"C{i % 10}", label=effect)
    ax.plot(x, diag.result["gap_before"]["joint_rmse"], "_", color="k", ms=22, mew=2, label=f"gap {_before(diag)}")
    ax.plot(x, diag.result["gap_after"]["joint_rmse"], "_", color="C3", ms=22, mew=2, label="gap after")
    ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("RMS on held-out samples (N·m)")
    ax.set_title("Torque of each named effect", fontsize=10)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return _save(fig, path)


def _scatter(diag: Diagnosis, names: list[str], values: np.ndarray, label: str, path: Path) -> Path:
    """The gap before and after against ``values`` (T, n), one panel per joint: what it still depends on."""
    n = len(names)
    cols = 4 if n > 6 else 3
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(4 * cols, 3 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for j, axj in enumerate(axes.flat):
        if j >= n:
            axj.set_visible(False)
            continue
        axj.scatter(values[:, j], diag.held.gap[:, j], s=2, alpha=0.4, color=BEFORE["color"], label=_before(diag))
        axj.scatter(values[:, j], diag.held_after[:, j], s=2, alpha=0.4, color=AFTER["color"], label=AFTER["label"])
        axj.set_title(names[j], fontsize=9)
        axj.set_xlabel(label)
        axj.set_ylabel("gap (N·m)")
    axes.flat[0].legend(markerscale=4, fontsize=8)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.5 / fig.get_figheight(), top=1.0 - 0.3 / fig.get_figheight(),
                        wspace=0.3, hspace=0.45)   # fixed margins: tight_layout would draw the figure twice
    return _save(fig, path)


def plot_diagnosis(diag: Diagnosis, robot: RobotModel, out: Path) -> list[Path]:
    """Every figure of the module docstring that applies (no contribution figure without an effect)."""
    names = list(robot.joint_names)
    paths = [_gap_bars(diag, names, out / "gap_per_joint.png"), _gap_over_time(diag, names, out / "gap_over_time.png")]
    if diag.terms:
        paths.append(_contribution_bars(diag, names, out / "effect_contributions.png"))
    paths.append(_scatter(diag, names, diag.held.qd, "joint velocity (rad/s)", out / "residual_vs_velocity.png"))
    paths.append(_scatter(diag, names, diag.held.q, "joint position (rad)", out / "residual_vs_position.png"))
    return paths
