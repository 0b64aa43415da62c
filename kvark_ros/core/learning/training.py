"""Training: residual models and filter tuning from contact-free recordings.

Per joint: residual ``τ_r = τ_m − τ_EL`` (paper eq. 27, accelerations by Savitzky-Golay
differentiation since recordings carry none; with a model augmentation from ``kvark diagnose``,
τ_EL is the augmented model's torque and the augmentation is stored with the model), GMM → GMR →
KMP with the length scale and λ₁ from a GP marginal-likelihood fit and λ₂ calibrated on held-out
samples (paper v2 §V-B), each joint's inputs (q̇ alone, or with q or the gravity torque g(q),
docs/method.md §3.7) chosen by the log-likelihood on the end of every recording, static filter
covariances by covariance matching (v2 §V-D), the
baselines' residual models and the momentum observers' noise levels. The robot model is
evaluated once per sample (``segment_dynamics``) and reused by every step; the joints' fits, independent of each
other, run in worker processes (``train_model``'s ``jobs``).
"""
from __future__ import annotations

import time
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
from scipy.signal import savgol_filter

from kvark_ros import __version__
from kvark_ros.core.estimation.calibration import CALIBRATED_OBSERVER, IntervalScale
from kvark_ros.core.config import FilterSettings, default_filter_settings
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.estimation.model_checks import data_source
from kvark_ros.core.estimation.observers import make_observer
from kvark_ros.core.estimation.observers.base import FilterTuning
from kvark_ros.core.estimation.observers.momentum_noise import MomentumNoise
from kvark_ros.core.estimation.residual import INPUT_KINDS, LEARNED_BASELINES, KMPResidualModel
from kvark_ros.core.estimation.residual.common import joint_workers, single_threaded
from kvark_ros.core.learning.kmp_inputs import fit_kmp, second_inputs, start_kmp_fit
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.estimation.stiction import StictionBand
from kvark_ros.core.learning.interval_factors import floor_factor, interval_scale, variance_floor
from kvark_ros.core.learning.static_band import friction_torque, identify_band
from kvark_ros.core.learning.tuning import match_covariances, virtual_measurements

N_SUPPORT = 40               # GMR support points per joint (q̇ only)
N_SUPPORT_2D = 80            # when a joint takes a second input: the points cover a curve in a plane
INPUT_MODES = ("auto",) + INPUT_KINDS     # --residual-inputs: choose per joint, or one kind for all
MIN_NLL_GAIN = 0.05          # nats per sample a second input must gain over q̇ alone to be kept
N_COMPONENTS = 20            # GMM components (paper v2: 20)
HOLDOUT = 0.2                # share held out (``--holdout``): random samples for λ₂ calibration (paper v2 §V-B) and
                             # the end of every recording to choose the inputs (contiguous, unseen motion)
COVERAGE_TARGET = 0.95       # λ₂ is set so that 95 % of held-out residuals fall in μ ± 1.96 σ
LAMBDA2_GRID = np.geomspace(1e-2, 1e8, 61)
SAVGOL_WINDOW = 0.15         # s, window of the acceleration and torque filter (75 samples at 500 Hz)
MIN_UNSEEN = 2.0             # s of unseen recording ends (4 × the 0.5 s warm-up) below which c is read in-sample only
BAND_WINDOW = 0.05           # s, the same filter for the friction the static band is read from (band_friction)


@dataclass(frozen=True)
class SegmentDynamics:
    """The robot model along one recording, evaluated once per sample, all (T, n).

    tau_el: τ_EL (+ τ_aug when augmented) at the smoothed q̈ and τ_m (eq. 27), N·m;
    p: generalized momentum M(q) q̇ (eq. 5), N·m·s; u: its model input Cᵀq̇ − g + τ_m with the
    recorded τ_m (eq. 7), N·m; g: the gravity torque g(q), N·m.
    """

    tau_el: np.ndarray
    p: np.ndarray
    u: np.ndarray
    g: np.ndarray


@dataclass(frozen=True)
class TrainingData:
    """Concatenated training samples: q (T, n) rad, q̇ (T, n) rad/s, g(q) (T, n) N·m, τ_r (T, n) N·m;
    segments keep recordings apart, dynamics holds the robot model along each of them."""

    q: np.ndarray
    g: np.ndarray
    qd: np.ndarray
    tau_r: np.ndarray
    segments: tuple[EstimatorInputs, ...]
    dynamics: tuple[SegmentDynamics, ...]


