"""``kvark benchmark``: every observer on the same simulated data, the way the papers compare them.

Simulates contact-free training bags (optimised excitation) and test bags (payload, contact,
collision), trains the residual models, replays every observer (the oracle gets the plant
file) and writes ``results.json`` (``{"scenarios": {NAME: <metrics.json>}}``) and ``report.md``
with tables in the spirit of paper v2 Tables III, IV, V, VII, VIII and IX. With ``--augment`` it
also runs the model-gap workflow (``kvark diagnose`` on the training bags), trains on the augmented
model and replays ``AUGMENTED_OBSERVERS`` again: ``results.json`` gains ``"augmented"``.

The replays are ``kvark evaluate``'s tasks (one per test bag × observer) on a local Dask cluster, one worker
process per core, with the saved model; each scenario's metrics.json, report.md and plots are then written
here, from the observers' outputs the tasks return.

The output directory is built beside ``--out`` and swapped in whole at the end (``staged_directory``); an existing
non-empty one is replaced only with ``--force``, and then its bags are reused (hard-linked into the new output).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from kvark_ros.core.config import ConfigError, EstimatorConfig, default_config_path, load_config, parse_observers
from kvark_ros.core.files import check_output, staged_directory, write_text_atomically
from kvark_ros.core.estimation.model_store import TrainedModel, save_model
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.core.learning.training import HOLDOUT, train_model
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.acceptance import COVERAGE_RANGE, ORACLE_LIMIT, RMSE_LIMIT
from kvark_ros.tools.evaluate import Setup, dask_client, decoded, evaluate_bags, loaded, merge
from kvark_ros.tools.sim_bags import (AUGMENTED_OBSERVERS, FULL, QUICK, TEST_SCENARIOS, BenchmarkPlan, reuse_bags,
                                      simulate_bags, training_clocks)
from kvark_ros.tools.report import metrics_table
from kvark_ros.tools.train import add_residual_inputs_option

if TYPE_CHECKING:
    from distributed import Client

    from kvark_ros.cli import SubParsers

ABLATIONS = ("kf", "kmp_kf", "kmp_kf_ewma", "kmp_kf_nis", "kvark")
PAPER_RATIOS = {"gpadkf": 0.59, "gmr_gp": 0.66, "nnadkf": 0.75}   # v2 Table IX, external ground truth
# The robots differ from their URDFs the way real ones do (link inertia, tool, stiction, drifts): a residual
# in q̇ alone cannot look perfect there. `--plant kvark_ros/sim/plants/<robot>_default.yaml`: friction only, the
# plant `kvark simulate` uses by default.
DEFAULT_PLANT = "realistic"


RMSE_LIMITS = (("momentum", RMSE_LIMIT), ("kf", RMSE_LIMIT), ("oracle", ORACLE_LIMIT))   # ≤ limit × the other's
VECTOR_TOLERANCE = 0.05            # |vector coverage95 − 0.95|


def acceptance(scenarios: Mapping[str, Any]) -> list[str]:
    """The acceptance checks on the simulated plants, as lines that say pass or FAIL with the figures:
    K-VARK's RMSE against ``RMSE_LIMITS``, its coverage95 pooled and per joint in ``COVERAGE_RANGE``, its vector
    coverage95 within ``VECTOR_TOLERANCE`` of 0.95, its mean 95 % interval score no worse than kf's
    (``metrics.interval_score``), and its contact flag (no onset missed)."""
    lines = []
    low, high = COVERAGE_RANGE
    for name in TEST_SCENARIOS:
        observers = scenarios.get(name, {}).get("observers", {})
        if "kvark" not in observers:
            continue
        kvark = observers["kvark"]
        for other, limit in RMSE_LIMITS:
            if other in observers:
                ratio = kvark["joint_rmse_mean"] / observers[other]["joint_rmse_mean"]
                lines.append(f"- {name}: K-VARK / {other} joint RMSE = {ratio:.2f} (≤ {limit}: "
                             f"{'pass' if ratio <= limit else 'FAIL'})")
        coverage, per_joint = kvark.get("coverage95"), kvark.get("coverage95_per_joint")
        if coverage is not None:
            ok = low <= coverage <= high
            lines.append(f"- {name}: K-VARK coverage95 = {coverage:.3f} ({low}-{high}: {'pass' if ok else 'FAIL'})")
        if per_joint:
            outside = [j + 1 for j, value in enumerate(per_joint) if not low <= value <= high]
            lines.append(f"- {name}: K-VARK coverage95 per joint {min(per_joint):.3f}-{max(per_joint):.3f} "
                         f"({low}-{high}: {'pass' if not outside else 'FAIL, joints ' + str(outside)})")
        vector = kvark.get("vector_coverage95")
        if vector is not None:
            ok = abs(vector - 0.95) <= VECTOR_TOLERANCE
            lines.append(f"- {name}: K-VARK vector coverage95 = {vector:.3f} (0.95 ± {VECTOR_TOLERANCE}: "
                         f"{'pass' if ok else 'FAIL'})")
        score, kf_score = kvark.get("interval_score95"), observers.get("kf", {}).get("interval_score95")
        if score is not None and kf_score is not None:
            lines.append(f"- {name}: K-VARK mean interval score (95 %) = {score:.3f} N·m, kf's {kf_score:.3f} "
                         f"(no worse: {'pass' if score <= kf_score else 'FAIL'})")
        contact = kvark.get("contact") or {}
        if contact.get("onsets"):
            delays = ", ".join(f"{1e3 * d:.0f}" for d in contact.get("detection_delay") or [])
            missed = contact.get("missed_onsets", 0)
            lines.append(f"- {name}: K-VARK contact flag: {contact['onsets'] - missed} of {contact['onsets']} "
                         f"onsets after {delays or '–'} ms ({'pass' if not missed else 'FAIL'}: none missed)")
    return lines


def write_report(out: Path, results: Mapping[str, Any], training: Mapping[str, Any], robot: str,
                 plan: BenchmarkPlan, seconds: float) -> None:
    """report.md with the papers' kinds of tables."""
    scenarios = results["scenarios"]
    text = [f"# kvark benchmark: {robot}", "",
            f"Training: {len(plan.train_seeds)} × {plan.train_duration:g} s excitation bags, started "
            f"{', '.join(f'{clock:.0f}' for clock in training_clocks(len(plan.train_seeds)))} s after power-on "
            f"(the drifts' phases spread); tests: {plan.test_duration:g} s each, started at a time drawn from the "
            f"seed. Total {seconds / 60:.1f} min.", "",
            "## Residual models on held-out training samples (cf. v2 Table III)", "",
            "| model | " + " | ".join(f"joint {j + 1}" for j in range(len(training["held_out_rmse"]))) + " |",
            "|---|" + "---|" * len(training["held_out_rmse"])]
    for name, rmse in training.get("held_out_rmse_by_model", {"kmp": training["held_out_rmse"]}).items():
        text.append(f"| {name} | " + " | ".join(f"{v:.3f}" for v in rmse) + " |")
    for name, metrics in scenarios.items():
        text += ["", f"## {name} (ground truth: {metrics['ground_truth']}; cf. v2 Tables IV-V)", "",
                 metrics_table(metrics["observers"])]
    text += ["", "## Ablations, joint RMSE in N·m (cf. v2 Tables VII-VIII)", "",
             "| scenario | " + " | ".join(ABLATIONS) + " | measured order (best first) |",
             "|---|" + "---|" * (len(ABLATIONS) + 1)]
    for name, metrics in scenarios.items():
        values = {a: metrics["observers"][a]["joint_rmse_mean"] for a in ABLATIONS if a in metrics["observers"]}
        order = " < ".join(sorted(values, key=values.get))
        text.append(f"| {name} | " + " | ".join(f"{values.get(a, float('nan')):.4f}" for a in ABLATIONS)
                    + f" | {order} |")
    text += ["", "## K-VARK against the learned baselines (cf. v2 Table IX)", "",
             "| scenario | " + " | ".join(f"K-VARK / {b} (paper {r})" for b, r in PAPER_RATIOS.items()) + " |",
             "|---|" + "---|" * len(PAPER_RATIOS)]
    for name, metrics in scenarios.items():
        obs = metrics["observers"]
        cells = [f"{obs['kvark']['joint_rmse_mean'] / obs[b]['joint_rmse_mean']:.2f}" if b in obs and "kvark" in obs
                 else "–" for b in PAPER_RATIOS]
        text.append(f"| {name} | " + " | ".join(cells) + " |")
    if "augmented" in results:
        text += ["", augmentation_section(results)]
    text += ["", "## Acceptance checks", ""] + acceptance(scenarios)
    text += ["", "Per-scenario reports and plots: " + ", ".join(f"[{n}]({n}/report.md)" for n in scenarios)]
    write_text_atomically(out / "report.md", "\n".join(text) + "\n")


