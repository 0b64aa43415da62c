"""``kvark replay``: run a bag through one or more observers, as the ROS node would.

One pass over the bag per observer through the same ``Estimator`` the node uses. Writes
``estimates/`` (a rosbag2 MCAP bag: the inputs plus each observer's outputs under ``/kvark/<observer>/``),
``metrics.json`` (paper v2 Tables IV-V), ``report.md`` and plots.

Ground truth (``--ground-truth``), ``auto`` takes in order of preference: the true external torque the
bag carries (``topic``, simulation), the wrist F/T through ``τ = Jᵀ w`` (``ft``, v2 eq. 37), or the
two-run difference against a ``--reference-bag`` recorded without the load (``reference``, v2 eq. 40,
our sign: ``τ_ext = τ_free − τ_loaded``); ``zero`` says the robot touched nothing (free motion), so every
estimate is error. ``--trim START END`` drops the first START and last END seconds (a start-up or a stop).
The estimates bag is written by default for up to ``ESTIMATES_BAG_S`` s of data, beyond only with
``--estimates-bag`` (every observer's outputs at every sample: a 1 kHz recording of minutes gave 200 MB).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from kvark_ros.core.config import OBSERVER_NAMES, EstimatorConfig, load_config, parse_observers
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.files import check_output, staged_directory, write_text_atomically
from kvark_ros.core.estimation.tare import TareError
from kvark_ros.core.estimation.inputs import EstimatorInputs, trimmed_rows
from kvark_ros.core.estimation.model_store import TrainedModel, load_model
from kvark_ros.core.estimation.model_checks import measured_rate, model_warnings
from kvark_ros.core.estimation.observers import ResidualPredictor
from kvark_ros.core.estimation.robot_model import RobotModel, condition_numbers, urdf_sha256
from kvark_ros.io import (BagError, BagWriter, RecordedRun, bool_messages, float64_array_messages,
                          joint_state_messages, load_message_types, wrench_messages, write_run_messages)
from kvark_ros.io.recorded_inputs import read_checked, read_inputs
from kvark_ros.cli_options import add_trim_option
from kvark_ros.io.runs import numerical_failures
from kvark_ros.tools.two_run_reference import align_reference, interpolate
from kvark_ros.tools.truth_topics import missing_truth
from kvark_ros.tools.metrics import in_motion, mahalanobis_rows, observer_metrics, static_band
from kvark_ros.tools.wrench_truth import sensed_wrench

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

OUTPUT_PREFIX = "/kvark"
ESTIMATES_BAG_S = 60.0    # s of data up to which the estimates bag is written by default (1 kHz, minutes: 200 MB)


@dataclass(frozen=True)
class GroundTruth:
    """τ_ext (T, n) N·m and wrench (T, 6) at the end-effector origin in the configured axes (NaN rows: the wrist
    sensor does not observe the contact, ``wrench_truth``), or None."""

    kind: str
    tau_ext: np.ndarray
    wrench: np.ndarray | None


@dataclass(frozen=True)
class ObserverRun:
    """One observer's outputs along the inputs; rows where ``valid`` is False had no estimate.
    ``contact``, ``collision``: the Estimator's debounced contact flag and its collision flag (T,) bool;
    ``tare``: what a ``--tare-at`` tare did (state, offset per joint N·m, note), or None;
    ``mahalanobis``: (T,) eᵀP⁻¹e of the error e = τ̂ − τ_true under the full reported covariance P (NaN without an
    estimate or a finite truth), or None without a covariance or a truth (kept per sample: memory stays (T,))."""

    name: str
    tau_ext: np.ndarray
    tau_std: np.ndarray | None
    wrench: np.ndarray
    wrench_std: np.ndarray | None
    valid: np.ndarray
    us_per_step: float
    rejected: dict[str, int]
    contact: np.ndarray
    collision: np.ndarray
    tare: dict | None = None
    mahalanobis: np.ndarray | None = None
    condition: np.ndarray | None = None         # (T,) κ of J (NaN without an estimate), docs/method.md §1.4.1
    unobservable: np.ndarray | None = None      # (T,) int: wrench directions the joints cannot sense (σ_i < δ)

    def singularity(self) -> dict[str, float | None]:
        """metrics.json's wrench-observability figures: the share of estimates with an unobservable wrench
        direction and the median and maximum condition number of J (None without estimates)."""
        if self.condition is None or self.unobservable is None or not self.valid.any():
            return {"unobservable_share": None, "condition_median": None, "condition_max": None}
        condition = self.condition[self.valid]
        return {"unobservable_share": round(float(np.mean(self.unobservable[self.valid] > 0)), 6),
                "condition_median": round(float(np.median(condition)), 3),
                "condition_max": round(float(np.max(condition)), 3)}


GROUND_TRUTHS = ("auto", "zero", "topic", "ft", "reference")


def zero_truth(inputs: EstimatorInputs, why: str) -> GroundTruth:
    """A true external torque and wrench of zero on every sample (a contact-free recording)."""
    return GroundTruth(f"zero: {why}", np.zeros(inputs.q.shape), np.zeros((len(inputs), 6)))


def _take(inputs: EstimatorInputs, truth: GroundTruth | None,
          rows: np.ndarray) -> tuple[EstimatorInputs, GroundTruth | None]:
    """The inputs and the ground truth at ``rows``."""
    kept = inputs.take(rows)
    if truth is None:
        return kept, None
    return kept, GroundTruth(truth.kind, truth.tau_ext[rows], None if truth.wrench is None else truth.wrench[rows])


def ground_truth(robot: RobotModel, config: EstimatorConfig, run: RecordedRun, inputs: EstimatorInputs,
                 reference: EstimatorInputs | None, kind: str = "auto", bag: str | Path | None = None
                 ) -> GroundTruth | None:
    """The ground truth ``kind`` (``GROUND_TRUTHS``; ``auto``: the best the data offers, see module docstring) on
    the inputs' stamps; ``BagError`` when the asked one is not in the data (naming ``bag``'s topics, if given)."""
    if kind == "zero":
        return zero_truth(inputs, "contact-free recording (--ground-truth zero)")
    if kind == "reference" and reference is None:
        raise BagError("--ground-truth reference needs --reference-bag, which this replay does not have")
    if (kind == "topic" and run.external_torque is None) or (kind == "ft" and run.wrench is None):
        raise missing_truth(kind, config, bag)
    use_topic, use_ft = kind in ("auto", "topic"), kind in ("auto", "ft")
    wrench = None
    if run.wrench is not None:
        measured = np.hstack((run.wrench.force, run.wrench.torque))
        at_sensor = interpolate(inputs.stamp, run.wrench.stamp, measured)
        wrench = robot.wrenches_at_end_effector(inputs.q, run.wrench.frame_id, at_sensor, config.wrench.frame)
    if run.external_torque is not None and use_topic:
        tau = interpolate(inputs.stamp, run.external_torque.stamp, run.external_torque.effort)
        if wrench is None:    # no wrist sensor: the true torque through the same pseudo-inverse (eq. 39)
            wrench = _wrench_of_torque(robot, config, inputs.q, tau)
        else:                 # the wrist sensor cannot see a push on a link: no true wrench there
            wrench = sensed_wrench(robot, config.wrench.frame, inputs.q, tau, wrench)
        return GroundTruth("true external joint torque (/ground_truth/external_joint_torque)", tau, wrench)
    if run.wrench is not None and use_ft:
        tau = np.array([robot.sensor_torque(q, run.wrench.frame_id, w) if np.isfinite(w).all()
                        else np.full(robot.n, np.nan) for q, w in zip(inputs.q, at_sensor)])
        return GroundTruth(f"wrist F/T through J^T w (v2 eq. 37, frame {run.wrench.frame_id})", tau, wrench)
    if reference is not None and kind in ("auto", "reference"):
        alignment = align_reference(inputs, reference, config.joint_names)
        elapsed = inputs.stamp - inputs.stamp[0]
        free = interpolate(elapsed + alignment.shift, reference.stamp - reference.stamp[0], reference.tau_m)
        tau = free - inputs.tau_m
        return GroundTruth(f"two-run difference against the reference bag (v2 eq. 40), aligned by cross-correlating "
                           f"q: shift {alignment.shift:+.3f} s, q RMS difference ≤ {alignment.q_rms.max():.4f} rad",
                           tau, _wrench_of_torque(robot, config, inputs.q, tau))
    return None


def _wrench_of_torque(robot: RobotModel, config: EstimatorConfig, q: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Ground-truth wrench from a ground-truth torque through the estimator's own mapping (eq. 39)."""
    return np.array([robot.wrench_from_torque(qk, tk, None, config.wrench.damping, config.wrench.frame)[0]
                     if np.isfinite(tk).all() else np.full(6, np.nan) for qk, tk in zip(q, tau)])