def smoothed_signals(stamp: np.ndarray, qd: np.ndarray, tau_m: np.ndarray,
                     window_time: float = SAVGOL_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """q̈ (T, n) and τ_m (T, n) through the same zero-phase Savitzky-Golay filter of ``window_time`` s.

    q̈ comes from smoothing q̇ and differentiating against the actual stamps. τ_m must be smoothed
    the same way: the controller's torque reacts to sensor noise faster than any acceleration
    filter passes, so an unsmoothed τ_m against a smoothed M q̈ leaves that jitter in the residual
    (measured on the simulated Panda: 0.5 N·m scatter on joints 1-4 with τ_m raw, see README).
    """
    dt = float(np.median(np.diff(stamp)))
    window = max(5, int(round(window_time / dt)) | 1)
    if len(stamp) <= window:
        return np.gradient(qd, stamp, axis=0), tau_m
    return (np.gradient(savgol_filter(qd, window, 3, axis=0), stamp, axis=0),
            savgol_filter(tau_m, window, 3, axis=0))


def segment_dynamics(robot: RobotModel, seg: EstimatorInputs, qdd: np.ndarray,
                     tau_smoothed: np.ndarray) -> SegmentDynamics:
    """One pass of the robot model over a recording: τ_EL at (q, q̇, q̈ (T, n) rad/s², smoothed τ_m
    (T, n) N·m) and the momentum terms at the recorded τ_m."""
    tau_el = np.empty(seg.q.shape)
    p = np.empty(seg.q.shape)
    u = np.empty(seg.q.shape)
    g = np.empty(seg.q.shape)
    for k, (q, qd, a, tau_s, tau) in enumerate(zip(seg.q, seg.qd, qdd, tau_smoothed, seg.tau_m)):
        tau_el[k] = robot.model_torque(q, qd, a, tau_s)
        p[k], u[k] = robot.momentum_terms(q, qd, tau)
        g[k] = robot.gravity(q)
    for array in (tau_el, p, u, g):
        array.setflags(write=False)
    return SegmentDynamics(tau_el, p, u, g)


def training_data(robot: RobotModel, segments: Sequence[EstimatorInputs]) -> TrainingData:
    """Residual torques ``τ_m − τ_EL`` (eq. 27; τ_EL + τ_aug when augmented) of every recording."""
    qd_all, tau_r_all, dynamics = [], [], []
    for seg in segments:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m)
        dyn = segment_dynamics(robot, seg, qdd, tau_m)
        qd_all.append(seg.qd)
        tau_r_all.append(tau_m - dyn.tau_el)
        dynamics.append(dyn)
    return TrainingData(np.concatenate([seg.q for seg in segments]), np.concatenate([dyn.g for dyn in dynamics]),
                        np.concatenate(qd_all), np.concatenate(tau_r_all), tuple(segments), tuple(dynamics))


def calibrate_lambda2(model: KMPResidualModel, qd: np.ndarray, tau_r: np.ndarray, q: np.ndarray | None = None,
                      g: np.ndarray | None = None,
                      target: float = COVERAGE_TARGET) -> tuple[KMPResidualModel, np.ndarray]:
    """Per joint, the λ₂ whose μ ± 1.96 σ interval covers ``target`` of the held-out residuals
    (q̇, τ_r and, for a model that takes them, q and g: (T, n)).

    λ₂ leaves the KMP mean alone (eq. 22) and scales the variance (eq. 23), which every candidate gets from one
    eigendecomposition per joint (``KMPResidualModel.lambda2_sweep``). Returns the calibrated model and its held-out
    coverage per joint.
    """
    hits = np.zeros((len(LAMBDA2_GRID), model.n_joints))
    for rows, mean, var in model.lambda2_sweep(qd, q, g, LAMBDA2_GRID):
        hits += np.sum(np.abs(tau_r[rows] - mean) <= 1.96 * np.sqrt(var), axis=1)
    best = np.argmin(np.abs(hits / len(qd) - target), axis=0)
    calibrated = model.with_hyperparameters(replace(model.hyper, lambda2=LAMBDA2_GRID[best]))
    mean, var = calibrated.predict_batch(qd, q, g)
    return calibrated, np.mean(np.abs(tau_r - mean) <= 1.96 * np.sqrt(var), axis=0)


