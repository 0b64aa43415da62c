"""``kvark train``: residual models and filter tuning from contact-free ROS 2 bags.

Reads the bags, trains with ``kvark_ros.core.learning.training`` (residuals τ_m − τ_EL, GMM → GMR → KMP,
covariance matching, the baselines' residual models; with a model augmentation from
``kvark diagnose`` the residuals are relative to the augmented model and the augmentation is
stored with the model), records where the model came from (bag and URDF hashes) and writes the
model directory with its plots beside it and swaps it in whole: a failed run leaves the previous model untouched, and
an existing non-empty ``--out`` is replaced only with ``--force``. ``--trim`` and ``--rate`` select the samples of
every bag (``select_samples``), ``--holdout`` is the share training holds out for its own checks. A fit the data
defeat is one error line naming the bags and what to check (``kvark_ros.io.runs.numerical_failures``), never a
traceback.
"""
from __future__ import annotations

import argparse
import hashlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kvark_ros.core.estimation.augmentation import load_augmentation
from kvark_ros.core.config import EstimatorConfig, load_config
from kvark_ros.core.estimation.model_store import write_model_files
from kvark_ros.core.files import check_output, staged_directory
from kvark_ros.core.estimation.residual.common import available_cores
from kvark_ros.core.estimation.robot_model import RobotModel, urdf_sha256
from kvark_ros.core.learning.training import HOLDOUT, INPUT_MODES, train_model
from kvark_ros.io.recorded_inputs import load_recordings
from kvark_ros.cli_options import add_sample_options
from kvark_ros.io.runs import numerical_failures

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers


def sha256_file(path: Path) -> str:
    """sha256 of one file, read in 1 MiB blocks."""
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


def positive_int(text: str) -> int:
    """An integer ≥ 1 (argparse type of --jobs)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_residual_inputs_option(parser: Any, judged_on: str) -> None:
    """``--residual-inputs`` (``train_model``'s ``residual_inputs``) on a parser or an argument group, as train and
    benchmark --real take it; ``judged_on``: the samples auto chooses by."""
    parser.add_argument("--residual-inputs", choices=INPUT_MODES, default="auto",
                        help="inputs of each joint's KMP residual: auto (default) chooses per joint between q̇ alone "
                             "(qd, the paper's model), q̇ with the joint position (qd_q) and q̇ with the model's "
                             f"gravity torque (qd_g) by log-likelihood on {judged_on.replace('%', '%%')}; or one of "
                             "them for every joint")


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "train", help="train the residual models and filter tuning from contact-free bags",
        description="Read contact-free ROS 2 bags (MCAP or sqlite3), compute the residual torque τ_m − τ_EL "
                    "per joint, fit GMM → GMR → KMP (and the baselines' models), tune the filters by "
                    "covariance matching and write the model directory atomically, with training plots. An "
                    "existing non-empty --out is replaced only with --force.")
    parser.add_argument("--config", required=True, help="estimator config YAML (e.g. config/panda.yaml)")
    parser.add_argument("--bags", nargs="+", required=True, metavar="BAG", help="training bags (directories or files)")
    parser.add_argument("--out", required=True, help="model directory to write (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole (once the new model is complete)")
    parser.add_argument("--augmentation", metavar="FILE",
                        help="augmentation.yaml of `kvark diagnose` to train on the improved model (default: the "
                             "config's model_augmentation; '' for none); copied into the model directory")
    parser.add_argument("--no-baselines", action="store_true",
                        help="skip the GMR-GP, sparse-GP and MLP baselines (faster)")
    add_residual_inputs_option(parser, "the last --holdout of every bag")
    parser.add_argument("--seed", type=int, default=0, help="random seed for the hold-out split and fits")
    parser.add_argument("--jobs", type=positive_int, default=None, metavar="N",
                        help="worker processes for the joints' fits, each with one BLAS thread (default: every "
                             f"available core, {available_cores()} here; 1 fits them one after the other in this "
                             "process); the model is the same for any N")
    parser.add_argument("--no-plots", action="store_true", help="do not write training plots")
    add_sample_options(parser, HOLDOUT, "share held out: random samples to calibrate the KMP's λ2 and the end of "
                                        "every bag to choose the residual inputs")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.out, args.force, (*args.bags, args.augmentation))
    config: EstimatorConfig = load_config(args.config)
    source = config.model_augmentation if args.augmentation is None else args.augmentation
    augmentation = load_augmentation(source, config.joint_names) if source else None
    robot = RobotModel.from_config(config, augmentation)
    print(f"[train] URDF {config.urdf}", flush=True)
    if augmentation is not None:
        print(f"[train] model augmented by {source}: {', '.join(augmentation.effect_names) or 'no effects'}",
              flush=True)
    segments = load_recordings(args.bags, config, "train", tuple(args.trim), args.rate)
    info = {"robot": config.robot, "joint_names": list(config.joint_names),
            "urdf_sha256": urdf_sha256(config.urdf),
            "augmentation": None if augmentation is None else {
                "file": Path(source).name, "effects": list(augmentation.effect_names)},
            "bags": [{"name": Path(bag).name, "sha256": bag_hash(Path(bag))} for bag in args.bags],
            "samples_selected": {"trim_s": [float(v) for v in args.trim], "rate_hz": args.rate,
                                 "holdout": args.holdout}}
    out, plots = Path(args.out), []
    with numerical_failures(args.bags, "training", "check the bags' skipped-sample lines above, --trim what is not "
                            "free motion, or train on more motion (a few seconds per bag at least)"):
        trained = train_model(robot, config.robot, segments, baselines=not args.no_baselines, seed=args.seed,
                              info=info, residual_inputs=args.residual_inputs,
                              log=lambda line: print(line, flush=True), jobs=args.jobs, settings=config.filter,
                              holdout=args.holdout)
        with staged_directory(out, args.force) as staging:
            write_model_files(staging, trained)
            if not args.no_plots:
                from kvark_ros.tools.plots import plot_training
                plots = [out / path.relative_to(staging) for path in plot_training(robot, trained, segments,
                                                                                   staging)]
    print(f"[train] model written to {out}", flush=True)
    for path in plots:
        print(f"[train] plot {path}", flush=True)
    return 0
