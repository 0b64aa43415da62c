"""Figures for people: training fits (paper Figs. 3-5), replay time histories with zoomed insets at contact
onsets, and estimation errors over time (Figs. 7, 9).

Each observer keeps its colour in every figure (``colours``); the ground truth is black. Every interval is the
95 % one (±1.96 σ).

Figures are built with ``matplotlib.figure.Figure`` and rendered by Agg straight to PNG: no pyplot (its import
alone costs more than drawing a figure), no display, no global state, so plotting stays a small part of a replay.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.tools.colours import TRUTH_COLOUR, observer_colour
from kvark_ros.tools.metrics import Z95

MAX_POINTS = 4000        # scatter points per joint, so figures stay light
DPI = 90
HIGHLIGHTED = "kvark"    # the estimate drawn above the other observers (the best one aside)
TRUTH_STYLE = {"color": TRUTH_COLOUR, "lw": 1.0, "zorder": 5}
BAND_LABEL = "95 % band"
UNOBSERVED_LABEL = "not observed by the sensor"
UNOBSERVED_STYLE = {"color": "0.86", "lw": 0, "zorder": 0}
CLIPPED_NOTE = "95 % band clipped at the thick edge marks"
BAND_ROOM = 0.25         # a band may widen a panel by this share of its lines' span on either side, no more
TRUTH_LABEL = "ground truth"
_LEGEND_TAIL = (BAND_LABEL, UNOBSERVED_LABEL)    # legend entries after the lines
INSET_HALF_WIDTH = 0.15  # s either side of a contact onset
MAX_INSETS = 3           # per figure
INSET_SIZE = (0.235, 0.56)                    # width, height in axes fractions
INSET_SLOTS = tuple((x, y) for y in (0.36, 0.03) for x in (0.01, 0.255, 0.505, 0.755))   # one inset per column
PANEL_HEIGHT = 1.7       # in, one time-history panel
PNG = {"pil_kwargs": {"compress_level": 3}}   # zlib level 3: ~0.1 s less per replay than the default 6, ~6 % larger
FIGURE_WIDTH = 11.0      # in


def _grid(n: int) -> tuple[Figure, np.ndarray]:
    cols = 4 if n > 6 else 3
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(4 * cols, 3 * rows), dpi=DPI)
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes.flat


def plot_training(robot: RobotModel, trained: TrainedModel, segments: Sequence[EstimatorInputs],
                  out: Path) -> list[Path]:
    """Residual torque against velocity with each model's mean and the KMP's 95 % band, one panel per joint.

    A joint whose KMP also takes the pose (q or g(q)) has no single curve over q̇: its KMP mean is drawn at
    the data's own samples instead."""
    from kvark_ros.core.learning.training import training_data
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
                band = Z95 * np.sqrt(var[:, j])
                ax.fill_between(grid[:, j], mean[:, j] - band, mean[:, j] + band, alpha=0.25,
                                color=line.get_color(), label=f"KMP {BAND_LABEL}")
        ax.set_title(robot.joint_names[j], fontsize=9)
        ax.set_xlabel("velocity (rad/s)")
        ax.set_ylabel("residual (N·m)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    path = out / "training_residuals.png"
    fig.savefig(path, **PNG)
    return [path]


def _styles(names: Sequence[str], best: str | None) -> dict[str, dict]:
    """Line style per observer in its own colour: the best observer thick on top, K-VARK under it, the rest thin
    underneath (a noisy baseline drawn last would hide both)."""
    styles = {}
    for name in names:
        if name == best:
            styles[name] = {"color": observer_colour(name), "lw": 1.7, "alpha": 1.0, "zorder": 4}
        elif name == HIGHLIGHTED:
            styles[name] = {"color": observer_colour(name), "lw": 1.2, "alpha": 0.95, "zorder": 3}
        else:
            styles[name] = {"color": observer_colour(name), "lw": 0.5, "alpha": 0.45, "zorder": 2}   # faint: context
    return styles


def _stack(n: int, title: str, ylabel: str) -> tuple[Figure, np.ndarray]:
    """One full-width panel per component on a shared time axis (a contact shows at the same x in every
    joint), fixed margins instead of tight_layout (which draws the figure twice)."""
    height = PANEL_HEIGHT * n + 1.1
    fig = Figure(figsize=(FIGURE_WIDTH, height), dpi=DPI)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    fig.subplots_adjust(left=0.08, right=0.985, top=1.0 - 0.8 / height, bottom=0.5 / height, hspace=0.25)
    fig.suptitle(title, y=1.0 - 0.08 / height, fontsize=11)
    fig.supylabel(ylabel, fontsize=10)
    for ax in axes[:-1]:
        ax.xaxis.set_visible(False)   # the bottom panel's time axis serves all; ticks are costly to build
    axes[-1].set_xlabel("time (s)")
    axes[-1].xaxis.set_major_locator(MaxNLocator(10, steps=[1, 2, 5, 10]))
    return fig, axes


def _fit_lines(ax: Axes, lines: Sequence[np.ndarray], bands: Sequence[tuple[np.ndarray, np.ndarray, str]] = ()) -> None:
    """y-limits around the lines, widened for the 95 % bands (lower, upper, colour) by at most ``BAND_ROOM`` of the
    lines' span on either side: a filter's first samples have a huge variance, a sticking joint's band is its whole
    static friction band, and either would flatten the lines (``_mark_clipped`` marks the cut)."""
    finite = np.concatenate(lines)
    finite = finite[np.isfinite(finite)]
    if not len(finite):
        return
    low, high = finite.min(), finite.max()
    pad = 0.05 * (high - low) or 0.1
    room = max(BAND_ROOM * (high - low), pad)
    band_low = min((np.nanmin(lower) for lower, _, _ in bands if np.isfinite(lower).any()), default=np.inf)
    band_high = max((np.nanmax(upper) for _, upper, _ in bands if np.isfinite(upper).any()), default=-np.inf)
    ax.set_ylim(max(min(low - pad, band_low), low - room), min(max(high + pad, band_high), high + room))


def _mark_clipped(ax: Axes, t: np.ndarray, bands: Sequence[tuple[np.ndarray, np.ndarray, str]]) -> None:
    """Where a 95 % band (lower, upper, colour) leaves the panel, a thick mark of its colour on that edge, and a
    note in the panel's right title: the band is cut, not that narrow."""
    low, high = ax.get_ylim()
    edge = ax.get_xaxis_transform()          # x in data, y in axes fractions
    clipped = False
    for lower, upper, colour in bands:
        for beyond, y in ((upper > high, 1.0), (lower < low, 0.0)):
            if not beyond.any():
                continue
            wide = beyond.copy()             # one sample either side: a lone clipped sample still draws a mark
            wide[1:] |= beyond[:-1]
            wide[:-1] |= beyond[1:]
            ax.plot(t, np.where(wide, y, np.nan), transform=edge, color=colour, lw=3.0, solid_capstyle="butt",
                    clip_on=False, zorder=6)
            clipped = True
    if clipped:
        ax.set_title(CLIPPED_NOTE, loc="right", fontsize=7, pad=2, color="0.3")


def _free_slot(ax: Axes, t: np.ndarray, values: np.ndarray, onset: float, used: set) -> tuple[float, float]:
    """The inset slot of ``ax`` covering the fewest drawn samples (``values`` (T, k)), away from the onset itself."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    xs = ((t - x0) / (x1 - x0))[:, None]
    ys = (values - y0) / (y1 - y0)
    at = (onset - x0) / (x1 - x0)
    best, fewest = INSET_SLOTS[0], np.inf
    for slot in INSET_SLOTS:
        if slot[0] in used or slot[0] - 0.03 <= at <= slot[0] + INSET_SIZE[0] + 0.03:
            continue
        inside = np.count_nonzero((xs >= slot[0]) & (xs <= slot[0] + INSET_SIZE[0])
                                  & (ys >= slot[1]) & (ys <= slot[1] + INSET_SIZE[1]))
        if inside < fewest:
            best, fewest = slot, inside
    used.add(best[0])
    return best


def _insets(axes: np.ndarray, t: np.ndarray, drawn: list[list[tuple[np.ndarray, dict]]], focus: np.ndarray,
            onsets: Sequence[float], stamp0: float) -> None:
    """A zoomed inset (±INSET_HALF_WIDTH s) at each onset, in the panel whose ``focus`` (T, n) moves most there;
    its y-range fits the truth and the highlighted estimates (a far-off baseline may leave it)."""
    used: dict[int, set] = {}
    for onset in np.asarray(onsets)[:MAX_INSETS] - stamp0:
        rows = slice(*np.searchsorted(t, [onset - INSET_HALF_WIDTH, onset + INSET_HALF_WIDTH]))
        window = focus[rows]
        spread = [np.ptp(column[np.isfinite(column)]) if np.isfinite(column).any() else -1.0 for column in window.T]
        if len(window) < 2 or max(spread) < 0.0:
            continue
        j = int(np.argmax(spread))
        key = [values for values, style in drawn[j] if style["zorder"] >= 3] or [values for values, _ in drawn[j]]
        x, y = _free_slot(axes[j], t, np.column_stack(key), onset, used.setdefault(j, set()))
        inset = axes[j].inset_axes([x, y, *INSET_SIZE], zorder=6)
        for values, style in drawn[j]:
            inset.plot(t[rows], values[rows], **style)
        near = np.concatenate([values[rows] for values in key])
        if np.isfinite(near).any():
            low, high = np.nanmin(near), np.nanmax(near)
            pad = 0.1 * (high - low) or 0.1
            inset.set_ylim(low - pad, high + pad)
        inset.set_xlim(t[rows][0], t[rows][-1])
        inset.tick_params(labelsize=6, pad=1)
        inset.set_title(f"onset at {onset:.2f} s", fontsize=7, pad=2)
        axes[j].indicate_inset_zoom(inset, edgecolor="0.35")


def _histories(stamp: np.ndarray, truth: np.ndarray | None, estimates: Mapping[str, np.ndarray],
               labels: Sequence[str], ylabel: str, title: str, path: Path, stddev: Mapping[str, np.ndarray],
               best: str | None, onsets: Sequence[float], focus: np.ndarray | None,
               unobserved: np.ndarray | None = None) -> Path:
    """Time histories, one panel per component: the truth (black, on top) or a zero line, the best observer and
    K-VARK with their 95 % bands (clipped to the panel, marked where cut), the other observers thin underneath,
    insets at the onsets, and the ``unobserved`` (T,) samples (no truth there) shaded."""
    fig, axes = _stack(len(labels), title, ylabel)
    t = stamp - stamp[0]
    styles = _styles(list(estimates), best)
    drawn: list[list[tuple[np.ndarray, dict]]] = []
    for j, ax in enumerate(axes):
        lines, bands = [], []
        if unobserved is not None and unobserved.any():
            ax.fill_between(t, 0.0, 1.0, where=unobserved, transform=ax.get_xaxis_transform(),
                            label=UNOBSERVED_LABEL, **UNOBSERVED_STYLE)
        if truth is not None:
            lines.append((truth[:, j], TRUTH_STYLE))
            ax.plot(t, truth[:, j], label=TRUTH_LABEL, **TRUTH_STYLE)
        else:
            ax.axhline(0.0, color=TRUTH_COLOUR, lw=0.6, zorder=1)
        for name, values in estimates.items():
            style = styles[name]
            lines.append((values[:, j], style))
            ax.plot(t, values[:, j], label=f"{name} (lowest RMSE)" if name == best else name, **style)
            if name in stddev and style["zorder"] >= 3:
                half = Z95 * stddev[name][:, j]
                bands.append((values[:, j] - half, values[:, j] + half, style["color"]))
                ax.fill_between(t, bands[-1][0], bands[-1][1], color=style["color"], alpha=0.15, lw=0, zorder=1,
                                label=BAND_LABEL if len(bands) == 1 else None)
        drawn.append(lines)
        _fit_lines(ax, [values for values, _ in lines], bands)
        _mark_clipped(ax, t, bands)
        ax.set_title(labels[j], fontsize=9, loc="left", pad=2)
        ax.tick_params(labelsize=8)
        ax.yaxis.set_major_locator(MaxNLocator(4))   # few ticks: each is a Line2D and a Text to build and draw
    if focus is not None and len(onsets):
        _insets(axes, t, drawn, focus, onsets, float(stamp[0]))
    handles, names = axes[0].get_legend_handles_labels()
    entries = dict(zip(names, handles))
    order = [TRUTH_LABEL, *(name for name in names if name not in (TRUTH_LABEL, *_LEGEND_TAIL)), *_LEGEND_TAIL]
    names = [name for name in order if name in entries]          # the truth, the observers, then what shades
    handles = [entries[name] for name in names]
    fig.legend(handles, names, loc="upper center", ncol=len(names), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - 0.3 / fig.get_figheight()))
    fig.savefig(path, **PNG)
    return path


def plot_time_histories(stamp: np.ndarray, truth: np.ndarray | None, estimates: Mapping[str, np.ndarray],
                        labels: Sequence[str], ylabel: str, path: Path, *,
                        stddev: Mapping[str, np.ndarray] | None = None, best: str | None = None,
                        onsets: Sequence[float] = (), title: str = "", unobserved: np.ndarray | None = None) -> Path:
    """Truth and each observer's estimate over time, one panel per component (a joint by name, or an axis).

    Layered so that what people look for stays visible: the baselines thin and underneath, K-VARK above them,
    the ``best`` observer above that, the ground truth on top (a noisy residual-free observer drawn last would
    hide both); the 95 % bands (``stddev``: σ per observer) of the best and K-VARK; a zoomed inset at each of the
    first ``MAX_INSETS`` ``onsets`` (stamps); the ``unobserved`` (T,) samples, where the truth is unknown (a push
    the wrist sensor cannot see), shaded and labelled."""
    return _histories(stamp, truth, estimates, labels, ylabel, title or ylabel, path, stddev or {}, best, onsets,
                      truth, unobserved)


def plot_errors(stamp: np.ndarray, truth: np.ndarray, estimates: Mapping[str, np.ndarray], labels: Sequence[str],
                ylabel: str, path: Path, *, best: str | None = None, onsets: Sequence[float] = (),
                title: str = "") -> Path:
    """Each observer's estimation error (estimate − truth) over time, one panel per component, layered as
    ``plot_time_histories`` about a zero line, with insets at the ``onsets`` (where a slow observer lags)."""
    errors = {name: values - truth for name, values in estimates.items()}
    return _histories(stamp, None, errors, labels, ylabel, title or ylabel, path, {}, best, onsets, truth)


def plot_error_bars(metrics: Mapping[str, Mapping[str, float]], key: str, ylabel: str, path: Path) -> Path:
    """One bar per observer for a scalar metric (e.g. mean joint RMSE), each in its observer's colour."""
    names = [name for name in metrics if metrics[name].get(key) is not None]
    fig = Figure(figsize=(max(4, 0.7 * len(names)), 3), dpi=DPI)
    ax = fig.subplots()
    ax.bar(names, [metrics[name][key] for name in names], color=[observer_colour(name) for name in names])
    ax.set_ylabel(ylabel)
    ax.set_xticks(np.arange(len(names)), names, rotation=45, ha="right", rotation_mode="anchor")   # under its bar
    fig.tight_layout()
    fig.savefig(path, **PNG)
    return path


def plot_reliability(observers: Mapping[str, Mapping], path: Path) -> Path | None:
    """Reliability diagram: observed against nominal coverage (metrics' ``reliability``) of every observer that
    reports a covariance, in its colour, solid for the per-joint ±z σ intervals, dashed for the χ²_n ellipsoid of
    the whole vector (one legend entry per observer, one per line style); the diagonal is perfect calibration,
    below it too confident, above it too cautious. None (nothing written) when no observer has a reliability
    table."""
    tables = {name: entry["reliability"] for name, entry in observers.items() if entry.get("reliability")}
    if not tables:
        return None
    fig = Figure(figsize=(7.4, 4.6), dpi=DPI)                 # room for the legend beside the square axes
    ax = fig.subplots()
    diagonal, = ax.plot([0, 1], [0, 1], color="0.5", lw=0.8, ls=":", label="perfect calibration")
    handles, names = [diagonal], [diagonal.get_label()]
    for name, style in _styles(list(tables), None).items():
        table = tables[name]
        style = {**style, "lw": 2.4 if name == HIGHLIGHTED else 1.0}
        joint, = ax.plot(table["nominal"], table["joint"], marker="o", ms=3, label=f"{name} per joint", **style)
        handles.append(joint)
        names.append(name)
        if table.get("vector") is not None:
            ax.plot(table["nominal"], table["vector"], marker="s", ms=3, ls="--", label=f"{name} vector", **style)
    handles += [Line2D([], [], color="0.3", marker="o", ms=3, lw=1.0),
                Line2D([], [], color="0.3", marker="s", ms=3, lw=1.0, ls="--")]
    names += ["solid: per joint (±z σ)", "dashed: whole vector (χ²ₙ)"]
    observed = [value for t in tables.values() for value in [*t["joint"], *(t.get("vector") or [])]]
    low = np.floor(10.0 * min(0.4, *observed)) / 10.0     # from 0.4, or lower to show a far too confident one
    middle, gap = low + 0.3 * (1.0 - low), 0.01 * (1.0 - low)   # where no nominal level (≥ 0.5) has a point
    for side, words in ((-1, "below: σ too small"), (1, "above: σ too large")):
        ax.text(middle - side * gap, middle + side * gap, words, rotation=45, rotation_mode="anchor", ha="center",
                va="top" if side < 0 else "bottom", fontsize=7, color="0.4")
    ax.set_xlim(low, 1.0)
    ax.set_ylim(low, 1.0)
    ax.set_aspect("equal")
    ax.set_xlabel("nominal coverage")
    ax.set_ylabel("observed coverage")
    ax.set_title("Calibration of the reported covariance", fontsize=10)
    ax.legend(handles, names, fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path, **PNG)
    return path
