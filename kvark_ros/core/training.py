"""Training: residual models and filter tuning from contact-free recordings.

Per joint: residual ``τ_r = τ_m − τ_EL`` (paper eq. 27, accelerations by Savitzky-Golay
differentiation since recordings carry none; with a model augmentation from ``kvark diagnose``,
τ_EL is the augmented model's torque and the augmentation is stored with the model), GMM → GMR →
KMP with the length scale and λ₁ from a GP marginal-likelihood fit and λ₂ calibrated on held-out
samples (paper v2 §V-B), static filter covariances by covariance matching (v2 §V-D), the
baselines' residual models and the momentum observers' noise levels. The robot model is
evaluated once per sample (``segment_dynamics``) and reused by every step.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
from scipy.signal import savgol_filter

from kvark_ros import __version__
from kvark_ros.core.inputs import EstimatorInputs
from kvark_ros.core.model_store import TrainedModel
from kvark_ros.core.observers.base import FilterTuning
from kvark_ros.core.observers.momentum_observers import MomentumNoise
from kvark_ros.core.residual import (
    LEARNED_BASELINES,
    KMPHyperparameters,
    KMPResidualModel,
    hyperparameters_from_gp,
)
from kvark_ros.core.robot_model import RobotModel
from kvark_ros.core.tuning import match_covariances, virtual_measurements

N_SUPPORT = 40               # GMR support points per joint
N_COMPONENTS = 20            # GMM components (paper v2: 20)
HOLDOUT = 0.2                # share of samples held out for λ₂ calibration (paper v2 §V-B)
COVERAGE_TARGET = 0.95       # λ₂ is set so that 95 % of held-out residuals fall in μ ± 1.96 σ
LAMBDA2_GRID = np.geomspace(1e-2, 1e8, 61)
SAVGOL_WINDOW = 0.15         # s, window of the acceleration and torque filter (75 samples at 500 Hz)


@dataclass(frozen=True)
class SegmentDynamics:
    """The robot model along one recording, evaluated once per sample, all (T, n).

    tau_el: τ_EL (+ τ_aug when augmented) at the smoothed q̈ and τ_m (eq. 27), N·m;
    p: generalized momentum M(q) q̇ (eq. 5), N·m·s; u: its model input Cᵀq̇ − g + τ_m with the
    recorded τ_m (eq. 7), N·m.
    """

    tau_el: np.ndarray
    p: np.ndarray
    u: np.ndarray


@dataclass(frozen=True)
class TrainingData:
    """Concatenated training samples: q̇ (T, n) rad/s, τ_r (T, n) N·m; segments keep recordings apart,
    dynamics holds the robot model along each of them."""

    qd: np.ndarray
    tau_r: np.ndarray
    segments: tuple[EstimatorInputs, ...]
    dynamics: tuple[SegmentDynamics, ...]


def smoothed_signals(stamp: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q̈ (T, n) and τ_m (T, n) through the same zero-phase Savitzky-Golay filter.

    q̈ comes from smoothing q̇ and differentiating against the actual stamps. τ_m must be smoothed
    the same way: the controller's torque reacts to sensor noise faster than any acceleration
    filter passes, so an unsmoothed τ_m against a smoothed M q̈ leaves that jitter in the residual
    (measured on the simulated Panda: 0.5 N·m scatter on joints 1-4 with τ_m raw, see README).
    """
    dt = float(np.median(np.diff(stamp)))
    window = max(5, int(round(SAVGOL_WINDOW / dt)) | 1)
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
    for k, (q, qd, a, tau_s, tau) in enumerate(zip(seg.q, seg.qd, qdd, tau_smoothed, seg.tau_m)):
        tau_el[k] = robot.model_torque(q, qd, a, tau_s)
        p[k], u[k] = robot.momentum_terms(q, qd, tau)
    for array in (tau_el, p, u):
        array.setflags(write=False)
    return SegmentDynamics(tau_el, p, u)


def training_data(robot: RobotModel, segments: Sequence[EstimatorInputs]) -> TrainingData:
    """Residual torques ``τ_m − τ_EL`` (eq. 27; τ_EL + τ_aug when augmented) of every recording."""
    qd_all, tau_r_all, dynamics = [], [], []
    for seg in segments:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m)
        dyn = segment_dynamics(robot, seg, qdd, tau_m)
        qd_all.append(seg.qd)
        tau_r_all.append(tau_m - dyn.tau_el)
        dynamics.append(dyn)
    return TrainingData(np.concatenate(qd_all), np.concatenate(tau_r_all), tuple(segments), tuple(dynamics))