def plant_oracle(config: EstimatorConfig, plant: str | None) -> ResidualPredictor | None:
    """The simulator plant's true residual for the oracle observer (``--plant``), on the plant's true rigid body when
    the config is one of the simulator's robots; None without a plant file."""
    if plant is None:
        return None
    from kvark_ros.sim.plant import OracleResidual, load_plant
    from kvark_ros.sim.robots import ROBOTS, robot_setup
    from kvark_ros.sim.true_model import true_urdf
    spec = load_plant(plant, config.n_joints)
    urdf = true_urdf(robot_setup(config.robot), spec) if config.robot in ROBOTS else None
    return OracleResidual(spec, config.n_joints, urdf=urdf)


def run_observer(config: EstimatorConfig, trained: TrainedModel, inputs: EstimatorInputs, name: str,
                 oracle: ResidualPredictor | None = None, tare_at: float | None = None,
                 truth_tau: np.ndarray | None = None, estimator: Estimator | None = None) -> ObserverRun:
    """Step a fresh Estimator with observer ``name`` over every input sample (``oracle``: for the oracle).

    ``tare_at``: s after the first sample from which a tare is started (``Estimator.start_tare``, as the node's
    ``~/tare``) at the first sample the arm is at rest; its outcome is in ``ObserverRun.tare``. ``truth_tau``: the
    true τ_ext (T, n) N·m, for ``ObserverRun.mahalanobis`` (its time is not counted in ``us_per_step``).
    ``estimator``: one built from the same arguments and not yet stepped (replay builds them before decoding)."""
    if estimator is None:
        estimator = Estimator.from_config(config, trained, observer=name, oracle=oracle)
    tare_stamp = None if tare_at is None else inputs.stamp[0] + tare_at
    tare_started = False
    count, n = len(inputs), estimator.robot.n
    tau = np.zeros((count, n))
    wrench = np.zeros((count, 6))
    tau_var = np.full((count, n), np.nan)
    wrench_var = np.full((count, 6), np.nan)
    valid = np.zeros(count, dtype=bool)
    contact = np.zeros(count, dtype=bool)
    collision = np.zeros(count, dtype=bool)
    distance = np.full(count, np.nan)
    scored_covariances = np.full((count, n, n), np.nan) if truth_tau is not None else None
    jacobians, unobservable = np.zeros((count, 6, n)), np.zeros(count, dtype=int)
    started = time.perf_counter()
    for k in range(count):
        if tare_stamp is not None and not tare_started and inputs.stamp[k] >= tare_stamp:
            try:
                estimator.start_tare()
                tare_started = True
            except TareError:          # moving (or warming up): the node's ~/tare refuses too; try the next sample
                pass
        estimate = estimator.step(inputs.stamp[k], inputs.q[k], inputs.qd[k], inputs.tau_m[k])
        if estimate is None:
            continue
        valid[k], contact[k], collision[k] = True, estimate.contact, estimate.collision
        tau[k], wrench[k], jacobians[k] = estimate.tau_ext, estimate.wrench, estimate.jacobian
        unobservable[k] = estimate.weak_directions.shape[1]
        if estimate.tau_cov is not None:
            tau_var[k] = estimate.tau_cov.diagonal()
            wrench_var[k] = estimate.wrench_cov.diagonal()
            if scored_covariances is not None:
                scored_covariances[k] = estimate.tau_cov
    elapsed = time.perf_counter() - started
    # After the loop, in batches, outside us_per_step: κ of J (Estimate.jacobian_condition) and the Mahalanobis
    # distance of the error.
    condition = np.full(count, np.nan)
    condition[valid] = condition_numbers(jacobians[valid])
    if scored_covariances is not None:
        distance = mahalanobis_rows(tau - truth_tau, scored_covariances)
    reports = estimator.observer.reports_covariance
    rejected = {status: number for status, number in estimator.counts.items() if status != "ok"}
    tare = None
    if tare_stamp is not None:
        tare = {"state": estimator.tare.state if tare_started else "never at rest after --tare-at",
                "offset": [round(float(v), 6) for v in estimator.tare.offset], "note": estimator.tare.note}
    return ObserverRun(name, tau, np.sqrt(tau_var) if reports else None, wrench,
                       np.sqrt(wrench_var) if reports else None, valid, 1e6 * elapsed / max(count, 1), rejected,
                       contact, collision, tare, mahalanobis=distance if reports and truth_tau is not None else None,
                       condition=condition, unobservable=unobservable)


