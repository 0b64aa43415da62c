"""``kvark benchmark --real BAG``: every observer on a contact-free recording of a real robot.

The recording is split in time: the first ``--train-share`` (70 %) trains the models (and, for the
augmented model, ``kvark diagnose``), the rest is held out. The robot touched nothing, so the true
external torque is zero there and every estimate is error: the report gives each observer's false
τ_ext (joint RMSE, N·m), false force (N), the coverage95 of zero (share of joint samples whose 95 %
interval contains 0; also per joint, for the whole vector in the χ²_n 95 % ellipsoid of the full covariance,
and the share of samples where some joint's interval misses 0 against its nominal 1 − 0.95ⁿ) and the
false-contact share (samples flagged), and each observer's mean 95 % interval score (``metrics.interval_score``), for
the nominal URDF model and for the model augmented with what the diagnosis named. A config whose
``model_augmentation`` names a calibration (e.g. a known-load one, ``kvark diagnose --known-load``) is a calibrated
robot: the diagnosis then names what changed since (``--against``), and the report states the calibration's drive
gains. Two lines judge the intervals on the augmented model (the nominal one beside them): K-VARK's coverage of zero
≥ ``JOINT_COVERAGE`` on every joint, and its interval score no worse than any other observer's that reports an
interval. With ``--pushes F`` the held-out part is judged a second time, with known pushes of F newtons
superposed on it (``real_pushes``): how each observer follows a contact and lets go of it on the robot's own data,
augmented model. Nothing is tuned to the held-out part.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kvark_ros.core.config import (
    ConfigError,
    EstimatorConfig,
    default_config_path,
    load_config,
    parse_observers,
)
from kvark_ros.core.files import staged_directory, write_text_atomically
from kvark_ros.core.estimation.augmentation import load_augmentation
from kvark_ros.core.estimation.inputs import EstimatorInputs, select_samples
from kvark_ros.core.estimation.model_store import save_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import train_model
from kvark_ros.io import BagError
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.io.runs import numerical_failures
from kvark_ros.core.contact_events import CONTACT_TORQUE
from kvark_ros.tools.acceptance import JOINT_COVERAGE, verdict
from kvark_ros.tools.metrics import observer_metrics, static_band
from kvark_ros.tools.real_pushes import HOLD, RAMP, SETTLE, Pushes, phase_rmse, pushed
from kvark_ros.tools.replay import run_observer, zero_truth

LEARNED_BASELINES = ("gpadkf", "nnadkf", "gmr_gp")


def split(inputs: EstimatorInputs, train_share: float, rate: float,
          trim: tuple[float, float] = (0.0, 0.0)) -> tuple[EstimatorInputs, EstimatorInputs]:
    """(training part, held-out part) by time of the recording less ``trim`` (s dropped at its start and end),
    every k-th sample kept so the rate is about ``rate`` Hz (0: as recorded; ``decimation_step``)."""
    kept = select_samples(inputs, trim, rate)
    cut = kept.stamp[0] + train_share * (kept.stamp[-1] - kept.stamp[0])
    return kept.take(kept.stamp < cut), kept.take(kept.stamp >= cut)


def evaluate(config: EstimatorConfig, trained: Any, held: EstimatorInputs, observers: Sequence[str],
             log, pushes: Pushes | None = None) -> dict[str, Any]:
    """metrics.json-style entries of every observer on the held-out part, against a zero truth, or with ``pushes``
    on the pushed part against their τ_ext (plus ``push_rmse``: ``phase_rmse``)."""
    truth = zero_truth(held, "contact-free recording") if pushes is None else pushes.truth
    inputs = held if pushes is None else pushes.inputs
    band = None if pushes is None else static_band(trained)
    results = {}
    for step, name in enumerate(observers, start=1):
        result = run_observer(config, trained, inputs, name, truth_tau=truth.tau_ext)
        results[name] = observer_metrics(result, truth, inputs.stamp, band=band)
        if pushes is None:
            log(f"[benchmark] {step}/{len(observers)} {name:<11} false τ_ext "
                f"{results[name]['joint_rmse_mean']:.3f} N·m")
        else:
            results[name]["push_rmse"] = phase_rmse(result, pushes)
            log(f"[benchmark] {step}/{len(observers)} {name:<11} τ_ext RMSE during the pushes "
                f"{results[name]['push_rmse']['during']:.3f} N·m, after them {results[name]['push_rmse']['after']:.3f}")
    return results


def report(results: dict[str, Any]) -> str:
    """report.md: one row per observer, nominal and augmented side by side."""
    lines = [f"# Real recording `{results['bag']}`", "",
             f"- {results['samples']['train']} training samples (first {results['train_share']:.0%}), "
             f"{results['samples']['held_out']} held out at about {results['rate_hz']:.0f} Hz; τ_m from "
             f"{results['torque_source']}; true external torque zero (contact-free recording)"
             + (" after dropping {:g} s at the start and {:g} s at the end".format(*results["trim_s"])
                if any(results.get("trim_s", ())) else ""),
             f"- augmentation named by kvark diagnose: {', '.join(results['augmentation']['effects']) or 'none'} "
             f"(held-out gap {results['augmentation']['gap_before']:.3f} → "
             f"{results['augmentation']['gap_after']:.3f} N·m)"
             + ("" if not results.get("calibration") else f", against the calibration `{results['calibration']}`"),
             f"- drive gains: {gains_sentence(results['augmentation'].get('drive_gains'), results['joint_names'])}",
             "", "| observer | false τ_ext RMSE (N·m) nominal / augmented | false force RMSE (N) | "
             "coverage95 of 0 | vector coverage95 of 0 | any-joint miss of 0 | interval score (N·m) | "
             "false contact share |",
             "|---|---|---|---|---|---|---|---|"]
    nominal, augmented = results["nominal"], results["augmented"]

    def cell(entry: dict, key: str, digits: int = 3) -> str:
        value = entry.get(key)
        return "–" if value is None else f"{value:.{digits}f}"

    for name, entry in nominal.items():
        other = augmented.get(name, {})
        lines.append(f"| {name} | {cell(entry, 'joint_rmse_mean')} / {cell(other, 'joint_rmse_mean')} | "
                     f"{cell(entry, 'force_rmse_mean')} / {cell(other, 'force_rmse_mean')} | "
                     f"{cell(entry, 'coverage95')} / {cell(other, 'coverage95')} | "
                     f"{cell(entry, 'vector_coverage95')} / {cell(other, 'vector_coverage95')} | "
                     f"{cell(entry, 'any_joint_miss_share')} / {cell(other, 'any_joint_miss_share')} | "
                     f"{cell(entry, 'interval_score95')} / {cell(other, 'interval_score95')} | "
                     f"{cell(entry['contact'], 'false_contact_share')} / "
                     f"{cell(other.get('contact', {}), 'false_contact_share')} |")
    return "\n".join(lines + ["", *per_joint_coverage(nominal, augmented, results["joint_names"]),
                              "", *interval_lines(results), *push_table(results.get("pushes"))]) + "\n"


def gains_sentence(record: dict[str, Any] | None, joint_names: Sequence[str]) -> str:
    """The drive gains the augmented model reads τ_m through: measured with a known load (each ± its 95 %
    half-width; a joint the data did not narrow below the prior: not identified) or unidentified."""
    if not record:
        return "not stated (a diagnosis written before the record existed)"
    if record.get("calibrated_with") is None:
        return (f"unidentified (τ_m is {record['torque_measurement']}; free motion cannot tell them from the links' "
                f"inertia: a payload's mass may be off by up to ±{record['mass_share']:.0%})")
    from kvark_ros.gap.known_load import gain_cells      # the diagnosis' modules only where a report needs them
    found = ", ".join(gain_cells(record, joint_names))
    return f"measured with a known load of {record['calibrated_with']['mass_kg']:g} kg: {found} (95 %)"


def interval_lines(results: dict[str, Any]) -> list[str]:
    """The intervals judged on the augmented model (the nominal model beside, for reference): K-VARK's coverage95 of
    zero at least ``JOINT_COVERAGE`` on every joint, and its mean interval score no worse than that of any other
    observer that reports an interval (the score pays for width and for every miss, so neither a too-wide nor a
    too-narrow interval wins)."""
    lines = ["Intervals (judged on the augmented model; the nominal model for reference):", ""]
    for model, judged in (("augmented", True), ("nominal", False)):
        entries = results.get(model) or {}
        kvark = entries.get("kvark") or {}
        per_joint, score = kvark.get("coverage95_per_joint"), kvark.get("interval_score95")
        if per_joint:
            lines.append(f"- {model}: K-VARK coverage95 of 0 per joint {min(per_joint):.3f}-{max(per_joint):.3f} "
                         f"(≥ {JOINT_COVERAGE} on every joint: {verdict(min(per_joint) >= JOINT_COVERAGE, judged)})")
        others = {name: entry["interval_score95"] for name, entry in entries.items()
                  if name != "kvark" and entry.get("interval_score95") is not None}
        if score is not None and others:
            best = min(others, key=others.get)
            ok = score <= others[best]
            lines.append(f"- {model}: K-VARK interval score {score:.3f} N·m against the best other observer with an "
                         f"interval, {best} {others[best]:.3f} (no worse than every other: {verdict(ok, judged)})")
    return lines


def push_table(pushes: dict[str, Any] | None) -> list[str]:
    """report.md's third table (``--pushes``): each observer on the held-out part with the pushes superposed."""
    if not pushes:
        return []
    lines = ["", f"Known pushes superposed on the held-out part (augmented model): {pushes['count']} pushes of "
             f"{pushes['force_n']:g} N at the end-effector origin along the {pushes['frame']} axes, each "
             f"{pushes['hold_s']:g} s between {pushes['ramp_s']:g} s ramps; τ_m less Jᵀ F, q and q̇ as recorded "
             "(a stiffly position-controlled arm; kvark_ros/tools/real_pushes.py). Contact delay: from the first "
             f"sample a push puts more than {CONTACT_TORQUE:g} N·m on a joint to the flag; after: the free motion from "
             f"{SETTLE:g} s after each push to the next.", "",
             "| observer | τ_ext RMSE (N·m) all / during / after | force RMSE (N) | coverage95 | contact delay median "
             "(ms) | pushes never flagged | false contact share |", "|---|---|---|---|---|---|---|"]

    def cell(value: Any, digits: int = 3, scale: float = 1.0) -> str:
        return "–" if value is None else f"{value * scale:.{digits}f}"

    for name, entry in pushes["observers"].items():
        contact, phases = entry["contact"], entry["push_rmse"]
        lines.append(f"| {name} | {cell(entry['joint_rmse_mean'])} / {cell(phases['during'])} / "
                     f"{cell(phases['after'])} | {cell(entry.get('force_rmse_mean'))} | "
                     f"{cell(entry.get('coverage95'))} | {cell(contact.get('detection_delay_median'), 0, 1000.0)} | "
                     f"{contact.get('missed_onsets', '–')} | {cell(contact.get('false_contact_share'))} |")
    return lines