def calibrate_lambda2(model: KMPResidualModel, qd: np.ndarray, tau_r: np.ndarray,
                      target: float = COVERAGE_TARGET) -> tuple[KMPResidualModel, np.ndarray]:
    """Per joint, the λ₂ whose μ ± 1.96 σ interval covers ``target`` of the held-out residuals.

    λ₂ leaves the KMP mean alone (eq. 22) and scales the variance (eq. 23). Returns the
    calibrated model and the held-out coverage per joint.
    """
    coverage = np.empty((len(LAMBDA2_GRID), model.n_joints))
    for index, lambda2 in enumerate(LAMBDA2_GRID):
        hyper = replace(model.hyper, lambda2=np.full(model.n_joints, lambda2))
        mean, var = KMPResidualModel(model.reference, hyper).predict_batch(qd)
        coverage[index] = np.mean(np.abs(tau_r - mean) <= 1.96 * np.sqrt(var), axis=0)
    best = np.argmin(np.abs(coverage - target), axis=0)
    hyper = replace(model.hyper, lambda2=LAMBDA2_GRID[best])
    return KMPResidualModel(model.reference, hyper, model.metadata), coverage[best, np.arange(model.n_joints)]


def _tuning(data: TrainingData,
            predict_batch: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> FilterTuning:
    """Covariance matching on the virtual measurements corrected by one residual model's mean."""
    ys = [virtual_measurements(dyn.p, dyn.u, seg.stamp, predict_batch(seg.qd)[0])
          for seg, dyn in zip(data.segments, data.dynamics)]
    dt = float(np.median(np.concatenate([np.diff(seg.stamp) for seg in data.segments])))
    return match_covariances(ys, dt)


def train_model(robot: RobotModel, robot_name: str, segments: Sequence[EstimatorInputs], *,
                baselines: bool = True, seed: int = 0, info: dict | None = None,
                log: Callable[[str], None] = print) -> TrainedModel:
    """Everything the observers need, from contact-free recordings of ``robot``."""
    started = time.perf_counter()
    data = training_data(robot, segments)
    rng = np.random.default_rng(seed)
    held_out = rng.random(len(data.qd)) < HOLDOUT
    qd_fit, tau_fit = data.qd[~held_out], data.tau_r[~held_out]
    log(f"[train] {len(data.qd)} samples from {len(segments)} recording(s); {held_out.sum()} held out")
    hyper: KMPHyperparameters = hyperparameters_from_gp(qd_fit, tau_fit, N_SUPPORT, seed)
    log(f"[train] GP fit: length scale {np.round(hyper.length_scale, 3).tolist()} rad/s, "
        f"λ1 {np.round(hyper.lambda1, 4).tolist()}")
    kmp = KMPResidualModel.fit(qd_fit, tau_fit, hyper, n_components=N_COMPONENTS, n_support=N_SUPPORT, seed=seed)
    kmp, coverage = calibrate_lambda2(kmp, data.qd[held_out], data.tau_r[held_out])
    log(f"[train] KMP λ2 {kmp.hyper.lambda2.tolist()}; held-out 95% coverage {np.round(coverage, 3).tolist()}")
    tuning = _tuning(data, kmp.predict_batch)
    log("[train] K-VARK filter tuned by covariance matching")
    qd_held, tau_held = data.qd[held_out], data.tau_r[held_out]
    residuals: dict = {}
    tunings: dict = {}
    if baselines:
        # GMR-GP samples the KMP's own GMR reference (fitted with N_COMPONENTS), as in the paper.
        options = {"gmr_gp": {"n_components": N_COMPONENTS, "n_support": N_SUPPORT, "reference": kmp.reference}}
        for name, model_class in LEARNED_BASELINES.items():
            residuals[name] = model_class.fit(qd_fit, tau_fit, seed=seed, **options.get(name, {}))
            tunings[name] = _tuning(data, residuals[name].predict_batch)
            log(f"[train] baseline {name} fitted and tuned")
    longest = int(np.argmax([len(seg.stamp) for seg in data.segments]))
    noise = MomentumNoise.from_training(data.dynamics[longest].p, data.dynamics[longest].u,
                                        data.segments[longest].stamp)
    held_mean, held_var = kmp.predict_batch(qd_held)
    held_mse = {name: np.mean((tau_held - model.predict_batch(qd_held)[0]) ** 2, axis=0)
                for name, model in {"kmp": kmp, **residuals}.items()}
    held_rmse = {name: np.sqrt(mse).tolist() for name, mse in held_mse.items()}
    tuning = replace(tuning, residual_variance=held_mse["kmp"])
    tunings = {name: replace(value, residual_variance=held_mse[name]) for name, value in tunings.items()}
    info = dict(info or {})
    info.update({
        "kvark_ros_version": __version__,
        "samples": int(len(data.qd)), "held_out": int(held_out.sum()),
        "kmp": {"n_support": N_SUPPORT, "n_components": N_COMPONENTS,
                "length_scale": kmp.hyper.length_scale.tolist(), "sigma_f2": kmp.hyper.sigma_f2.tolist(),
                "lambda1": kmp.hyper.lambda1.tolist(), "lambda2": kmp.hyper.lambda2.tolist()},
        "held_out_rmse": held_rmse["kmp"],
        "held_out_rmse_by_model": held_rmse,
        "held_out_coverage95": coverage.tolist(),
        "held_out_mean_std": np.sqrt(held_var.mean(axis=0)).tolist(),
        "training_seconds": round(time.perf_counter() - started, 1),
    })
    return TrainedModel(robot_name, robot.joint_names, kmp, tuning, info, residuals, tunings, noise,
                        robot.augmentation)