def write_estimates(path: Path, run: RecordedRun, inputs: EstimatorInputs, results: Sequence[ObserverRun],
                    config: EstimatorConfig) -> None:
    """The bag's own messages plus every observer's outputs, atomically: per estimate its joint torque, wrench,
    torque σ (observers with a covariance), contact and collision flag, one topic after the other."""
    frame = "base" if config.wrench.frame == "base" else config.ee_frame
    names = run.joint_names
    with BagWriter(path) as bag:
        write_run_messages(bag, run)
        for result in results:
            prefix = f"{OUTPUT_PREFIX}/{result.name}"
            valid = np.flatnonzero(result.valid)
            stamp = inputs.stamp[valid]
            blocks = [joint_state_messages(f"{prefix}/external_joint_torque", stamp, names,
                                           effort=result.tau_ext[valid]),
                      wrench_messages(f"{prefix}/external_wrench", stamp, frame, result.wrench[valid, :3],
                                      result.wrench[valid, 3:])]
            if result.tau_std is not None:
                blocks.append(float64_array_messages(f"{prefix}/external_joint_torque_stddev", stamp,
                                                     result.tau_std[valid], names))
            blocks += [bool_messages(f"{prefix}/contact", stamp, result.contact[valid]),
                       bool_messages(f"{prefix}/collision", stamp, result.collision[valid])]
            bag.write_messages(blocks, np.tile(np.arange(len(blocks)), len(valid)),
                               np.repeat(np.arange(len(valid)), len(blocks)))