def lambda2_warnings(lambda2: np.ndarray, coverage: np.ndarray, joint_names: Sequence[str]) -> list[str]:
    """A warning line per joint whose calibrated λ₂ (n,) sits at an edge of ``LAMBDA2_GRID``: its held-out
    coverage (n,) missed ``COVERAGE_TARGET`` (at the grid's low end the variance N σ_f²/λ₂ is at its largest and
    still too small; at the high end at its smallest and still too large)."""
    lines = []
    for j in np.flatnonzero((lambda2 <= LAMBDA2_GRID[0]) | (lambda2 >= LAMBDA2_GRID[-1])):
        verdict = "too large" if coverage[j] > COVERAGE_TARGET else "too small"
        lines.append(f"[train] warning: λ2 of {joint_names[j]} is at the edge of its grid ({lambda2[j]:.3g}): "
                     f"held-out coverage {coverage[j]:.2f}, not {COVERAGE_TARGET:.2f}, so its KMP variance is "
                     f"{verdict} for this data; record more varied motion or check this joint's residual")
    return lines


def _n_support(kinds: Sequence[str]) -> int:
    return N_SUPPORT if all(kind == "qd" for kind in kinds) else N_SUPPORT_2D


@single_threaded
def choose_inputs(data: TrainingData, mode: str, seed: int, log: Callable[[str], None],
                  executor: Executor | None = None,
                  holdout: float = HOLDOUT) -> tuple[tuple[str, ...], dict[str, list[float]]]:
    """Each joint's residual inputs (``INPUT_KINDS``) and the held-out log-likelihood behind the choice.

    ``mode`` ``auto``: every kind is fitted on all but the last ``holdout`` share of every recording,
    its λ₂ calibrated and its mean Gaussian log-likelihood per sample taken on that end (contiguous, so it
    measures motion the model has not seen, not interpolation between neighbouring samples); a joint keeps
    q̇ alone unless a second input gains ``MIN_NLL_GAIN``. Any other mode is one kind for every joint. The joints
    are fitted in ``executor``'s workers when given.
    """
    n = data.qd.shape[1]
    if mode in INPUT_KINDS:
        return (mode,) * n, {}
    if mode != "auto":
        raise ValueError(f"residual inputs must be one of {list(INPUT_MODES)}, got {mode!r}")
    tail = recording_ends(data, holdout)
    log(f"[train] residual inputs: fitting {', '.join(INPUT_KINDS)} on every joint ...")
    fits = {}
    for kind in sorted(INPUT_KINDS, key=lambda kind: kind == "qd"):     # the two-input fits, the longest, first
        kinds = (kind,) * n
        z = second_inputs(kinds, data.q, data.g)
        fits[kind] = start_kmp_fit(data.qd[~tail], z[~tail], data.tau_r[~tail], kinds, N_COMPONENTS,
                                   _n_support(kinds), seed, executor)
    scores: dict[str, list[float]] = {}
    for step, kind in enumerate(INPUT_KINDS, start=1):
        model, _ = calibrate_lambda2(fits[kind](), data.qd[tail], data.tau_r[tail], data.q[tail], data.g[tail])
        mean, var = model.predict_batch(data.qd[tail], data.q[tail], data.g[tail])
        loglik = np.mean(-0.5 * np.log(2.0 * np.pi * var) - 0.5 * (data.tau_r[tail] - mean) ** 2 / var, axis=0)
        scores[kind] = loglik.tolist()
        log(f"[train] residual inputs {step}/{len(INPUT_KINDS)}: {kind} fitted on every joint, λ2 calibrated")
    table = np.array([scores[kind] for kind in INPUT_KINDS])
    best = np.argmax(table, axis=0)
    chosen = tuple(INPUT_KINDS[b] if table[b, j] >= table[0, j] + MIN_NLL_GAIN else "qd" for j, b in enumerate(best))
    log(f"[train] residual inputs by held-out log-likelihood (nats/sample, last {holdout:.0%} of each "
        f"recording): " + "; ".join(f"{kind} {np.round(scores[kind], 2).tolist()}" for kind in INPUT_KINDS)
        + f" → {list(chosen)}")
    return chosen, scores


def _tuning(data: TrainingData, mean_of: Callable[[EstimatorInputs, SegmentDynamics], np.ndarray]) -> FilterTuning:
    """Covariance matching on the virtual measurements corrected by one residual model's mean."""
    ys = [virtual_measurements(dyn.p, dyn.u, seg.stamp, mean_of(seg, dyn))
          for seg, dyn in zip(data.segments, data.dynamics)]
    dt = float(np.median(np.concatenate([np.diff(seg.stamp) for seg in data.segments])))
    return match_covariances(ys, dt)