def per_joint_coverage(nominal: dict[str, Any], augmented: dict[str, Any], joint_names: Sequence[str]) -> list[str]:
    """report.md's second table: coverage95 of zero per joint, one row per observer with a covariance and model
    (a joint far below 0.95 has a σ too small for what its model misses); nominal of the any-joint miss."""
    rows = [(f"{name}, {model}", entry) for model, entries in (("nominal", nominal), ("augmented", augmented))
            for name, entry in entries.items() if entry.get("coverage95_per_joint")]
    if not rows:
        return []
    n = len(rows[0][1]["coverage95_per_joint"])
    lines = [f"Coverage95 of 0 per joint (any-joint miss nominal for independent joints: 1 − 0.95^{n} = "
             f"{rows[0][1]['any_joint_miss_nominal']:.3f}):", "",
             "| observer, model | " + " | ".join(joint_names) + " |", "|---|" + "---|" * n]
    for label, entry in rows:
        lines.append(f"| {label} | " + " | ".join(f"{v:.3f}" for v in entry["coverage95_per_joint"]) + " |")
    return lines


def run_real(args: argparse.Namespace) -> int:
    """The ``--real`` job (module docstring), built beside ``--out`` and swapped in whole (``staged_directory``)."""
    with numerical_failures([args.real], "the benchmark", "check the bag's skipped-sample lines above, and --trim "
                            "what is not free motion"), staged_directory(args.out, args.force) as out:
        return _run_real(args, out)


