"""``kvark diagnose``: where the nominal model and the measured data disagree, in physical terms.

1. the gap ``τ_m − τ_EL`` per joint on the recorded motion (q̈ and τ_m through the same
   Savitzky-Golay filter as ``kvark train``);
2. greedy forward selection over the named effects of ``kvark_ros.gap.effects`` (``gap.selection``): samples are
   split in time (the last ``holdout`` share of every recording is held out); each round every (effect, joint set)
   candidate is fitted on the training part by bounded least squares within the priors (every effect within its
   prior scaled to the robot, ``gap.priors``; payload and link changes also with Gaussian priors toward the URDF and
   kept physically consistent), the one that lowers the held-out gap most is accepted when the BIC improves and the
   held-out gap of the affected joints drops by at least ``MIN_REDUCTION``; the search stops when no candidate is
   accepted. A backward pass then refits without each accepted effect in turn and drops the one whose removal costs
   least while removing it does not worsen the BIC or does not worsen the held-out gap of any joint by
   ``MIN_REDUCTION`` and ``MIN_ABS_REDUCTION`` (an effect accepted early can be made redundant by later ones, and a
   small effect can soak up what a later one explains); repeated until every remaining effect is needed. Because
   effects can look alike along a motion (a payload and drive gain errors both scale with gravity), greedy selection
   is run ``STARTS`` times, each from another acceptable first effect; a later selection replaces the kept one when
   it has a lower BIC with no more effects (BIC alone, with correlated samples, lets small spurious effects in: a run
   that trades one look-alike for the right effect ends with fewer of them). Every start begins from the URDF's
   priors; a candidate's tightened priors (physical consistency) are kept only when it is accepted. Each remaining
   effect's reported reduction is the held-out gap of all effects but that one against all of them;
3. refits the final set under the chosen start's priors until every link it changes is physically consistent, drops
   the joints (bodies) that the joint fit put at a bound of their prior (another effect seen through them, as at
   acceptance); against a calibrated model prefers a payload to link changes that explain no more
   (``payload_first``); names what the data want beyond a prior, the explanation that explains most first
   (``admissible.beyond_priors``), and the flag that allows it; and writes ``diagnosis.json``, ``augmentation.yaml``
   (the accepted effects, loadable by ``effects.augmentation_gap``; against an augmented model, its effects first),
   ``report.md`` and plots (``gap.diagnosis_result``, ``gap.diagnosis_report``).

With a known-load recording (``--known-load MASS BAG``, ``gap.known_load``) the drive gains are measured: the
recording joins the others with the known part of its load taken out of its gap, the load's unknown moments are
nuisance parameters and drive_gain on every joint is in every selection. What the load identifies is kept from that
fit, the drive gains; every other effect is then selected again on the free-motion recordings alone, on the robot
with those gains (as against a calibrated model, from the whole library but drive_gain): fitted with the loaded
recording, link inertia and friction also took up its misfit (on the real UR10e the free-motion figures lost 0.13
N·m to it). A gain that fit wanted beyond its prior stays unidentified, and that record leads the warnings. Without a
known load the report says the gains are unidentified and how far a payload's mass may be off because of them.

Against a calibrated model the library is what changes between runs of one robot (``CHANGES_BETWEEN_RUNS``: a load,
friction, torque offsets); links, armature, gains, ripple and encoders are its construction, calibrated with it.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import yaml

from kvark_ros.core.config import ConfigError, EstimatorConfig, load_config
from kvark_ros.core.effect_catalog import CHANGES_BETWEEN_RUNS, EFFECT_NAMES
from kvark_ros.core.estimation.augmentation import Augmentation, load_augmentation, parse_augmentation
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.linalg import single_threaded_blas
from kvark_ros.core.estimation.model_store import TrainedModel, save_model
from kvark_ros.core.estimation.robot_model import RobotModel, flange_link_parameters
from kvark_ros.core.files import check_output, staged_directory
from kvark_ros.core.hints import did_you_mean
from kvark_ros.core.learning.training import SAVGOL_WINDOW, smoothed_signals, train_model
from kvark_ros.gap.diagnosis_report import Diagnosis, augmentation as augmentation_document, write_outputs
from kvark_ros.gap.diagnosis_result import DiagnosisInputs, state
from kvark_ros.gap.effects import LINK_PRIOR, Priors, Signals, flange_parameter_map, link_prior_scale, signals
from kvark_ros.gap.fitting import Fitter
from kvark_ros.gap.known_load import KnownLoad, calibrate_with, load_signals
from kvark_ros.gap.plausibility import beyond_prior_warning, prior_summary
from kvark_ros.gap.priors import FLAGS, MEASUREMENT_WIDTHS, robot_priors
from kvark_ros.gap.selection import per_joint, rmse, select
from kvark_ros.io.recorded_inputs import load_recordings
from kvark_ros.cli_options import add_sample_options
from kvark_ros.io.runs import numerical_failures

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

HOLDOUT = 0.3            # share of every recording (its end) held out
DECIMATE_DT = 0.008      # s, sample spacing after smoothing (the filter passes far less than 60 Hz)


def prepare(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float,
            load: KnownLoad | None = None) -> tuple[Signals, Signals]:
    """(train, held-out) samples of every recording, filtered, trimmed and decimated; with a known ``load`` its
    recordings too, their gap less the load's known torque (``known_load.load_signals``)."""
    train_idx, held_idx, parts, loaded = [], [], [], []
    offset = 0
    for seg, with_load in [*((seg, False) for seg in segments), *((seg, True) for seg in (load.segments if load
                                                                                             else ()))]:
        qdd, tau_m = smoothed_signals(seg.stamp, seg.qd, seg.tau_m)
        dt = float(np.median(np.diff(seg.stamp)))
        trim = int(round(SAVGOL_WINDOW / dt))
        step = max(1, int(round(DECIMATE_DT / dt)))
        keep = np.arange(trim, len(seg.stamp) - trim, step)
        if len(keep) < 20:
            if with_load:
                raise ValueError("the known-load recording is too short to diagnose (need a few seconds of motion)")
            continue
        parts.append((seg.q[keep], seg.qd[keep], qdd[keep], tau_m[keep]))
        loaded.append(np.full(len(keep), with_load))
        split = int(round(len(keep) * (1.0 - holdout)))
        train_idx.append(offset + np.arange(split))
        held_idx.append(offset + np.arange(split, len(keep)))
        offset += len(keep)
    if not parts or all(mask.all() for mask in loaded):
        raise ValueError("recordings too short to diagnose (need a few seconds of motion)")
    q, qd, qdd, tau = (np.concatenate([p[i] for p in parts]) for i in range(4))
    s = signals(robot, q, qd, qdd, tau)
    if load is not None:
        s = load_signals(s, np.concatenate(loaded), load)
    return s.take(np.concatenate(train_idx)), s.take(np.concatenate(held_idx))


def diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float = HOLDOUT,
             effects: Sequence[str] | None = None, log: Callable[[str], None] = print, *,
             priors: Priors, known_load: KnownLoad | None = None) -> Diagnosis:
    """Greedy selection of named effects explaining the gap (see module docstring), within ``priors`` (required:
    their width follows the robot's ``torque_measurement``; completed with the flange link's mass of ``robot`` and
    every effect's bounds derived from its URDF, ``gap.priors.robot_priors``; ``priors.payload_com`` fixes the
    payload's centre of mass). ``effects`` None: every effect; against a calibrated model (``robot.augmentation``)
    only ``CHANGES_BETWEEN_RUNS``. ``known_load``: a known-load calibration (``gap.known_load``), on the nominal
    model only."""
    if known_load is not None and robot.augmentation is not None:
        raise ValueError("a known-load calibration calibrates the robot's construction (its drive gains): run it on "
                         "the nominal model, not against a calibrated one")
    effects = effects or (EFFECT_NAMES if robot.augmentation is None else CHANGES_BETWEEN_RUNS)
    flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    priors = robot_priors(robot, replace(priors, flange_mass=float(flange[0])))
    with single_threaded_blas():  # hundreds of small least-squares fits
        found = _diagnose(robot, segments, holdout, effects, log, priors, known_load, robot.augmentation is not None)
        if known_load is None:
            return found
        calibrated = robot.with_augmentation(measured_gains(found, robot, known_load))
        log("[diagnose] the drive gains measured; every other effect again on the free-motion recordings alone, "
            "with those gains")
        again = _diagnose(calibrated, segments, holdout, [name for name in effects if name != "drive_gain"], log,
                          priors, None, new_load=False)
        again.result["known_load_calibration"] = True
        # The gains the fit with the load wanted beyond their prior (left unidentified) lead the warnings.
        carried = [{**record, "known_load": True} for record in found.result["beyond_priors"]
                   if record["effect"] == "drive_gain"]
        again.result["beyond_priors"] = [*carried, *again.result["beyond_priors"]]
        again.result["warnings"] = [*(beyond_prior_warning(record, priors, robot.joint_names) for record in carried),
                                    *again.result["warnings"]]
        return replace(again, relative_to=calibrated)


