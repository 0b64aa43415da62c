"""``kvark train``: residual models and filter tuning from contact-free ROS 2 bags.

Per joint: residual ``τ_r = τ_m − τ_EL`` (paper eq. 27, accelerations by Savitzky-Golay
differentiation since bags carry none; with a model augmentation from ``kvark diagnose``, τ_EL is
the augmented model's torque and the augmentation is stored with the model), GMM → GMR → KMP with the length scale and λ₁ from a
GP marginal-likelihood fit and λ₂ calibrated on held-out samples (paper v2 §V-B), static
filter covariances by covariance matching (v2 §V-D), and the baselines' residual models.
The model directory is written atomically: a failed run leaves the previous model untouched.
"""
from __future__ import annotations

import argparse
import hashlib
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from scipy.signal import savgol_filter

from kvark_ros import __version__
from kvark_ros.core.augmentation import load_augmentation
from kvark_ros.core.config import EstimatorConfig, load_config
from kvark_ros.core.model_store import TrainedModel, save_model
from kvark_ros.core.observers.base import FilterTuning
from kvark_ros.core.observers.momentum_observers import MomentumNoise
from kvark_ros.core.residual_model import KMPHyperparameters, KMPResidualModel
from kvark_ros.core.robot_model import RobotModel, urdf_sha256
from kvark_ros.core.tuning import match_covariances, virtual_measurements
from kvark_ros.io.alignment import EstimatorInputs, estimator_inputs
from kvark_ros.io.bag import read_run

N_SUPPORT = 40               # GMR support points per joint
N_COMPONENTS = 20            # GMM components (paper v2: 20)
HOLDOUT = 0.2                # share of samples held out for λ₂ calibration (paper v2 §V-B)
COVERAGE_TARGET = 0.95       # λ₂ is set so that 95 % of held-out residuals fall in μ ± 1.96 σ
LAMBDA2_GRID = np.geomspace(1e-2, 1e8, 61)
SAVGOL_WINDOW = 0.15         # s, window of the acceleration and torque filter (75 samples at 500 Hz)


@dataclass(frozen=True)
class TrainingData:
    """Concatenated training samples: q̇ (T, n) rad/s, τ_r (T, n) N·m; segments keep recordings apart."""

    qd: np.ndarray
    tau_r: np.ndarray
    segments: tuple[EstimatorInputs, ...]


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


def training_data(robot: RobotModel, segments: Sequence[EstimatorInputs]) -> TrainingData:
    """Residual torques ``τ_m − τ_EL`` (eq. 27; τ_EL + τ_aug when augmented) of every recording."""
    qd_all, tau_r_all = [], []
    for seg in segments:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m)
        tau_el = np.array([robot.model_torque(q, qd, a, tau) for q, qd, a, tau in zip(seg.q, seg.qd, qdd, tau_m)])
        qd_all.append(seg.qd)
        tau_r_all.append(tau_m - tau_el)
    return TrainingData(np.concatenate(qd_all), np.concatenate(tau_r_all), tuple(segments))


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


def _tuning(robot: RobotModel, segments: Sequence[EstimatorInputs],
            predict_batch: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None) -> FilterTuning:
    """Covariance matching on the virtual measurements corrected by one residual model's mean."""
    ys = [virtual_measurements(robot, None if predict_batch is None else predict_batch(seg.qd)[0],
                               seg.stamp, seg.q, seg.qd, seg.tau_m) for seg in segments]
    dt = float(np.median(np.concatenate([np.diff(seg.stamp) for seg in segments])))
    return match_covariances(ys, dt)


