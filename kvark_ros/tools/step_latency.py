"""``kvark bench``: per-step latency of the Estimator (robot model + observer + wrench + contact tests).

Trains a residual model on a synthetic free-motion stream of the configured robot (or takes a trained model
directory, ``--model``: a real robot's with its residual inputs and augmentation), then steps a fresh Estimator
per observer over a synthetic stream with a step external torque, timing each ``Estimator.step`` call. Every
observer gets a row (the oracle needs a plant file and is left out); its ``kernel`` column says whether its
filter step ran compiled inside the estimator's one compiled call (numba: the momentum-form K-VARK family, kvark,
its ablations, gmr_gp, gpadkf, nnadkf) or in numpy between two compiled calls (the difference form, the
residual-free observers); the rest of every step is compiled. The last printed line is one JSON object.
"""
from __future__ import annotations

import argparse
import gc
import json
import time
from typing import TYPE_CHECKING

import numpy as np

from kvark_ros.core.config import OBSERVER_NAMES, default_config_path, load_config, parse_observers
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.observers import LEARNED_BASELINE_VARIANTS, make_observer
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.tools.synthetic import step_torque, synthetic_stream, train_synthetic

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

WARM_UP_STEPS = 500
BENCH_OBSERVERS = tuple(name for name in OBSERVER_NAMES if name != "oracle")   # the oracle needs a plant file


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "bench", help="per-step latency of the estimator on a synthetic stream",
        description="Step the Estimator on a synthetic stream of the robot (known friction, a step "
                    "external torque) and print per-step latency (p50/p99, µs) and accuracy per observer. "
                    "The last line is one JSON object.")
    parser.add_argument("--robot", default="panda", help="robot whose config/<robot>.yaml is used (default: panda)")
    parser.add_argument("--config", help="config YAML (default: the robot's shipped config)")
    parser.add_argument("--observer", default="kvark",
                        help=f"observer name, a comma-separated list, or 'all' ({', '.join(BENCH_OBSERVERS)}); "
                             "default: kvark")
    parser.add_argument("--duration", type=float, default=10.0, help="length of the timed stream, s (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the synthetic streams (default 0)")
    parser.add_argument("--model", help="time this trained model directory (its residual inputs, augmentation, band "
                                        "and interval factors) instead of one trained on the synthetic stream; the "
                                        "RMSE column then compares it with the synthetic plant, not its own robot")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    names = parse_observers(args.observer)
    if "oracle" in names:
        raise SystemExit("kvark bench: the oracle needs the simulator's plant file; benchmark it with kvark replay "
                         "--plant FILE")
    if args.duration <= 0:
        raise SystemExit("kvark bench: --duration must be positive")
    config = load_config(args.config or default_config_path(args.robot))
    if args.model:
        trained = load_model(args.model, config.joint_names)
        robot = RobotModel.from_config(config, trained.augmentation)
        print(f"timing the model {args.model} (residual inputs {', '.join(trained.residual.inputs)})", flush=True)
    else:
        robot = RobotModel.from_config(config)
        print(f"training a residual model on a 20 s synthetic free-motion stream of {config.robot} ...", flush=True)
        trained = train_synthetic(robot, config.robot, seed=args.seed,
                                  baselines=any(name in LEARNED_BASELINE_VARIANTS for name in names))
    torque = np.linspace(2.0, 0.5, robot.n)
    stream = synthetic_stream(robot, args.duration, seed=args.seed + 1, external=step_torque(args.duration / 4, torque))
    results = {}
    print(f"{'observer':<12} {'kernel':>6} {'steps':>6} {'p50 µs':>8} {'p99 µs':>8} {'max µs':>8} {'RMSE N·m':>9}")
    for name in names:
        warm_up = Estimator(config, robot, make_observer(name, trained, config.filter), trained)
        for k in range(min(WARM_UP_STEPS, len(stream.stamp))):   # caches and allocator settle, untimed
            warm_up.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        estimator = Estimator(config, robot, make_observer(name, trained, config.filter), trained)
        latency, error = time_estimator(estimator, stream)
        results[name] = {"kernel": "numba" if getattr(estimator.observer, "compiled", False) else "numpy",
                         "steps": len(latency),
                         "p50_us": round(float(np.percentile(latency, 50)), 2),
                         "p99_us": round(float(np.percentile(latency, 99)), 2),
                         "max_us": round(float(latency.max()), 2), "rmse_nm": round(error, 4)}
        row = results[name]
        print(f"{name:<12} {row['kernel']:>6} {row['steps']:>6} {row['p50_us']:>8.1f} {row['p99_us']:>8.1f} "
              f"{row['max_us']:>8.1f} {row['rmse_nm']:>9.4f}", flush=True)
    first = results[names[0]]
    summary = {"robot": config.robot, "observer": names[0], "kernel": first["kernel"], "steps": first["steps"],
               "p50_us": first["p50_us"], "p99_us": first["p99_us"], "observers": results}
    print(json.dumps(summary))
    return 0


def time_estimator(estimator: Estimator, stream) -> tuple[np.ndarray, float]:
    """Latency of every step (µs) and the RMSE of τ_ext against the stream's truth (N·m)."""
    count = len(stream.stamp)
    latency = np.empty(count)
    estimates = np.zeros((count, estimator.robot.n))
    valid = np.zeros(count, dtype=bool)
    gc.collect()
    gc.freeze()          # long-lived objects (models, training data) out of the collector's scans
    clock = time.perf_counter_ns
    for k in range(count):
        start = clock()
        estimate = estimator.step(stream.stamp[k], stream.q[k], stream.qd[k], stream.tau_m[k])
        latency[k] = (clock() - start) * 1e-3
        if estimate is not None:
            estimates[k], valid[k] = estimate.tau_ext, True
    error = float(np.sqrt(np.mean((estimates[valid] - stream.tau_ext[valid]) ** 2)))
    return latency, error