def _fit_baselines(data: TrainingData, qd_fit: np.ndarray, tau_fit: np.ndarray, kmp: KMPResidualModel, seed: int,
                   log: Callable[[str], None], executor: Executor | None) -> tuple[dict, dict]:
    """The learned baselines' residual models (fitted on q̇, τ_r (T, n) of the KMP's samples, each joint in
    ``executor``'s workers when given) and their filter tunings, by observer name."""
    # GMR-GP samples the KMP's own GMR reference (fitted with N_COMPONENTS), as in the paper.
    options = {"gmr_gp": {"n_components": N_COMPONENTS, "n_support": N_SUPPORT, "reference": kmp.reference}}
    residuals: dict = {}
    tunings: dict = {}
    for step, (name, model_class) in enumerate(LEARNED_BASELINES.items(), start=1):
        fit_started = time.perf_counter()
        residuals[name] = model_class.fit(qd_fit, tau_fit, seed=seed, executor=executor, **options.get(name, {}))
        tunings[name] = _tuning(data, lambda seg, dyn, model=residuals[name]: model.predict_batch(seg.qd)[0])
        log(f"[train] baselines {step}/{len(LEARNED_BASELINES)}: {name} fitted and tuned "
            f"({time.perf_counter() - fit_started:.1f} s)")
    return residuals, tunings


@single_threaded
def train_model(robot: RobotModel, robot_name: str, segments: Sequence[EstimatorInputs], *,
                baselines: bool = True, seed: int = 0, info: dict | None = None, residual_inputs: str = "auto",
                log: Callable[[str], None] = print, jobs: int | None = None,
                settings: FilterSettings | None = None, holdout: float = HOLDOUT) -> TrainedModel:
    """Everything the observers need, from contact-free recordings of ``robot``; ``residual_inputs`` is one
    of ``INPUT_MODES`` (``choose_inputs``); ``settings``: the ``filter.*`` keys the kvark intervals are calibrated
    with (``calibrate_intervals``; None: the defaults); ``holdout``: the share held out (``HOLDOUT``).

    The joints' fits are independent and run in ``jobs`` worker processes (None: every available core, 1: one after
    the other here), each with its own seed and one BLAS thread: the model is the same bit for bit. BLAS runs one
    thread here too (the matrices are small, see ``single_threaded_blas``).
    """
    started = time.perf_counter()
    data = training_data(robot, segments)
    log(f"[train] robot model along {len(segments)} recording(s): {len(data.qd)} samples "
        f"({time.perf_counter() - started:.1f} s)")
    with joint_workers(jobs, data.qd.shape[1]) as executor:
        kinds, selection = choose_inputs(data, residual_inputs, seed, log, executor, holdout)
        rng = np.random.default_rng(seed)
        held_out = rng.random(len(data.qd)) < holdout
        qd_fit, tau_fit = data.qd[~held_out], data.tau_r[~held_out]
        q_held, g_held = data.q[held_out], data.g[held_out]
        log(f"[train] KMP residual of {len(kinds)} joints: GMM → GMR, GP fit on {(~held_out).sum()} samples, "
            f"{held_out.sum()} held out for λ2 ...")
        kmp, coverage = fit_residual(data, kinds, ~held_out, held_out, seed, executor)
        log(f"[train] GP fit: length scale {np.round(kmp.hyper.length_scale, 3).tolist()} rad/s, "
            f"λ1 {np.round(kmp.hyper.lambda1, 4).tolist()}")
        log(f"[train] KMP λ2 {kmp.hyper.lambda2.tolist()}; held-out 95% coverage {np.round(coverage, 3).tolist()}")
        head = ~recording_ends(data, holdout)
        log(f"[train] KMP refitted on all but the last {holdout:.0%} of every recording, for the kvark intervals ...")
        head_kmp = fit_residual(data, kinds, head & ~held_out, head & held_out, seed, executor)[0]
        for line in lambda2_warnings(kmp.hyper.lambda2, coverage, robot.joint_names):
            log(line)
        tuning = _tuning(data, lambda seg, dyn: kmp.predict_batch(seg.qd, seg.q, dyn.g)[0])
        log("[train] K-VARK filter tuned by covariance matching")
        residuals, tunings = (_fit_baselines(data, qd_fit, tau_fit, kmp, seed, log, executor) if baselines
                              else ({}, {}))
    qd_held, tau_held = data.qd[held_out], data.tau_r[held_out]
    longest = int(np.argmax([len(seg.stamp) for seg in data.segments]))
    noise = MomentumNoise.from_training(data.dynamics[longest].p, data.dynamics[longest].u,
                                        data.segments[longest].stamp)
    held_mean, held_var = kmp.predict_batch(qd_held, q_held, g_held)
    held_mse = {"kmp": np.mean((tau_held - held_mean) ** 2, axis=0)}
    held_mse.update({name: np.mean((tau_held - model.predict_batch(qd_held)[0]) ** 2, axis=0)
                     for name, model in residuals.items()})
    held_rmse = {name: np.sqrt(mse).tolist() for name, mse in held_mse.items()}
    tuning = replace(tuning, residual_variance=held_mse["kmp"])
    tunings = {name: replace(value, residual_variance=held_mse[name]) for name, value in tunings.items()}
    info = dict(info or {})
    info.update({
        "kvark_ros_version": __version__,
        "samples": int(len(data.qd)), "held_out": int(held_out.sum()),
        "kmp": {"n_support": kmp.n_support, "n_components": N_COMPONENTS, "inputs": list(kinds),
                "input_selection_loglik": selection,
                "length_scale": kmp.hyper.length_scale.tolist(), "sigma_f2": kmp.hyper.sigma_f2.tolist(),
                "lambda1": kmp.hyper.lambda1.tolist(), "lambda2": kmp.hyper.lambda2.tolist()},
        "held_out_rmse": held_rmse["kmp"],
        "held_out_rmse_by_model": held_rmse,
        "held_out_coverage95": coverage.tolist(),
        "held_out_mean_std": np.sqrt(held_var.mean(axis=0)).tolist(),
        "training_seconds": round(time.perf_counter() - started, 1),
        "data_source": data_source([seg.simulated for seg in segments]),
    })
    # t_s: the median period of all training samples; the config's filter times convert at it (PerSample).
    sample_period = float(np.median(np.concatenate([np.diff(seg.stamp) for seg in data.segments])))
    log(f"[train] sample rate {1.0 / sample_period:.1f} Hz (recorded in the model: the filter's times convert at it)")
    stiction = StictionBand(identify_band(data.qd, band_friction(robot, data)))
    log("[train] static friction band F_s (N·m): "
        + ", ".join(f"{name} {value:.2f}" for name, value in zip(robot.joint_names, stiction.band)))
    trained = TrainedModel(robot_name, robot.joint_names, kmp, tuning, info, residuals, tunings, noise,
                           robot.augmentation, sample_period, stiction)
    return calibrate_intervals(trained, data, settings or default_filter_settings(), log,
                               (replace(trained, residual=head_kmp), ~head))