def measured_gains(found: Diagnosis, robot: RobotModel, load: KnownLoad) -> Augmentation:
    """The drive_gain effect of a known-load diagnosis ``found`` on the nominal ``robot``, with its ``drive_gains``
    record (the gains' intervals and the load), as the augmentation the rest is diagnosed against."""
    document = augmentation_document(found, robot)
    document["effects"] = [entry for entry in document["effects"] if entry["name"] == "drive_gain"]
    return parse_augmentation(yaml.safe_dump(document, sort_keys=False), robot.joint_names,
                              f"the drive gains measured with {load.source or f'{load.mass:g} kg'}")


def body_fitter(robot: RobotModel, train: Signals, held: Signals, priors: Priors) -> Fitter:
    """The Fitter of a diagnosis: rows weighted by 1/max(training gap RMSE, 0.01 N·m), the URDF's bodies and the
    Gaussian priors of payload and link_inertia (docs/method.md §8.3)."""
    fitter = Fitter(train, held, 1.0 / np.maximum(rmse(train.gap), 0.01), priors)
    fitter.flange = flange_link_parameters(robot.model, robot.flange_frame_id)
    fitter.flange_map = flange_parameter_map(robot)[1]
    link_scale = link_prior_scale(robot)
    flange_moment = float(np.max(np.abs(fitter.flange[[4, 6, 9]])))
    # payload: free (a tool of any mass, CoM and inertia); only if the flange link comes out inconsistent do its
    # second moments get a prior, first 30 % of the flange link's largest moment (as link_inertia's), then halved.
    fitter.prior_scale = {"link_inertia": link_scale, "payload": np.full(10, np.inf)}
    fitter.first_prior = {"link_inertia": link_scale, "payload": np.concatenate(
        [np.full(4, np.inf), np.full(6, LINK_PRIOR["inertia"] * flange_moment)])}
    fitter.links = [robot.model.inertias[i].toDynamicParameters() for i in range(1, robot.n)]
    return fitter


def _diagnose(robot: RobotModel, segments: Sequence[EstimatorInputs], holdout: float, effects: Sequence[str],
              log: Callable[[str], None], priors: Priors, load: KnownLoad | None, new_load: bool) -> Diagnosis:
    """``diagnose``'s selection on ``robot``; ``new_load`` (against a calibrated model, but not in a known-load
    calibration's second pass) prefers a payload to link changes that explain no more (``selection.payload_first``)."""
    if not 0.05 <= holdout <= 0.9:
        raise ValueError(f"holdout must be in [0.05, 0.9], got {holdout}")
    unknown = sorted(set(effects) - set(EFFECT_NAMES))
    if unknown:
        raise ValueError(f"unknown effects {unknown}; known: {list(EFFECT_NAMES)}")
    inputs = DiagnosisInputs(robot, segments, holdout, effects, priors, load)
    train, held = prepare(robot, segments, holdout, load)
    log(f"[diagnose] {len(train)} training and {len(held)} held-out samples (every {DECIMATE_DT * 1e3:.0f} ms, last "
        f"{holdout:.0%} of each recording held out"
        + ("" if load is None else f"; with the known load of {load.mass:g} kg among them") + ")")
    fitter = body_fitter(robot, train, held, priors)
    if load is not None:
        calibrate_with(fitter, load)
    log(f"[diagnose] held-out gap per joint before (N·m): {per_joint(rmse(held.gap), robot.joint_names)}")
    terms, fit = select(fitter, effects, robot.joint_names, log, new_load)
    return state(inputs, fitter, terms, fit, log, DECIMATE_DT)