def _run_real(args: argparse.Namespace, out: Path) -> int:
    """``run_real`` writing into ``out``."""
    started = time.perf_counter()

    def log(line: str) -> None:
        print(line, flush=True)

    config = load_config(args.config or default_config_path(args.robot))
    if not 0.1 <= args.train_share <= 0.9:
        raise ConfigError(f"--train-share {args.train_share} is outside [0.1, 0.9]; the held-out part must be "
                          "long enough to judge and the training part to learn from")
    inputs = read_inputs(args.real, config)[1]
    train, held = split(inputs, args.train_share, args.rate, tuple(args.trim))
    if len(train) < 500 or len(held) < 100:
        raise BagError(f"{args.real}: {len(train)} training and {len(held)} held-out samples; record at least "
                       "a few seconds of motion")
    observers = [name for name in parse_observers(args.observers) if name != "oracle"
                 and not (args.no_baselines and name in LEARNED_BASELINES)]
    log(f"[benchmark] {args.real}: {len(train)} training and {len(held)} held-out samples (τ_m from "
        f"{inputs.torque_source})")
    calibration = config.model_augmentation
    base = load_augmentation(calibration, config.joint_names) if calibration else None
    config = replace(config, model_augmentation="")     # each model trained here carries its own
    robot = RobotModel.from_config(config)
    try:
        pushes = pushed(robot, config.wrench.frame, held, args.pushes) if args.pushes else None
    except ValueError as exc:
        raise ConfigError(f"--pushes {args.pushes:g}: {exc}") from exc
    steps = 4 if pushes is None else 5
    log(f"[benchmark] step 1/{steps}: training on the nominal model")
    nominal = train_model(robot, config.robot, [train], baselines=not args.no_baselines, log=log,
                          settings=config.filter, residual_inputs=args.residual_inputs)
    save_model(out / "model", nominal)
    log(f"[benchmark] step 2/{steps}: {len(observers)} observers on the held-out part, nominal model")
    results: dict[str, Any] = {
        "bag": str(args.real), "train_share": args.train_share, "trim_s": [float(v) for v in args.trim],
        "torque_source": inputs.torque_source, "joint_names": list(config.joint_names), "calibration": calibration,
        "residual_inputs": args.residual_inputs,
        "rate_hz": round(1.0 / float(np.median(np.diff(held.stamp))), 1),
        "samples": {"train": len(train), "held_out": len(held)},
        "nominal": evaluate(config, nominal, held, observers, log)}
    from kvark_ros.gap.diagnose import train_on_diagnosis
    log(f"[benchmark] step 3/{steps}: diagnosis of the training part"
        + ("" if base is None else f" against the calibration {calibration}") + ", training on the augmented model")
    calibrated = robot if base is None else RobotModel.from_config(config, base)
    augmented, results["augmentation"] = train_on_diagnosis(config, calibrated, [train], out,
                                                            baselines=not args.no_baselines, log=log,
                                                            plots=not args.no_plots,
                                                            residual_inputs=args.residual_inputs)
    log(f"[benchmark] step 4/{steps}: {len(observers)} observers on the held-out part, augmented model")
    results["augmented"] = evaluate(config, augmented, held, observers, log)
    if pushes is not None:
        log(f"[benchmark] step 5/{steps}: {len(observers)} observers on the held-out part with "
            f"{len(pushes.starts)} pushes of {args.pushes:g} N superposed, augmented model")
        results["pushes"] = {"force_n": args.pushes, "count": len(pushes.starts), "starts_s": pushes.starts,
                             "frame": config.wrench.frame, "ramp_s": RAMP, "hold_s": HOLD,
                             "observers": evaluate(config, augmented, held, observers, log, pushes)}
    write_text_atomically(out / "results.json", json.dumps(results, indent=2))
    write_text_atomically(out / "report.md", report(results))
    if not args.no_plots:      # matplotlib only when drawing, as replay
        from kvark_ros.tools.real_figures import write_real_figures
        write_real_figures(out, config, held, {"nominal": nominal, "augmented": augmented}, results, pushes)
    log(report(results))
    log(f"[benchmark] wrote {args.out}/results.json and {args.out}/report.md in "
        f"{(time.perf_counter() - started) / 60:.1f} min")
    return 0
