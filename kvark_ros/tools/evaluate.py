"""``kvark evaluate``: many bags × observers at once on a Dask cluster, merged into one table.

Every bag × observer is one task, run by a worker process of a Dask ``distributed`` cluster: by default a
local one (one worker per core, one thread each, BLAS one thread), or the running scheduler ``--scheduler``
names. A task computes exactly what ``kvark replay --no-plots`` writes into metrics.json for that bag and
observer (the same ``read_inputs``, ``ground_truth``, ``run_observer`` and ``observer_metrics``; only the timing
figures ``us_per_step`` and ``decode_seconds`` differ from run to run). Tasks carry paths, not arrays: a worker
reads the bag itself and loads the config and model once, into a cache of its own keyed by the files' paths and
modification times (a long-lived worker picks up a retrained model). A task that fails (a corrupt or missing bag:
``BagError``) becomes an error entry of the table; the others still run.

Writes DIR/results.json (``{"bags": {BAG: <replay's metrics.json for that bag>}, "summary": {OBSERVER: means over
the bags}}``; a bag's failed tasks under ``errors``) and DIR/report.md (one row per bag × observer).
dask and distributed are imported only here, inside the functions that use them.
"""
from __future__ import annotations

import argparse
import glob
import json
import logging
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from kvark_ros.core.config import (
    OBSERVER_NAMES,
    ConfigError,
    EstimatorConfig,
    default_config_path,
    load_config,
    parse_observers,
)
from kvark_ros.core.files import check_output, staged_directory, write_text_atomically
from kvark_ros.core.estimation.inputs import EstimatorInputs
from kvark_ros.core.estimation.model_checks import measured_rate, model_warnings
from kvark_ros.core.estimation.model_store import MODEL_FILE, TrainedModel, load_model
from kvark_ros.core.estimation.observers import ResidualPredictor, make_observer
from kvark_ros.core.estimation.robot_model import RobotModel, urdf_sha256
from kvark_ros.io import BagError
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.tools.metrics import in_motion, observer_metrics, static_band
from kvark_ros.tools.replay import GroundTruth, ObserverRun, bag_fields, ground_truth, plant_oracle, run_observer

if TYPE_CHECKING:
    from distributed import Client

    from kvark_ros.cli import SubParsers

TRUTHS = {"bag": "auto", "zero": "zero"}     # --ground-truth -> replay's ground-truth kind (no reference bag here)
BLAS_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
CONNECT_TIMEOUT = 10.0     # s to reach a --scheduler, and for a worker to join it
CACHED_BAGS = 2            # decoded bags a worker keeps: tasks run bag after bag, so the next one rarely needs more
# results.json's summary and report.md's columns: (key path in metrics.json's observer entry, header, decimals)
FIGURES = ((("joint_rmse_mean",), "joint RMSE (N·m)", 4), (("force_rmse_mean",), "force RMSE (N)", 3),
           (("coverage95",), "coverage95", 3), (("contact", "false_contact_share"), "false contact share", 3),
           (("contact", "detection_delay_mean"), "contact delay (s)", 3), (("us_per_step",), "µs/step", 0))


@dataclass(frozen=True)
class Setup:
    """What every task needs, as paths its worker opens: the config file, the model directory, the ground truth
    (a ``TRUTHS`` key) and a simulator plant file for the oracle (or None). Paths are absolute, so a worker
    started elsewhere (a cluster on a shared file system) finds them."""

    config: str
    model: str
    truth: str = "bag"
    plant: str | None = None


@dataclass(frozen=True)
class TaskResult:
    """One bag × observer: metrics.json's per-bag fields and the observer's entry, or the error that stopped it;
    ``run``: the observer's outputs when asked for (the benchmark draws its plots from them)."""

    bag: str
    observer: str
    fields: dict[str, Any] | None
    metrics: dict[str, Any] | None
    error: str | None = None
    run: ObserverRun | None = None


def _version(path: str | None) -> tuple:
    """(inode, size, modification time) of a file, or of a directory and its entries; () if missing. Part of the
    cache keys: a worker that outlives a retrained model or a rewritten bag reads the new one."""
    try:
        paths = [path] + (sorted(entry.path for entry in os.scandir(path)) if os.path.isdir(path) else [])
        return tuple((status.st_ino, status.st_size, status.st_mtime_ns) for status in map(os.stat, paths))
    except (OSError, TypeError):        # missing (the reader says so), or no path (no plant file)
        return ()