def train_model(robot: RobotModel, robot_name: str, segments: Sequence[EstimatorInputs], *,
                baselines: bool = True, seed: int = 0, info: dict | None = None,
                log: Callable[[str], None] = print) -> TrainedModel:
    """Everything the observers need, from contact-free recordings of ``robot``."""
    from kvark_ros.core.residual_baselines import (GMRGPResidualModel, MLPResidualModel, SparseGPResidualModel,
                                                   hyperparameters_from_gp)
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
    tuning = _tuning(robot, segments, kmp.predict_batch)
    log("[train] K-VARK filter tuned by covariance matching")
    qd_held, tau_held = data.qd[held_out], data.tau_r[held_out]
    residuals: dict = {}
    tunings: dict = {}
    if baselines:
        fits = {"gmr_gp": lambda: GMRGPResidualModel.fit(qd_fit, tau_fit, N_COMPONENTS, N_SUPPORT, seed=seed,
                                                         reference=kmp.reference),
                "gpadkf": lambda: SparseGPResidualModel.fit(qd_fit, tau_fit, seed=seed),
                "nnadkf": lambda: MLPResidualModel.fit(qd_fit, tau_fit, seed=seed)}
        for name, fit in fits.items():
            residuals[name] = fit()
            tunings[name] = _tuning(robot, segments, residuals[name].predict_batch)
            log(f"[train] baseline {name} fitted and tuned")
    momentum, inputs, stamps = [], [], []
    for seg in segments:
        pu = [robot.momentum_terms(q, qd, tau) for q, qd, tau in zip(seg.q, seg.qd, seg.tau_m)]
        momentum.append(np.array([p for p, _ in pu]))
        inputs.append(np.array([u for _, u in pu]))
        stamps.append(seg.stamp)
    longest = int(np.argmax([len(s) for s in stamps]))
    noise = MomentumNoise.from_training(momentum[longest], inputs[longest], stamps[longest])
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


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def bag_hash(path: Path) -> str:
    """sha256 over a bag's storage files (a directory) or the file itself."""
    files = sorted(p for p in Path(path).rglob("*") if p.is_file()) if Path(path).is_dir() else [Path(path)]
    digest = hashlib.sha256()
    for file in files:
        digest.update(sha256_file(file).encode())
    return digest.hexdigest()


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train", help="train the residual models and filter tuning from contact-free bags",
        description="Read contact-free ROS 2 bags (MCAP or sqlite3), compute the residual torque τ_m − τ_EL "
                    "per joint, fit GMM → GMR → KMP (and the baselines' models), tune the filters by "
                    "covariance matching and write the model directory atomically, with training plots.")
    parser.add_argument("--config", required=True, help="estimator config YAML (e.g. config/panda.yaml)")
    parser.add_argument("--bags", nargs="+", required=True, metavar="BAG", help="training bags (directories or files)")
    parser.add_argument("--out", required=True, help="model directory to write (replaced only on success)")
    parser.add_argument("--augmentation", metavar="FILE",
                        help="augmentation.yaml of `kvark diagnose` to train on the improved model (default: the "
                             "config's model_augmentation; '' for none); copied into the model directory")
    parser.add_argument("--no-baselines", action="store_true",
                        help="skip the GMR-GP, sparse-GP and MLP baselines (faster)")
    parser.add_argument("--seed", type=int, default=0, help="random seed for the hold-out split and fits")
    parser.add_argument("--no-plots", action="store_true", help="do not write training plots")
    parser.set_defaults(run=run)


def load_recordings(config: EstimatorConfig, bags: Sequence[str], tag: str) -> list[EstimatorInputs]:
    """Estimator inputs of every bag, with one status line each (shared by train and diagnose)."""
    segments = []
    for bag in bags:
        inputs = estimator_inputs(read_run(bag, config.joint_names), config.command_max_age, path=str(bag))
        print(f"[{tag}] {bag}: {len(inputs)} samples (τ_m from {inputs.torque_source}, "
              f"{inputs.dropped} dropped)", flush=True)
        segments.append(inputs)
    return segments


def run(args: argparse.Namespace) -> int:
    config: EstimatorConfig = load_config(args.config)
    source = config.model_augmentation if args.augmentation is None else args.augmentation
    augmentation = load_augmentation(source, config.joint_names) if source else None
    robot = RobotModel.from_config(config, augmentation)
    if augmentation is not None:
        print(f"[train] model augmented by {source}: {', '.join(augmentation.effect_names) or 'no effects'}",
              flush=True)
    segments = load_recordings(config, args.bags, "train")
    info = {"robot": config.robot, "joint_names": list(config.joint_names),
            "urdf_sha256": urdf_sha256(config.urdf),
            "augmentation": None if augmentation is None else {
                "file": Path(source).name, "effects": list(augmentation.effect_names)},
            "bags": [{"name": Path(bag).name, "sha256": bag_hash(Path(bag))} for bag in args.bags]}
    trained = train_model(robot, config.robot, segments, baselines=not args.no_baselines, seed=args.seed,
                          info=info, log=lambda line: print(line, flush=True))
    save_model(args.out, trained)
    print(f"[train] model written to {args.out}", flush=True)
    if not args.no_plots:
        from kvark_ros.tools.plots import plot_training
        for path in plot_training(robot, trained, segments, Path(args.out)):
            print(f"[train] plot {path}", flush=True)
    return 0