def bag_fields(inputs: EstimatorInputs, truth: GroundTruth | None, trained: TrainedModel, warnings: list[str],
               decode_seconds: float, trim: tuple[float, float] = (0.0, 0.0),
               skipped: dict[str, int] | None = None) -> dict:
    """metrics.json's fields of the bag itself (``kvark evaluate`` writes the same per bag); ``skipped``: samples
    skipped beyond the physics of the URDF per reason (``io.recorded_inputs.read_checked``)."""
    return {"ground_truth": truth.kind if truth is not None else "none", "trim_s": [float(v) for v in trim],
            "samples": len(inputs), "duration_s": round(float(inputs.stamp[-1] - inputs.stamp[0]), 3),
            "torque_source": inputs.torque_source, "dropped_samples": inputs.dropped,
            "skipped_samples": dict(skipped or {}),
            "decode_seconds": round(decode_seconds, 3), "sample_rate_hz": round(measured_rate(inputs.stamp), 3),
            "model_sample_rate_hz": round(trained.sample_rate, 3), "warnings": warnings}


def replay(config: EstimatorConfig, trained: TrainedModel, bag: Path, out: Path, observers: Sequence[str],
           reference_bag: Path | None = None, oracle: ResidualPredictor | None = None, write_bag: bool | None = None,
           plots: bool = True, log=print, truth_kind: str = "auto",
           trim: tuple[float, float] = (0.0, 0.0), tare_at: float | None = None, force: bool = False) -> dict:
    """Replay ``bag`` through ``observers``; write outputs into ``out``; return metrics.json's content.

    ``oracle``: the simulator's true residual (``kvark_ros.sim.plant.OracleResidual``), for the oracle;
    ``truth_kind``: one of ``GROUND_TRUTHS``; ``trim``: seconds dropped at the start and at the end;
    ``write_bag``: the estimates bag always (True), never (False) or for up to ``ESTIMATES_BAG_S`` s of data (None).
    ``out`` is built beside itself and swapped in whole (``staged_directory``: an existing non-empty ``out`` only
    with ``force``), so no file of an earlier replay stays.
    """
    check_output(out, force)
    started = time.perf_counter()
    # Built before decoding: a model or oracle that cannot serve an observer fails first, and what a process builds
    # once (the compiled kernels from numba's cache, the message types) is outside the replay's own time.
    estimators = [Estimator.from_config(config, trained, observer=name, oracle=oracle) for name in observers]
    load_message_types()
    start_up = time.perf_counter() - started
    started = time.perf_counter()
    run, inputs, check, skipped = read_checked(bag, config)
    for line in skipped:
        log(f"[replay] warning: {line}")
    log(f"[replay] {bag}: {len(inputs)} samples at {measured_rate(inputs.stamp):.0f} Hz, τ_m from "
        f"{inputs.torque_source}{' (simulated)' if inputs.simulated else ''}")
    warnings = model_warnings(trained, config.robot, measured_rate(inputs.stamp), inputs.simulated)
    for line in warnings:
        log(f"[replay] {line}")
    reference = None
    if reference_bag is not None:
        reference = read_inputs(reference_bag, config, lambda line: log(f"[replay] {line}"))[1]
    robot = RobotModel.from_config(config, trained.augmentation)
    truth = ground_truth(robot, config, run, inputs, reference, truth_kind, bag)
    if trim != (0.0, 0.0):     # after the ground truth: a reference run is aligned from the recordings' starts
        inputs, truth = _take(inputs, truth, trimmed_rows(inputs.stamp, *trim))
    decode_seconds = time.perf_counter() - started
    results = []
    for step, (name, estimator) in enumerate(zip(observers, estimators), start=1):
        result = run_observer(config, trained, inputs, name, oracle, tare_at, None if truth is None else truth.tau_ext,
                              estimator)
        results.append(result)
        log(f"[replay] {step}/{len(observers)} {name:<12} {result.us_per_step:7.1f} µs/step, "
            f"{result.valid.sum()} estimates")
    duration = float(inputs.stamp[-1] - inputs.stamp[0])
    moving = in_motion(inputs.qd, config.filter.stiction_velocity)
    metrics = {"bag": str(bag), **bag_fields(inputs, truth, trained, warnings, decode_seconds, trim,
                                             {drop.reason: len(drop.rows) for drop in check.drops}),
               "start_up_seconds": round(start_up, 3),
               "observers": {r.name: observer_metrics(r, truth, inputs.stamp, static_band(trained), moving)
                             for r in results}}
    if write_bag is None and duration > ESTIMATES_BAG_S:
        log(f"[replay] estimates bag not written: {duration:.0f} s of data, over {ESTIMATES_BAG_S:.0f} s (it would "
            f"hold every observer's outputs at every sample); pass --estimates-bag to write it")
    with staged_directory(out, force) as staging:
        if write_bag or (write_bag is None and duration <= ESTIMATES_BAG_S):
            write_estimates(staging / "estimates", run, inputs, results, config)
        write_text_atomically(staging / "metrics.json", json.dumps(metrics, indent=2))
        if plots:
            from kvark_ros.tools.report import write_replay_report
            write_replay_report(staging, metrics, robot, inputs, truth, results)
    total = time.perf_counter() - started
    log(f"[replay] {len(observers)} observer(s) over {duration:.1f} s of data in {total:.2f} s "
        f"({duration / total:.0f} × real time; reading {decode_seconds:.2f} s), after {start_up:.2f} s of start-up "
        f"(estimators with their compiled kernels, message types)")
    return metrics


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "replay", help="run a bag through observers; write an output bag, metrics, plots and a report",
        description="Replay a ROS 2 bag through one or more observers with the same Estimator the ROS node "
                    "uses. Writes the bag DIR/estimates/ (estimates.mcap: inputs plus /kvark/<observer>/... outputs; "
                    f"by default for up to {ESTIMATES_BAG_S:.0f} s of data), DIR/metrics.json, DIR/report.md and "
                    "plots. DIR is written whole: an existing non-empty DIR is replaced only with --force.")
    parser.add_argument("--config", required=True, help="estimator config YAML")
    parser.add_argument("--model", help="model directory (default: residual_model.model_dir of the config)")
    parser.add_argument("--bag", required=True, help="bag to replay")
    parser.add_argument("--observers", default="kvark",
                        help=f"comma-separated observers or 'all' ({', '.join(OBSERVER_NAMES)}); default kvark")
    parser.add_argument("--reference-bag", help="the same motion without the load, for two-run ground truth")
    parser.add_argument("--plant", help="simulator plant file (needed by the oracle observer)")
    parser.add_argument("--ground-truth", choices=GROUND_TRUTHS, default="auto",
                        help="true external torque: auto (default: the bag's /ground_truth topic, else its wrist "
                             "F/T, else --reference-bag), zero (the robot touched nothing: every estimate is "
                             "error), or one of topic, ft, reference (an error if the data lack it)")
    add_trim_option(parser)
    parser.add_argument("--tare-at", type=float, metavar="SECONDS",
                        help="start a tare (the node's ~/tare: average τ_ext over tare.duration s at rest, then "
                             "subtract it) at the first sample at rest from SECONDS after the bag's start")
    parser.add_argument("--out", required=True, help="output directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole (once the new output is complete)")
    estimates = parser.add_mutually_exclusive_group()
    estimates.add_argument("--estimates-bag", action="store_true", dest="estimates_bag", default=None,
                           help=f"write the estimates bag also for more than {ESTIMATES_BAG_S:.0f} s of data")
    estimates.add_argument("--no-bag", action="store_false", dest="estimates_bag",
                           help="never write the estimates bag")
    parser.add_argument("--no-plots", action="store_true",
                        help="skip the plots and report.md (metrics.json only; matplotlib is not loaded)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.out, args.force, (args.bag, args.reference_bag, args.model))
    config = load_config(args.config)
    model_dir = args.model or config.model_dir
    trained = load_model(model_dir, config.joint_names, urdf_sha256(config.urdf))
    source = trained.info.get("source") or ", ".join(
        str(bag.get("name", bag) if isinstance(bag, dict) else bag) for bag in trained.info.get("bags") or []) or "?"
    which = "" if args.model else " (the config's model_dir)"
    print(f"[replay] URDF {config.urdf}; model {model_dir}{which}, trained on {source}", flush=True)
    oracle = plant_oracle(config, args.plant)
    observers = parse_observers(args.observers, oracle is not None and trained.augmentation is None)
    if oracle is not None and trained.augmentation is not None and args.observers == "all":
        print("[replay] oracle skipped: it runs on the plant's own rigid body and friction, and this "
              "model is augmented", flush=True)
    with numerical_failures([args.bag], "the replay", "check the bag's skipped-sample lines above, and --trim what "
                            "the model was not trained for"):
        replay(config, trained, Path(args.bag), Path(args.out), observers,
               Path(args.reference_bag) if args.reference_bag else None, oracle, write_bag=args.estimates_bag,
               log=lambda line: print(line, flush=True), truth_kind=args.ground_truth, trim=tuple(args.trim),
               tare_at=args.tare_at, plots=not args.no_plots, force=args.force)
    print(f"[replay] wrote {args.out}/metrics.json{'' if args.no_plots else ' and report.md'}", flush=True)
    return 0