@lru_cache(maxsize=2)
def _loaded(setup: Setup, version: tuple) -> tuple[EstimatorConfig, TrainedModel, RobotModel,
                                                   ResidualPredictor | None]:
    config = load_config(setup.config)
    trained = load_model(setup.model, config.joint_names, urdf_sha256(config.urdf))
    return config, trained, RobotModel.from_config(config, trained.augmentation), plant_oracle(config, setup.plant)


def _setup_version(setup: Setup) -> tuple:
    return tuple(_version(path) for path in (setup.config, str(Path(setup.model) / MODEL_FILE), setup.plant))


def loaded(setup: Setup) -> tuple[EstimatorConfig, TrainedModel, RobotModel, ResidualPredictor | None]:
    """Config, model, robot model and oracle of ``setup``, loaded once per process (per worker)."""
    return _loaded(setup, _setup_version(setup))


@lru_cache(maxsize=CACHED_BAGS)
def _decoded(setup: Setup, bag: str, version: tuple) -> tuple[EstimatorInputs, GroundTruth | None, dict[str, Any]]:
    config, trained, robot, _ = loaded(setup)
    started = time.perf_counter()
    run, inputs = read_inputs(bag, config)
    if len(inputs) < 2:
        raise BagError(f"{bag}: fewer than two usable samples; check that joint_states and effort_commands overlap")
    truth = ground_truth(robot, config, run, inputs, None, TRUTHS[setup.truth])
    warnings = model_warnings(trained, config.robot, measured_rate(inputs.stamp), inputs.simulated)
    return inputs, truth, bag_fields(inputs, truth, trained, warnings, time.perf_counter() - started)


def decoded(setup: Setup, bag: str) -> tuple[EstimatorInputs, GroundTruth | None, dict[str, Any]]:
    """The bag's estimator inputs, its ground truth (None: the bag has none) and metrics.json's per-bag fields
    (replay's, without ``bag`` and ``observers``), decoded once per process for the tasks that follow."""
    return _decoded(setup, bag, (_setup_version(setup), _version(bag)))


def evaluate_task(setup: Setup, bag: str, observer: str, keep_run: bool = False) -> TaskResult:
    """Run ``observer`` over ``bag``: the figures ``kvark replay --no-plots`` writes for them (a Dask task)."""
    config, trained, _, oracle = loaded(setup)
    inputs, truth, fields = decoded(setup, bag)
    result = run_observer(config, trained, inputs, observer, oracle,
                          truth_tau=None if truth is None else truth.tau_ext)
    moving = in_motion(inputs.qd, config.filter.stiction_velocity)
    return TaskResult(bag, observer, fields,
                      observer_metrics(result, truth, inputs.stamp, static_band(trained), moving),
                      run=result if keep_run else None)