def band_friction(robot: RobotModel, data: TrainingData) -> np.ndarray:
    """The friction the model sees (T, n) N·m (``stiction.friction_torque``), here with τ_m and q̈ through a
    ``BAND_WINDOW`` filter: the residual model's ``SAVGOL_WINDOW`` smears the turn of every reversal, where the
    static level shows, over 150 ms and would give a band below it (docs/method.md §4.11)."""
    residual = []
    for seg in data.segments:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m, BAND_WINDOW)
        residual.append(tau_m - np.array([robot.model_torque(q, qd, a, tau) for q, qd, a, tau
                                          in zip(seg.q, seg.qd, qdd, tau_m)]))
    return friction_torque(np.concatenate(residual), robot.augmentation, data.q, data.qd, np.zeros_like(data.qd))


def fit_residual(data: TrainingData, kinds: tuple[str, ...], fit: np.ndarray, held: np.ndarray, seed: int,
                 executor: Executor | None) -> tuple[KMPResidualModel, np.ndarray]:
    """The KMP fitted on the samples ``fit`` (T,) bool with λ₂ calibrated on ``held`` (§3.5); (model, held-out
    coverage95 per joint)."""
    z = second_inputs(kinds, data.q, data.g)
    kmp = fit_kmp(data.qd[fit], z[fit], data.tau_r[fit], kinds, N_COMPONENTS, _n_support(kinds), seed, executor)
    return calibrate_lambda2(kmp, data.qd[held], data.tau_r[held], data.q[held], data.g[held])