def augmentation_section(results: Mapping[str, Any]) -> str:
    """Joint RMSE on the nominal and on the augmented model (the augmentation's effect)."""
    augmented = results["augmented"]
    lines = ["## Model augmentation (kvark diagnose on the training bags, docs/method.md §8)", "",
             f"Effects found: {', '.join(augmented['effects']) or 'none'}; held-out gap "
             f"{augmented['gap_before']:.4f} → {augmented['gap_after']:.4f} N·m.", "",
             "| scenario | observer | nominal model | augmented model | change |", "|---|---|---|---|---|"]
    for name, metrics in augmented["scenarios"].items():
        for observer, values in metrics["observers"].items():
            before = results["scenarios"][name]["observers"].get(observer, {}).get("joint_rmse_mean")
            after = values["joint_rmse_mean"]
            change = f"{after / before - 1:+.1%}" if before else "–"
            lines.append(f"| {name} | {observer} | {before if before is None else f'{before:.4f}'} | "
                         f"{after:.4f} | {change} |")
    return "\n".join(lines)


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "benchmark", help="simulate, train and compare every observer (writes results.json and report.md)",
        description="Simulate training bags (excitation) and test bags (payload, contact, collision), train, "
                    "replay every observer and write DIR/results.json and DIR/report.md with tables like the "
                    "papers'. The training bags start evenly spread over the simulator's first half hour after "
                    "power-on (cold to warm, the drifting offsets at spread phases). Bags are kept under DIR/bags "
                    "and reused on a rerun with --force. DIR is written whole: an existing non-empty DIR is replaced "
                    "only with --force.")
    parser.add_argument("--robot", choices=("panda", "ur5"), help="simulated robot (default panda)")
    parser.add_argument("--out", required=True, help="output directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole once the new output is complete (its bags are reused)")
    parser.add_argument("--quick", action="store_true", help="less data: finishes in a few minutes")
    parser.add_argument("--seed", type=int, default=0, help="offset of every simulation seed (default 0); with "
                                                            "--population, the population's seed")
    parser.add_argument("--population", type=int, metavar="N",
                        help="draw N simulated robots (Panda, UR5 and UR10 classes, each with its own plant, rate and "
                             "payload; kvark_ros/sim/population.py), train and diagnose each on its own free motion, "
                             "test on its payload, contact and collision scenes; report the distributions per arm "
                             "class (one Dask task per robot); conflicts with --robot, --plant and --real")
    parser.add_argument("--observers", default="all", help="comma-separated observers or 'all' (default)")
    parser.add_argument("--plant", help="simulate this plant file instead of "
                                        "kvark_ros/sim/plants/<robot>_realistic.yaml (link inertia and tool errors, "
                                        "stiction, drifts; <robot>_default.yaml is friction only). Delete DIR/bags "
                                        "when changing it: bags are reused")
    parser.add_argument("--augment", action="store_true",
                        help=f"also diagnose the training bags, train on the augmented model and replay "
                             f"{', '.join(AUGMENTED_OBSERVERS)} with it (report section 'Model augmentation')")
    real = parser.add_argument_group(
        "real recording", "--real BAG: train on the first part of a contact-free recording of a real robot and "
                          "report every observer's false τ_ext, coverage of zero and false contacts on the rest, "
                          "on the nominal and on the diagnosed (augmented) model; no simulation")
    real.add_argument("--real", metavar="BAG", help="the contact-free recording (joint states with efforts, "
                                                  "optionally commands)")
    real.add_argument("--config", help="estimator config (default: config/<robot>.yaml)")
    real.add_argument("--train-share", type=float, default=0.7, help="first share of the time to train on "
                                                                      "(default 0.7)")
    real.add_argument("--trim", nargs=2, type=float, default=(0.0, 0.0), metavar=("START", "END"),
                      help="drop the first START and the last END seconds of the recording first (a start-up, "
                           "a stop; default 0 0)")
    real.add_argument("--rate", type=float, default=500.0,
                      help="keep every k-th sample for about this rate, Hz (default 500; 0: as recorded)")
    real.add_argument("--pushes", type=float, default=0.0, metavar="NEWTONS",
                      help="also judge the held-out part with known pushes of this force superposed on it (τ_m less "
                           "Jᵀ F: a stiffly position-controlled arm; 1 s holds, one every 3 s, along the wrench axes "
                           "in turn), augmented model: τ_ext RMSE during and after the pushes, contact delay "
                           "(default 0: off; e.g. 40)")
    add_residual_inputs_option(real, f"the last {HOLDOUT:.0%} of the training part, in both trainings")
    real.add_argument("--no-baselines", action="store_true", help="skip the learned baselines (faster)")
    real.add_argument("--no-plots", action="store_true",
                      help="skip the figures, the held-out part's and the diagnosis' (report.md and the JSON only)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.population is not None:
        from kvark_ros.tools.population_benchmark import check_arguments, run_population
        check_arguments(args)
        check_output(args.out, args.force)
        return run_population(args)
    if args.pushes and not args.real:
        raise ConfigError(f"--pushes {args.pushes:g} superposes pushes on a real recording: it needs --real BAG (the "
                          "simulated scenes have their own contacts)")
    args.robot = args.robot or "panda"
    check_output(args.out, args.force, (args.real, args.config))
    if args.real:
        from kvark_ros.tools.real_benchmark import run_real
        return run_real(args)
    started = time.perf_counter()
    plan = QUICK if args.quick else FULL

    def log(line: str) -> None:
        print(line, flush=True)

    config = load_config(default_config_path(args.robot))
    from kvark_ros.sim.plant import PLANT_DIR, load_plant
    plant_path = Path(args.plant) if args.plant else PLANT_DIR / f"{args.robot}_{DEFAULT_PLANT}.yaml"
    load_plant(plant_path, config.n_joints)      # a bad plant file fails here, not in the simulation or the oracle
    with staged_directory(args.out, args.force) as out:
        reuse_bags(Path(args.out) / "bags", out / "bags")
        results, trained = simulated_benchmark(args, config, plan, plant_path, out, log)
        write_text_atomically(out / "results.json", json.dumps(results, indent=2))
        write_report(out, results, trained.info, args.robot, plan, time.perf_counter() - started)
    for line in acceptance(results["scenarios"]):
        log(line)
    if args.augment:
        log(augmentation_section(results))
    log(f"[benchmark] wrote {args.out}/results.json and {args.out}/report.md in "
        f"{(time.perf_counter() - started) / 60:.1f} min")
    return 0


def simulated_benchmark(args: argparse.Namespace, config: EstimatorConfig, plan: BenchmarkPlan, plant_path: Path,
                        out: Path, log) -> tuple[dict[str, Any], TrainedModel]:
    """Simulate, train, replay every observer into ``out``; (results.json's content, the trained model)."""
    train_bags, test_bags = simulate_bags(args.robot, plan, out / "bags", args.seed, log, plant_path)
    robot = RobotModel.from_config(config)
    segments = [read_inputs(bag, config)[1] for bag in train_bags]
    log(f"[benchmark] training on {len(train_bags)} bags (nominal model)")
    trained = train_model(robot, config.robot, segments, seed=args.seed, log=log,
                          info={"bags": [bag.name for bag in train_bags]}, settings=config.filter)
    save_model(out / "model", trained)
    observers = parse_observers(args.observers, with_oracle=True)
    setup = Setup(str(default_config_path(args.robot).resolve()), str((out / "model").resolve()),
                  plant=str(plant_path.resolve()))
    results: dict[str, Any] = {}
    with dask_client(None, None, len(test_bags) * len(observers), log) as client:
        results["scenarios"] = replay_scenarios(client, setup, test_bags, observers, out, log)
        if args.augment:
            results["augmented"] = augmented_run(config, robot, segments, test_bags, out, args.seed, log,
                                                 client, setup)
    return results, trained


def replay_scenarios(client: Client, setup: Setup, test_bags: Mapping[str, Path], observers: Sequence[str],
                     out: Path, log) -> dict[str, Any]:
    """Every observer on every test bag as ``kvark evaluate``'s tasks on ``client``'s cluster; then per scenario
    what ``kvark replay`` writes into ``out/<scenario>``: metrics.json, report.md and the plots, the latter drawn
    here from the observers' outputs the tasks return. Returns each scenario's metrics.json content."""
    from kvark_ros.tools.report import write_replay_report
    log(f"[benchmark] replaying {len(test_bags)} test bags × {len(observers)} observers")
    bags = [str(bag) for bag in test_bags.values()]
    tasks = evaluate_bags(client, setup, bags, observers, keep_runs=True, log=log)
    failed = next((task for task in tasks if task.error is not None), None)
    if failed is not None:
        raise RuntimeError(f"replay of {failed.bag} with {failed.observer} failed: {failed.error}")
    merged = merge(bags, observers, tasks)["bags"]
    runs = {(task.bag, task.observer): task.run for task in tasks}
    robot = loaded(setup)[2]
    scenarios = {}
    for scenario, bag in test_bags.items():
        metrics = {**merged[str(bag)], "bag": f"{bag.parent.name}/{bag.name}"}     # relative to the output
        inputs, truth, _ = decoded(setup, str(bag))
        (out / scenario).mkdir(parents=True, exist_ok=True)
        write_text_atomically(out / scenario / "metrics.json", json.dumps(metrics, indent=2))
        write_replay_report(out / scenario, metrics, robot, inputs, truth, [runs[str(bag), name] for name in observers])
        scenarios[scenario] = metrics
    return scenarios


def augmented_run(config: EstimatorConfig, nominal: RobotModel, segments: list, test_bags: Mapping[str, Path],
                  out: Path, seed: int, log, client: Client, setup: Setup) -> dict[str, Any]:
    """Diagnose the training recordings on the ``nominal`` model, train on the augmented model (saved to
    ``out/model_augmented``), replay the test bags with it on ``client``'s cluster."""
    from kvark_ros.gap.diagnose import train_on_diagnosis
    log("[benchmark] diagnosing the training bags, training on the augmented model")
    _, summary = train_on_diagnosis(config, nominal, segments, out, baselines=False, seed=seed, log=log)
    augmented = replace(setup, model=str((out / "model_augmented").resolve()), plant=None)
    scenarios = replay_scenarios(client, augmented, test_bags, AUGMENTED_OBSERVERS, out / "augmented", log)
    return {**summary, "scenarios": scenarios}