def train_on_diagnosis(config: EstimatorConfig, robot: RobotModel, segments: Sequence[EstimatorInputs], out: Path,
                       baselines: bool, seed: int = 0, log: Callable[[str], None] = print,
                       known_load: KnownLoad | None = None, plots: bool = True,
                       residual_inputs: str = "auto") -> tuple[TrainedModel, dict]:
    """Diagnose ``segments`` on ``robot`` (the nominal model, or a calibrated one: then what changed since, as
    ``--against``) within the priors of ``config``'s torque measurement, as ``kvark diagnose`` does (with
    ``known_load``: ``--known-load``, on the nominal model); write the outputs to ``out/diagnosis`` (its figures
    with ``plots``), train on the model augmented with what was named (on ``segments`` alone: the known load is not
    the robot's; the KMP's inputs ``residual_inputs``, as ``train_model``'s) and save it to ``out/model_augmented``.
    Returns the trained model and a summary: the effects, the mean held-out gap before/after (N·m), the effects
    against their priors (``plausibility.prior_summary``) and the drive gains."""
    diagnosis = diagnose(robot, segments, log=log, priors=Priors(torque_measurement=config.torque_measurement),
                         known_load=known_load)
    for path in write_outputs(diagnosis, robot, out / "diagnosis", config.robot, plots):
        log(f"[diagnose] wrote {path}")
    augmentation = load_augmentation(out / "diagnosis" / "augmentation.yaml", config.joint_names)
    trained = train_model(RobotModel.from_config(config, augmentation), config.robot, segments, baselines=baselines,
                          seed=seed, log=log, settings=config.filter, residual_inputs=residual_inputs)
    save_model(out / "model_augmented", trained)
    return trained, {"effects": list(augmentation.effect_names),
                     "gap_before": diagnosis.result["gap_before"]["joint_rmse_mean"],
                     "gap_after": diagnosis.result["gap_after"]["joint_rmse_mean"],
                     "priors": prior_summary(diagnosis.result), "drive_gains": diagnosis.result["drive_gains"]}


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "diagnose", help="name the physical effects the nominal model lacks, from contact-free bags",
        description="Compute the gap τ_m − τ_EL between the commanded torque and the nominal model on "
                    "contact-free bags, select named physical effects (friction, armature, a payload or tool "
                    "mismatch at the flange, link inertial parameters, drive gain, torque offset, ripple, joint "
                    "offset) greedily on held-out data within plausible priors, every link kept physically "
                    "consistent, and write diagnosis.json, augmentation.yaml, report.md (with warnings and "
                    "look-alikes) and plots. An existing non-empty --out is replaced only with --force.")
    parser.add_argument("--config", required=True, help="estimator config YAML (e.g. config/panda.yaml)")
    parser.add_argument("--bags", nargs="+", required=True, metavar="BAG", help="contact-free bags")
    add_sample_options(parser, HOLDOUT, "share of every bag (its end) held out for selection")
    parser.add_argument("--out", required=True, help="output directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole (once the new output is complete)")
    parser.add_argument("--against", metavar="MODEL_DIR|AUGMENTATION",
                        help="diagnose relative to a model already corrected by this augmentation.yaml (or a model "
                             "directory's): only what changed since is named (a new tool on a calibrated robot), "
                             "from the effects that change between runs unless --effects says otherwise; the "
                             "written augmentation.yaml holds both")
    parser.add_argument("--known-load", nargs="+", metavar="MASS BAG",
                        help="a known-load calibration: MASS kg fixed to the flange during BAG (one or more bags, "
                             "motion like the others'); the drive gains are measured against it (free motion cannot "
                             "tell them from the links' inertia) and stated with their intervals, which a payload's "
                             "mass read with the written model carries; every other effect is then selected on the "
                             "--bags alone, with those gains. Not with --against")
    parser.add_argument("--known-load-com", type=_com, metavar="X,Y,Z",
                        help="the known load's centre of mass in the flange frame, m (default: fitted)")
    parser.add_argument("--payload-com", type=_com, metavar="X,Y,Z",
                        help="the payload's known centre of mass in the flange frame, m: only its mass and inertia "
                             "are fitted")
    parser.add_argument("--effects", type=_effect_list, default=None, metavar="A,B",
                        help=f"restrict the library to these effects (default all: {','.join(EFFECT_NAMES)}; with "
                             f"--against what changes between runs of one robot: {','.join(CHANGES_BETWEEN_RUNS)})")
    parser.add_argument("--max-gain-error", type=float, default=None, metavar="X",
                        help="prior of drive_gain: |1 − g| ≤ X (default from robot_model.torque_measurement: "
                             + ", ".join(f"{w['gain']:g} {m}" for m, w in MEASUREMENT_WIDTHS.items()) + ")")
    parser.add_argument("--max-joint-offset", type=float, default=float(np.degrees(Priors.max_joint_offset)),
                        metavar="DEG",
                        help="prior of joint_offset: |δ| ≤ DEG degrees (default 1; absolute encoders)")
    parser.add_argument("--prior", type=_prior_scale, action="append", default=[], metavar="EFFECT=FACTOR",
                        help="scale EFFECT's prior (derived from the URDF and robot_model.torque_measurement, "
                             "docs/method.md §8.6) by FACTOR, e.g. armature=2; repeatable")
    parser.add_argument("--no-plots", action="store_true", help="do not write plots")
    parser.set_defaults(run=run)