def local_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@contextmanager
def dask_client(scheduler: str | None, workers: int | None, tasks: int, log: Callable[[str], None]) -> Iterator[Client]:
    """A Dask client: of the running scheduler at ``scheduler``, or of a local cluster of ``workers`` processes
    (default one per core, at most one per task) with one thread each and BLAS limited to one thread;
    ``ConfigError`` when Dask is not installed."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ConfigError(f"kvark evaluate runs on Dask, which is not installed here ({exc}); install the pinned "
                          "versions with `pip install dask==2026.8.0 distributed==2026.8.0`, or replay bags one by "
                          "one with `kvark replay`") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, ValueError, TypeError) as exc:
            raise ConfigError(f"--scheduler {scheduler}: no Dask scheduler reached ({exc}); start one with "
                              "`dask scheduler` or leave out --scheduler for a local cluster") from None
        with client:
            try:
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
            except TimeoutError:
                raise ConfigError(f"--scheduler {scheduler}: the scheduler has no worker after "
                                  f"{CONNECT_TIMEOUT:g} s; start one with `dask worker {scheduler}`") from None
            log(f"[evaluate] scheduler {scheduler}: {len(client.scheduler_info()['workers'])} worker(s)")
            yield client
        return
    count = max(1, min(workers or local_cores(), tasks))
    with _environment(BLAS_ENV):     # BLAS reads its thread count when it loads: set before the workers start
        cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        log(f"[evaluate] local cluster: {count} worker process(es), one thread each")
        yield client


@contextmanager
def _environment(variables: Mapping[str, str]) -> Iterator[None]:
    """``variables`` in os.environ while the block runs (processes started in it inherit them), then as before."""
    before = {name: os.environ.get(name) for name in variables}
    os.environ.update(variables)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def evaluate_bags(client: Client, setup: Setup, bags: Sequence[str], observers: Sequence[str],
                  keep_runs: bool = False, log: Callable[[str], None] = print) -> list[TaskResult]:
    """Every bag × observer as a task on ``client``'s cluster (given the bag's absolute path), one progress line
    each as they finish; a failed task's result carries its error. Submitted bag after bag, so a worker decodes a
    bag once for the observers it runs on it."""
    from distributed import as_completed
    started = time.perf_counter()
    futures = {client.submit(evaluate_task, setup, os.path.abspath(bag), name, keep_runs, pure=False): (bag, name)
               for bag in bags for name in observers}
    finished = []
    for done, future in enumerate(as_completed(futures), start=1):
        bag, name = futures[future]
        if future.status == "error":
            exc = future.exception()
            result = TaskResult(bag, name, None, None, f"{type(exc).__name__}: {exc}")
            figure = f"error: {result.error}"
        else:
            result = replace(future.result(), bag=bag)      # the bag as given, not the path the worker opened
            rmse = result.metrics.get("joint_rmse_mean")
            figure = f"joint RMSE {rmse:.4f} N·m" if rmse is not None else f"{result.metrics['estimates']} estimates"
        future.release()
        finished.append(result)
        log(f"[evaluate] {done}/{len(futures)} {bag} {name}: {figure} ({time.perf_counter() - started:.1f} s)")
    return finished


def _figure(entry: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    """The value at ``path`` in a metrics entry (None where a level is missing or None)."""
    for key in path:
        entry = entry.get(key) if isinstance(entry, Mapping) else None
    return entry


def merge(bags: Sequence[str], observers: Sequence[str], tasks: Sequence[TaskResult]) -> dict[str, Any]:
    """results.json: per bag replay's metrics.json (observers in the asked order, failed ones under ``errors``),
    and per observer the mean of each ``FIGURES`` figure over the bags that have it."""
    by_key = {(task.bag, task.observer): task for task in tasks}
    results: dict[str, Any] = {"bags": {}, "summary": {}}
    for bag in bags:
        mine = [by_key[bag, name] for name in observers if (bag, name) in by_key]
        fields = next((task.fields for task in mine if task.fields is not None), {})
        entry = {"bag": bag, **fields, "observers": {t.observer: t.metrics for t in mine if t.error is None}}
        errors = {task.observer: task.error for task in mine if task.error is not None}
        results["bags"][bag] = {**entry, "errors": errors} if errors else entry
    for name in observers:
        entries = [entry["observers"][name] for entry in results["bags"].values() if name in entry["observers"]]
        summary: dict[str, Any] = {"bags": len(entries), "failed": len(bags) - len(entries)}
        for path, _, _ in FIGURES:
            values = [value for value in (_figure(entry, path) for entry in entries) if value is not None]
            summary[path[-1]] = round(float(np.mean(values)), 6) if values else None
        results["summary"][name] = summary
    results["failed"] = sum(len(entry.get("errors", {})) for entry in results["bags"].values())
    return results


def _cell(value: Any, decimals: int) -> str:
    return "–" if value is None else f"{value:.{decimals}f}"


def write_report(out: Path, results: Mapping[str, Any], heading: Sequence[str]) -> None:
    """report.md: the summary per observer, then one row per bag × observer (errors in the row)."""
    headers = [header for _, header, _ in FIGURES]
    lines = ["# kvark evaluate", "", *heading, "", "## Mean over the bags", "",
             "| observer | bags | failed | " + " | ".join(headers) + " |", "|---|" + "---|" * (len(FIGURES) + 2)]
    for name, summary in results["summary"].items():
        lines.append(f"| {name} | {summary['bags']} | {summary['failed']} | "
                     + " | ".join(_cell(summary[path[-1]], decimals) for path, _, decimals in FIGURES) + " |")
    lines += ["", "## Every bag × observer", "", "| bag | ground truth | observer | " + " | ".join(headers) + " |",
              "|---|" + "---|" * (len(FIGURES) + 2)]
    for bag, entry in results["bags"].items():
        truth = entry.get("ground_truth", "–").split(" (")[0]
        for name, metrics in entry["observers"].items():
            lines.append(f"| {bag} | {truth} | {name} | "
                         + " | ".join(_cell(_figure(metrics, path), decimals) for path, _, decimals in FIGURES)
                         + " |")
        for name, error in entry.get("errors", {}).items():
            lines.append(f"| {bag} | {truth} | {name} | error: {error.replace('|', '/')} |"
                         + " |" * (len(FIGURES) - 1))
    write_text_atomically(out / "report.md", "\n".join(lines) + "\n")


def expand_bags(patterns: Sequence[str]) -> list[str]:
    """The bags the patterns match, each once, in order (sorted within a pattern); a pattern that matches nothing
    stays as it is, so its tasks report the missing bag."""
    bags: list[str] = []
    for pattern in patterns:
        for bag in sorted(glob.glob(pattern)) or [pattern]:
            if bag not in bags:
                bags.append(bag)
    return bags


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "evaluate", help="run many bags through observers on a Dask cluster; one table of every bag's metrics",
        description="Run every bag × observer as one task on a Dask cluster (a local one by default: one worker "
                    "process per core; or a running scheduler) with the figures `kvark replay --no-plots` writes, "
                    "and merge them into DIR/results.json and DIR/report.md. A bag that fails is an error row; the "
                    "others still finish, and the exit code is 1. An existing non-empty DIR is replaced only with "
                    "--force.")
    parser.add_argument("--bags", nargs="+", required=True, metavar="GLOB",
                        help="bags or glob patterns (quote them: 'bags/panda_*'); a pattern that matches nothing is "
                             "reported as a missing bag")
    parser.add_argument("--model", required=True, help="model directory")
    parser.add_argument("--config", help="estimator config YAML (default: config/<robot>.yaml of the model's robot)")
    parser.add_argument("--observers", default="kvark",
                        help=f"comma-separated observers or 'all' ({', '.join(OBSERVER_NAMES)}); default kvark")
    parser.add_argument("--ground-truth", choices=tuple(TRUTHS), default="bag",
                        help="true external torque: bag (default: the bag's /ground_truth topic, else its wrist "
                             "F/T, as replay's auto; a bag with neither gets no error figures) or zero (the robot "
                             "touched nothing: every estimate is error)")
    parser.add_argument("--plant", help="simulator plant file (needed by the oracle observer)")
    cluster = parser.add_mutually_exclusive_group()
    cluster.add_argument("--scheduler", metavar="ADDRESS",
                         help="a running Dask scheduler (tcp://host:8786) whose workers see the same paths; default: "
                              "a local cluster")
    cluster.add_argument("--workers", type=int, metavar="N",
                         help="worker processes of the local cluster (default: one per core)")
    parser.add_argument("--out", required=True, help="output directory (new or empty; see --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace an existing --out whole (once the new output is complete)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_output(args.out, args.force, (args.model, args.config))
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: give at least 1")
    config_path = args.config or default_config_path(load_model(args.model).robot)
    setup = Setup(os.path.abspath(config_path), os.path.abspath(args.model), args.ground_truth,
                  os.path.abspath(args.plant) if args.plant else None)
    config, trained, _, oracle = loaded(setup)      # a bad config, model or plant fails here, before any cluster
    observers = parse_observers(args.observers, oracle is not None and trained.augmentation is None)
    for name in observers:
        make_observer(name, trained, config.filter, oracle)
    source = trained.info.get("source") or ", ".join(
        str(bag.get("name", bag) if isinstance(bag, dict) else bag) for bag in trained.info.get("bags") or []) or "?"
    bags = expand_bags(args.bags)

    def log(line: str) -> None:
        print(line, flush=True)

    log(f"[evaluate] URDF {config.urdf}; config {config_path}; model {args.model}, trained on {source}")
    log(f"[evaluate] {len(bags)} bag(s) × {len(observers)} observer(s) = {len(bags) * len(observers)} tasks")
    started = time.perf_counter()
    with dask_client(args.scheduler, args.workers, len(bags) * len(observers), log) as client:
        workers = len(client.scheduler_info()["workers"])
        tasks = evaluate_bags(client, setup, bags, observers, log=log)
    seconds = time.perf_counter() - started
    results = merge(bags, observers, tasks)
    out = Path(args.out)
    where = f"the scheduler {args.scheduler}" if args.scheduler else "a local cluster"
    with staged_directory(out, args.force) as staging:
        write_text_atomically(staging / "results.json", json.dumps(results, indent=2))
        write_report(staging, results, [
            f"Model `{args.model}` (trained on {source}), config `{config_path}`, ground truth `{args.ground_truth}`: "
            f"{len(bags)} bag(s) × {len(observers)} observer(s) on {where} of {workers} worker(s) in {seconds:.1f} s.",
            "Each row is what `kvark replay --no-plots` writes into metrics.json for that bag and observer; "
            "means over the bags that have the figure (no ground truth: no error figures)."])
    for warning in sorted({w for entry in results["bags"].values() for w in entry.get("warnings", [])}):
        log(f"[evaluate] warning: {warning}")
    log(f"[evaluate] {len(tasks)} tasks in {seconds:.1f} s, {results['failed']} failed; wrote {out}/results.json "
        f"and report.md")
    return 1 if results["failed"] else 0