def recording_ends(data: TrainingData, share: float) -> np.ndarray:
    """(T,) bool: the last ``share`` of every recording, in time (motion a model fitted on the rest has not seen)."""
    return np.concatenate([seg.stamp >= seg.stamp[-1] - share * (seg.stamp[-1] - seg.stamp[0])
                           for seg in data.segments])


def calibrate_intervals(trained: TrainedModel, data: TrainingData, settings: FilterSettings,
                        log: Callable[[str], None],
                        unseen: tuple[TrainedModel, np.ndarray] | None = None) -> TrainedModel:
    """``trained`` with kvark's interval factors c read off contact-free recordings (docs/method.md §4.13).

    c is read in-sample (``trained`` on every sample) and, with ``unseen`` (a model fitted without some samples,
    those samples (T,) bool: the ends of the recordings) of at least ``MIN_UNSEEN`` s, also where that model has
    not seen the motion: the model error a new recording meets. Each joint keeps the larger factor. The result also
    holds the reported variance's floor: the ``kf``'s steady state P_b (``variance_floor``) and its factor in free
    motion c_b, ``kf``'s own factor read the same way where below 1 (``floor_factor``)."""
    started = time.perf_counter()
    velocity = settings.stiction_velocity
    band = (None if trained.stiction is None or velocity == 0.0
            else lambda qd: trained.stiction.variance(qd, velocity))
    floor = variance_floor(make_observer("kf", trained, settings), trained.sample_period)
    # c is the misfit free motion shows, read on the filter an onset does not raise: a false onset there would
    # raise every joint's P for a while and so shrink c everywhere (§4.7); at a real onset the raised P stays in
    # what is reported, on top of c
    reading = replace(settings, onset_contact_bandwidth=0.0)

    def factors(observer: str, model: TrainedModel, rows: Sequence[np.ndarray]) -> np.ndarray:
        kept = [(seg, dyn, row) for seg, dyn, row in zip(data.segments, data.dynamics, rows) if row.sum() > 1]
        return interval_scale(make_observer(observer, model, reading),
                              [seg.stamp[row] for seg, _, row in kept], [seg.qd[row] for seg, _, row in kept],
                              [seg.q[row] for seg, _, row in kept], [dyn.p[row] for _, dyn, row in kept],
                              [dyn.u[row] for _, dyn, row in kept], [dyn.g[row] for _, dyn, row in kept],
                              band).scale

    everything = [np.ones(len(seg.stamp), bool) for seg in data.segments]
    in_sample, kf_in_sample = factors(CALIBRATED_OBSERVER, trained, everything), factors("kf", trained, everything)
    scale, kf_scale, out, seconds = in_sample, kf_in_sample, None, 0.0
    text = "in-sample " + ", ".join(f"{name} {value:.2f}" for name, value in zip(trained.joint_names, in_sample))
    if unseen is not None:
        cuts = np.cumsum([0] + [len(seg.stamp) for seg in data.segments])
        parts = [unseen[1][a:b] for a, b in zip(cuts[:-1], cuts[1:])]
        seconds = sum(float(np.ptp(seg.stamp[part])) for seg, part in zip(data.segments, parts) if part.sum() > 1)
        if seconds >= MIN_UNSEEN:
            out = factors(CALIBRATED_OBSERVER, unseen[0], parts)
            text += "; on unseen ends " + ", ".join(f"{value:.2f}" for value in out)
            scale = np.maximum(in_sample, out)
            kf_scale = np.maximum(kf_in_sample, factors("kf", unseen[0], parts))
    narrowing = floor_factor(kf_scale)
    text += ("; floor σ_b (kf's steady state, N·m) " + ", ".join(f"{value:.3g}" for value in np.sqrt(floor))
             + ", in free motion × c_b " + ", ".join(f"{value:.2f}" for value in narrowing))
    log(f"[train] kvark interval factors c (95 % of the contact-free τ̂ within ±1.96 √(c²σ² + σ²_s); reported: "
        f"±1.96 √(max(c²σ², σ_b²) + σ²_s) under a load, σ_b × c_b in free motion): {text} "
        f"({time.perf_counter() - started:.1f} s)")
    info = {**trained.info, "interval_factors": {"in_sample": in_sample.tolist(), "unseen_seconds": round(seconds, 2),
                                                 "unseen": None if out is None else out.tolist(),
                                                 "kf": kf_scale.tolist()}}
    return replace(trained, interval_scale=IntervalScale(scale, floor, narrowing), info=info)