def _com(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected three finite numbers X,Y,Z in metres, got {text!r}")
    return values


def _prior_scale(text: str) -> tuple[str, float]:
    name, value = (part.strip() for part in text.partition("=")[::2])
    if name in FLAGS:
        raise argparse.ArgumentTypeError(f"{name}'s prior has its own flag: {FLAGS[name]}")
    if name not in EFFECT_NAMES:
        raise argparse.ArgumentTypeError(f"unknown effect {name!r}{did_you_mean(name, EFFECT_NAMES)}; known: "
                                         f"{','.join(EFFECT_NAMES)}")
    try:
        factor = float(value)
    except ValueError:
        factor = float("nan")
    if not (np.isfinite(factor) and factor > 0):
        raise argparse.ArgumentTypeError(f"expected EFFECT=FACTOR with a positive FACTOR, got {text!r}")
    return name, factor


def _effect_list(text: str) -> tuple[str, ...]:
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = sorted(set(names) - set(EFFECT_NAMES))
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown effects {unknown or [text]}; known: {','.join(EFFECT_NAMES)}")
    return names


def _known_load(values: Sequence[str] | None, against: str | None) -> tuple[float, list[str]] | None:
    """(mass kg, bags) of ``--known-load MASS BAG [BAG …]``, or None; one-line errors for what it cannot be."""
    if not values:
        return None
    if against:
        raise ConfigError("--known-load calibrates the robot's construction (its drive gains): run it without "
                          "--against, then diagnose new loads --against its output")
    try:
        mass = float(values[0])
    except ValueError:
        mass = float("nan")
    if not (np.isfinite(mass) and mass > 0.0) or len(values) < 2:
        raise ConfigError(f"--known-load {' '.join(values)}: expected MASS (kg, positive) then one or more bags")
    return mass, list(values[1:])


def run(args: argparse.Namespace) -> int:
    known = _known_load(args.known_load, args.against)
    if args.known_load_com is not None and known is None:
        raise ConfigError("--known-load-com needs --known-load MASS BAG")
    check_output(args.out, args.force, (*args.bags, args.against, *(known[1] if known else ())))
    config = load_config(args.config)
    base = None
    if args.against:
        source = Path(args.against)
        base = load_augmentation(source / "augmentation.yaml" if source.is_dir() else source, config.joint_names)
        print(f"[diagnose] relative to the model augmented by {base.source}: {', '.join(base.effect_names)}",
              flush=True)
    robot = RobotModel.from_config(config, base)
    print(f"[diagnose] URDF {config.urdf}", flush=True)
    segments = load_recordings(args.bags, config, "diagnose", tuple(args.trim), args.rate)
    load = None
    if known is not None:
        mass, bags = known
        load = KnownLoad(mass, args.known_load_com, load_recordings(bags, config, "diagnose", tuple(args.trim),
                                                                    args.rate), f"{mass:g} kg on {', '.join(bags)}")
    log = lambda line: print(line, flush=True)   # noqa: E731
    if (args.max_gain_error is not None and args.max_gain_error <= 0) or args.max_joint_offset <= 0:
        raise ConfigError("--max-gain-error and --max-joint-offset must be positive")
    priors = Priors(max_gain_error=args.max_gain_error, max_joint_offset=float(np.radians(args.max_joint_offset)),
                    payload_com=args.payload_com, torque_measurement=config.torque_measurement,
                    scale=tuple(dict(args.prior).items()))
    out = Path(args.out)
    with numerical_failures([*args.bags, *(known[1] if known else ())], "the diagnosis", "check the bags' "
                            "skipped-sample lines above, --trim what is not motion, or try one bag at a time"), \
            staged_directory(out, args.force) as staging:
        diag = diagnose(robot, segments, args.holdout, effects=args.effects, log=log, priors=priors, known_load=load)
        written = write_outputs(diag, robot, staging, config.robot, plots=not args.no_plots)
    for path in written:
        log(f"[diagnose] wrote {out / path.relative_to(staging)}")
    return 0
