"""Figures for people: training fits (paper Figs. 3-5) and replay time histories (Figs. 7, 9)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend first: no display on robots or CI)
import numpy as np  # noqa: E402

from kvark_ros.core.inputs import EstimatorInputs  # noqa: E402
from kvark_ros.core.model_store import TrainedModel  # noqa: E402
from kvark_ros.core.robot_model import RobotModel  # noqa: E402

MAX_POINTS = 4000   # scatter points per joint, so figures stay light


def _grid(n: int) -> tuple[plt.Figure, np.ndarray]:
    cols = 4 if n > 6 else 3
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes.flat


def plot_training(robot: RobotModel, trained: TrainedModel, segments: Sequence[EstimatorInputs],
                  out: Path) -> list[Path]:
    """Residual torque against velocity with each model's mean ± 2σ, one panel per joint.

    A joint whose KMP also takes the pose (q or g(q)) has no single curve over q̇: its KMP mean is drawn at
    the data's own samples instead."""
    from kvark_ros.core.training import training_data
    data = training_data(robot, segments)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(data.qd), size=min(MAX_POINTS, len(data.qd)), replace=False)
    models = {"KMP": trained.residual, **{name.upper(): m for name, m in trained.baselines.items()}}
    fig, axes = _grid(robot.n)
    for j, ax in enumerate(axes[: robot.n]):
        ax.scatter(data.qd[pick, j], data.tau_r[pick, j], s=2, color="0.6", label="data")
        grid = np.zeros((200, robot.n))
        grid[:, j] = np.linspace(data.qd[:, j].min(), data.qd[:, j].max(), 200)
        for name, model in models.items():
            if name == "KMP" and trained.residual.inputs[j] != "qd":
                mean = model.predict_batch(data.qd[pick], data.q[pick], data.g[pick])[0]
                ax.scatter(data.qd[pick, j], mean[:, j], s=2, label=f"KMP ({trained.residual.inputs[j]}) at the data")
                continue
            mean, var = (model.predict_batch(grid, np.zeros_like(grid), np.zeros_like(grid)) if name == "KMP"
                         else model.predict_batch(grid))     # a q̇-only joint's curve does not depend on q, g
            line, = ax.plot(grid[:, j], mean[:, j], label=name)
            if name == "KMP":
                band = 2.0 * np.sqrt(var[:, j])
                ax.fill_between(grid[:, j], mean[:, j] - band, mean[:, j] + band, alpha=0.25,
                                color=line.get_color(), label="KMP ± 2σ")
        ax.set_title(robot.joint_names[j], fontsize=9)
        ax.set_xlabel("velocity (rad/s)")
        ax.set_ylabel("residual (N·m)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    path = out / "training_residuals.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return [path]


HIGHLIGHTED = "kvark"     # the estimate drawn above the other observers


def plot_time_histories(stamp: np.ndarray, truth: np.ndarray | None, estimates: Mapping[str, np.ndarray],
                        labels: Sequence[str], ylabel: str, path: Path,
                        stddev: Mapping[str, np.ndarray] | None = None) -> Path:
    """Truth and each observer's estimate over time, one panel per component (joint or axis).

    Layered so that what people look for stays visible: the baselines thin and underneath, K-VARK above them,
    the ground truth on top (a noisy residual-free observer drawn last would hide both)."""
    fig, axes = _grid(len(labels))
    t = stamp - stamp[0]
    for j, ax in enumerate(axes[: len(labels)]):
        if truth is not None:
            ax.plot(t, truth[:, j], color="k", lw=1.5, label="ground truth", zorder=5)
        for name, values in estimates.items():
            best = name == HIGHLIGHTED
            line, = ax.plot(t, values[:, j], lw=1.2 if best else 0.6, alpha=1.0 if best else 0.7,
                            zorder=4 if best else 2, label=name)
            if stddev is not None and name in stddev:
                ax.fill_between(t, values[:, j] - 1.96 * stddev[name][:, j], values[:, j] + 1.96 * stddev[name][:, j],
                                color=line.get_color(), alpha=0.15)
        ax.set_title(labels[j], fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel(ylabel)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_error_bars(metrics: Mapping[str, Mapping[str, float]], key: str, ylabel: str, path: Path) -> Path:
    """One bar per observer for a scalar metric (e.g. mean joint RMSE)."""
    names = [name for name in metrics if metrics[name].get(key) is not None]
    fig, ax = plt.subplots(figsize=(max(4, 0.7 * len(names)), 3))
    ax.bar(names, [metrics[name][key] for name in names], color="tab:blue")
    ax.set_ylabel(ylabel)
    ax.tick_params(axis="x", rotation=45)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
