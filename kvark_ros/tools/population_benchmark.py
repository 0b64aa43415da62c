"""``kvark benchmark --population N --seed S``: K-VARK on a population of simulated robots nobody tuned for.

Robot i of population S is ``kvark_ros.sim.population.draw_robot(i, S)`` (Panda-, UR5- and UR10-class arms, each
with its own plant). Each robot is one Dask task on ``kvark evaluate``'s engine (``dask_client``: a local cluster,
one worker process per core, pinned to its core): simulate its free-motion training bags and its payload, contact
and collision test bags (``sim_bags.simulate_bags``), train on the nominal model, diagnose and train on the
augmented model (``train_on_diagnosis``, as ``benchmark --augment``), and replay kvark, kf, momentum and the oracle
(which gets the robot's plant file) on the nominal model and kvark, kf, momentum on the augmented one
(``evaluate_task``, the task ``kvark evaluate`` runs), and diagnose its payload scene against the augmented model
(``flange_mass``: is the new load named a payload, of the drawn mass?). The figures are then pooled into
distributions over robots × scenes ("cells"): median, 90th percentile (the value 90 % of the cells do better than)
and worst, per arm class and pooled (coverage also over the joint samples in motion alone), and checked against
``acceptance_lines`` (and the contact flag's delay from the static band, the payload's mass, the effects against
their priors). ``results.json`` and ``report.md`` go into --out (``staged_directory``), each robot's bags,
plant, models and log under ``robots/<arm>_<index>``.
"""
from __future__ import annotations

import argparse
import json
import os
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

from kvark_ros.core.config import ConfigError
from kvark_ros.core.files import staged_directory, write_text_atomically
from kvark_ros.tools.acceptance import (acceptance_lines, cell, contact_delay_lines, distribution, flange_mass_line,
                                        prior_line, tally)
from kvark_ros.tools.sim_bags import AUGMENTED_OBSERVERS, TEST_SCENARIOS, BenchmarkPlan

if TYPE_CHECKING:
    from kvark_ros.sim.population import PopulationRobot

NOMINAL_OBSERVERS = ("kvark", "kf", "momentum", "oracle")
# Data per robot. Full: `--population 6 --seed 7` took 412 s on 2 cores (load 0.8; 11.2 min for seed 1001 with other
# jobs at load 4-6: a 500 Hz robot ~330 s, a 100/125 Hz one ~100 s); quick: `--population 3 --seed 1000` 2.3 min.
FULL = BenchmarkPlan(train_seeds=(11, 12, 13), train_duration=15.0, test_duration=10.0)
QUICK = BenchmarkPlan(train_seeds=(11, 12), train_duration=10.0, test_duration=8.0)
SEED_STRIDE = 100000        # simulation seeds of robot i of population S: S·SEED_STRIDE + 200·i + …
CONTACT_KEYS = ("onsets", "detection_delay_from_band", "within_band_onsets", "missed_beyond_band")


def _figures(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The figures kept per observer and scene: RMSE, coverage, the interval score and the contact flag's onsets
    counted from the static band (``tools.metrics.contact_metrics``)."""
    contact = metrics.get("contact") or {}
    return {**{key: metrics.get(key) for key in ("joint_rmse_mean", "joint_rmse", "coverage95", "coverage95_moving",
                                                 "coverage95_per_joint", "interval_score95")},
            "contact": {key: contact.get(key) for key in CONTACT_KEYS}}


def _pin_to_core() -> None:
    """Pin this Dask worker process to one core (by worker name), so training fits here, one joint after the
    other (``joint_workers`` sees one core): a worker process may not start processes of its own."""
    if not hasattr(os, "sched_setaffinity"):
        return
    try:
        from distributed import get_worker
        name = get_worker().name
    except (ImportError, ValueError):
        return
    cores = sorted(os.sched_getaffinity(0))
    index = name if isinstance(name, int) else sum(map(ord, str(name)))
    os.sched_setaffinity(0, {cores[index % len(cores)]})


def run_robot(robot: PopulationRobot, plan: BenchmarkPlan, folder: str) -> dict[str, Any]:
    """The whole pipeline for one robot (a Dask task): simulate, train, diagnose, replay; its figures per scene.

    ``folder``: the robot's own directory (absolute); its log goes to ``folder/log.txt``."""
    import yaml

    from kvark_ros.core.config import default_config_path, load_config
    from kvark_ros.core.estimation.model_store import save_model
    from kvark_ros.core.estimation.robot_model import RobotModel
    from kvark_ros.core.learning.training import train_model
    from kvark_ros.gap.diagnose import train_on_diagnosis
    from kvark_ros.gap.known_load import KnownLoad
    from kvark_ros.io.recorded_inputs import read_inputs
    from kvark_ros.tools.sim_bags import simulate_bags, simulate_known_load
    from kvark_ros.tools.evaluate import Setup, evaluate_task

    _pin_to_core()
    started = time.perf_counter()
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(f"{time.perf_counter() - started:7.1f} s {line}")

    plant_path = out / "plant.yaml"
    plant_path.write_text(f"# {robot.description}\n" + yaml.safe_dump(robot.plant, sort_keys=False))
    (out / "payload.yaml").write_text(yaml.safe_dump(robot.payload, sort_keys=False))
    sim_seed = robot.seed * SEED_STRIDE + 200 * robot.index
    try:
        train_bags, test_bags = simulate_bags(robot.setup, plan, out / "bags", sim_seed, log, plant_path,
                                              {"payload": robot.payload_plant()})
        config_path = default_config_path(robot.setup).resolve()
        config = load_config(config_path)
        nominal = RobotModel.from_config(config)
        segments = [read_inputs(bag, config)[1] for bag in train_bags]
        trained = train_model(nominal, config.robot, segments, baselines=False, seed=sim_seed, log=log, jobs=1,
                              info={"bags": [bag.name for bag in train_bags]}, settings=config.filter)
        save_model(out / "model", trained)
        setup = Setup(str(config_path), str((out / "model").resolve()), plant=str(plant_path.resolve()))
        scenes: dict[str, Any] = {name: {"nominal": {}, "augmented": {}} for name in TEST_SCENARIOS}
        for name, bag in test_bags.items():
            for observer in NOMINAL_OBSERVERS:
                scenes[name]["nominal"][observer] = _figures(evaluate_task(setup, str(bag.resolve()), observer).metrics)
        augmentation: dict[str, Any] = {}
        known = None
        if robot.known_load is not None:    # motor-current arms: the drive gains calibrated with a weighed mass
            bag = simulate_known_load(robot.setup, plan, out / "bags", sim_seed, log, robot.known_load_plant())
            known = KnownLoad(robot.known_load["mass"], None, [read_inputs(bag, config)[1]],
                              f"{robot.known_load['mass']:g} kg on {bag.name}")
        try:
            _, augmentation = train_on_diagnosis(config, nominal, segments, out, baselines=False, seed=sim_seed,
                                                 log=log, known_load=known)
            augmentation["drive_gains"]["true"] = robot.plant["drive_gain"]
            augmented = Setup(str(config_path), str((out / "model_augmented").resolve()))
            for name, bag in test_bags.items():
                for observer in AUGMENTED_OBSERVERS:
                    scenes[name]["augmented"][observer] = _figures(
                        evaluate_task(augmented, str(bag.resolve()), observer).metrics)
            augmentation["flange_mass"] = flange_mass(config, out, test_bags["payload"], robot.payload_kg, log)
            augmentation["flange_mass"]["known_load"] = known is not None
        except Exception as exc:       # a diagnosis that fails leaves the nominal figures standing, and says why
            augmentation = {"error": f"{type(exc).__name__}: {exc}"}
            log(f"[population] diagnosis failed: {augmentation['error']}\n{traceback.format_exc()}")
    finally:
        (out / "log.txt").write_text("\n".join(map(str, lines)) + "\n")
    return {"robot": {"index": robot.index, "arm": robot.arm, "rate_hz": robot.rate_hz,
                      "payload_kg": robot.payload_kg, "description": robot.description, "label": robot.label,
                      "plant": robot.plant, "payload": robot.payload, "known_load": robot.known_load},
            "augmentation": augmentation, "scenes": scenes, "seconds": round(time.perf_counter() - started, 1)}


def flange_mass(config: Any, folder: Path, payload_bag: Path, true_mass: float,
                log: Callable[[str], None]) -> dict[str, Any]:
    """``kvark diagnose --against`` the robot's diagnosed model on its payload scene: whether the new load is named
    a payload, and its mass change at the flange (kg, the identifiable combination, ``gap.plausibility``) with its
    95 % half-width against the drawn payload's mass. The diagnosis goes to ``folder/payload_diagnosis``."""
    from kvark_ros.core.estimation.augmentation import load_augmentation
    from kvark_ros.core.estimation.robot_model import RobotModel
    from kvark_ros.gap.diagnose import diagnose
    from kvark_ros.gap.diagnosis_report import write_outputs
    from kvark_ros.gap.effects import Priors
    from kvark_ros.gap.plausibility import prior_summary
    from kvark_ros.io.recorded_inputs import read_inputs

    base = load_augmentation(folder / "diagnosis" / "augmentation.yaml", config.joint_names)
    robot = RobotModel.from_config(config, base)
    result = diagnose(robot, [read_inputs(payload_bag, config)[1]], log=log,
                      priors=Priors(torque_measurement=config.torque_measurement))
    write_outputs(result, robot, folder / "payload_diagnosis", config.robot, plots=False)
    named = [effect for effect in result.result["effects"] if effect["name"] == "payload"]
    mass = named[0]["parameters"]["mass_change"] if named else None
    return {"true_kg": float(true_mass), "named": bool(named), "mass_kg": mass,
            "ci95_kg": named[0]["ci95"].get("mass") if named else None,
            "relative_error": None if mass is None else abs(mass - true_mass) / true_mass,
            "effects": [effect["name"] for effect in result.result["effects"]],
            "warnings": len(result.result["warnings"]), "priors": prior_summary(result.result)}


def cells(robots: Sequence[Mapping[str, Any]], arm: str | None = None) -> list[dict[str, Any]]:
    """One row per robot × scene (of arm class ``arm``; None: every robot): the observers' figures, kvark's on the
    augmented model as ``kvark_aug`` (and kf/momentum as ``kf_aug``/``momentum_aug``) where the diagnosis ran."""
    rows = []
    for result in robots:
        if arm is not None and result["robot"]["arm"] != arm:
            continue
        for scene, models in result["scenes"].items():
            row: dict[str, Any] = {"robot": result["robot"]["label"], "arm": result["robot"]["arm"], "scene": scene}
            for observer, figures in models.get("nominal", {}).items():
                row[observer] = figures
            for observer, figures in models.get("augmented", {}).items():
                row[f"{observer}_aug"] = figures
            rows.append(row)
    return rows


def _value(row: Mapping[str, Any], observer: str, key: str = "joint_rmse_mean") -> float | None:
    entry = row.get(observer)
    return None if entry is None else entry.get(key)


def summary(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Distributions over the cells: each observer's joint RMSE (N·m), kvark's and kf's mean 95 % interval score
    (N·m) and kvark's coverage95, pooled and per joint."""
    out: dict[str, dict[str, Any]] = {}
    for observer in ("kvark", "kvark_aug", "kf", "kf_aug", "momentum", "momentum_aug", "oracle"):
        out[f"{observer} RMSE"] = distribution([_value(row, observer) for row in rows])
    for observer in ("kvark", "kvark_aug", "kf", "kf_aug"):
        out[f"{observer} interval score"] = distribution([_value(row, observer, "interval_score95") for row in rows])
    for observer in ("kvark", "kvark_aug"):
        out[f"{observer} coverage95"] = distribution([_value(row, observer, "coverage95") for row in rows], False)
        out[f"{observer} coverage95 moving"] = distribution(
            [_value(row, observer, "coverage95_moving") for row in rows], False)
        out[f"{observer} coverage95 per joint"] = distribution(
            [v for row in rows for v in (_value(row, observer, "coverage95_per_joint") or [])], False)
    return out


def aggregate(robots: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per arm class (in order of appearance) and pooled: the cells' distributions and the acceptance lines."""
    from kvark_ros.sim.population import ARM_CLASSES
    groups: dict[str, Any] = {}
    present = [arm for arm in ARM_CLASSES if any(r["robot"]["arm"] == arm for r in robots)]
    for group in (*present, "pooled"):
        rows = cells(robots, None if group == "pooled" else group)
        members = [r for r in robots if group == "pooled" or r["robot"]["arm"] == group]
        lines = [*acceptance_lines(rows, group), *contact_delay_lines(rows, group),
                 *flange_mass_line(members, group), *prior_line(members, group)]
        groups[group] = {"robots": len({row["robot"] for row in rows}), "cells": len(rows),
                         "distributions": summary(rows), "acceptance": [*lines, tally(lines)]}
    return groups


def distribution_table(groups: Mapping[str, Any]) -> list[str]:
    """Markdown: per group, median / p90 / worst of every figure."""
    lines = ["| group | figure | median | p90 | worst | cells |", "|---|---|---|---|---|---|"]
    for group, entry in groups.items():
        for figure, dist in entry["distributions"].items():
            decimals = 3 if "coverage" in figure else 4
            lines.append(f"| {group} | {figure} | {cell(dist['median'], decimals)} | {cell(dist['p90'], decimals)} "
                         f"| {cell(dist['worst'], decimals)} | {dist['count']} |")
    return lines


def _gains(record: Mapping[str, Any] | None) -> str:
    """A robot's drive gains as its calibration found them: measured with the known load (each ± its 95 %
    half-width, the drawn gain after it), or unidentified (free motion, within ± the prior)."""
    if not record:
        return "–"
    if record.get("calibrated_with") is None:
        return f"unidentified (±{record['prior']:.0%})"
    true = record.get("true") or [float("nan")] * len(record["gain"])
    return ", ".join(f"{g:.3f} ± {h:.3f} ({t:.3f})" if ok else f"– ({t:.3f})"
                     for g, h, ok, t in zip(record["gain"], record["ci95"], record["identified"], true))


def write_report(out: Path, results: Mapping[str, Any]) -> None:
    """report.md: the robots, the distributions per arm class and pooled, every cell, the acceptance lines."""
    plan = results["plan"]
    text = [f"# kvark benchmark --population {len(results['robots'])} --seed {results['seed']}", "",
            f"Per robot: {plan['train_recordings']} × {plan['train_duration']:g} s training recordings (free "
            f"motion), payload, contact and collision scenes of {plan['test_duration']:g} s each; trained, diagnosed "
            f"and replayed on its own data. {results['workers']} worker(s), {results['seconds'] / 60:.1f} min.",
            "RMSE: joint RMSE (mean over joints), N·m; `_aug`: on the diagnosed (augmented) model. p90: the value "
            "90 % of the cells do better than (for coverage the 10th percentile).", "", "## Robots", "",
            "| robot | plant | effects named by the diagnosis | held-out gap (N·m) | drive gains ± 95 % (drawn) | "
            "payload scene against the diagnosed model: named (kg ± 95 %, drawn kg) | time (s) |",
            "|---|---|---|---|---|---|---|"]
    for result in results["robots"]:
        augmentation = result["augmentation"]
        effects = ", ".join(augmentation.get("effects", [])) or augmentation.get("error", "none")
        gap = (f"{augmentation['gap_before']:.3f} → {augmentation['gap_after']:.3f}" if "gap_before" in augmentation
               else "–")
        record = augmentation.get("flange_mass")
        payload = ("–" if record is None else f"{', '.join(record['effects']) or 'nothing'} "
                   f"({cell(record['mass_kg'], 2)} ± {cell(record['ci95_kg'], 2)}, {record['true_kg']:.2f})")
        text.append(f"| {result['robot']['label']} | {result['robot']['description']} | {effects} | {gap} | "
                    f"{_gains(augmentation.get('drive_gains'))} | {payload} | {result['seconds']:.0f} |")
    text += ["", "## Distributions over robots × scenes", ""] + distribution_table(results["groups"])
    text += ["", "## Every cell, joint RMSE (N·m) and coverage95", "",
             "| robot | scene | kvark | kvark_aug | kf | kf_aug | momentum | oracle | cov95 kvark | cov95 kvark_aug |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in cells(results["robots"]):
        rmse = " | ".join(cell(_value(row, name), 4)
                          for name in ("kvark", "kvark_aug", "kf", "kf_aug", "momentum", "oracle"))
        text.append(f"| {row['robot']} | {row['scene']} | {rmse} | {cell(_value(row, 'kvark', 'coverage95'), 3)} | "
                    f"{cell(_value(row, 'kvark_aug', 'coverage95'), 3)} |")
    text += ["", "## Acceptance checks", ""] + [line for entry in results["groups"].values()
                                               for line in entry["acceptance"]]
    write_text_atomically(out / "report.md", "\n".join(text) + "\n")


def check_arguments(args: argparse.Namespace) -> None:
    """One-line errors for options --population cannot take."""
    if args.population < 1:
        raise ConfigError(f"--population {args.population}: give at least 1 robot")
    if args.real:
        raise ConfigError("--population simulates its robots; it conflicts with --real (a recording): use one")
    if args.robot is not None:
        raise ConfigError("--population draws its robots (Panda, UR5 and UR10 classes); it conflicts with --robot")
    if args.plant:
        raise ConfigError("--population draws each robot's plant; it conflicts with --plant")
    if args.seed < 0:
        raise ConfigError(f"--seed {args.seed}: give a seed >= 0")


def run_population(args: argparse.Namespace, log: Callable[[str], None] = print) -> int:
    """``kvark benchmark --population N --seed S``."""
    from distributed import as_completed

    from kvark_ros.sim.population import draw_population
    from kvark_ros.tools.evaluate import dask_client
    check_arguments(args)
    started = time.perf_counter()
    plan = QUICK if args.quick else FULL
    robots = draw_population(args.population, args.seed)
    for robot in robots:
        log(f"[population] {robot.label}: {robot.description}")
    with staged_directory(args.out, args.force) as out:
        results: list[dict[str, Any]] = []
        failed: list[str] = []
        with dask_client(None, None, len(robots), log) as client:
            workers = len(client.scheduler_info()["workers"])
            futures = {client.submit(run_robot, robot, plan, str((out / "robots" / f"{robot.arm}_{robot.index}")
                                                                  .resolve()), pure=False): robot
                       for robot in robots}
            for done, future in enumerate(as_completed(futures), start=1):
                robot = futures[future]
                if future.status == "error":
                    failed.append(f"{robot.label}: {type(future.exception()).__name__}: {future.exception()}")
                    log(f"[population] {done}/{len(robots)} {robot.label} FAILED: {failed[-1]}")
                    continue
                result = future.result()
                future.release()
                results.append(result)
                log(f"[population] {done}/{len(robots)} {robot.arm} #{robot.index} ({robot.rate_hz:g} Hz) done in "
                    f"{result['seconds']:.0f} s")
        results.sort(key=lambda result: result["robot"]["index"])
        payload = {"seed": args.seed, "workers": workers, "seconds": round(time.perf_counter() - started, 1),
                   "plan": {"train_recordings": len(plan.train_seeds), "train_duration": plan.train_duration,
                            "test_duration": plan.test_duration},
                   "robots": results, "failed": failed, "groups": aggregate(results)}
        write_text_atomically(out / "results.json", json.dumps(payload, indent=2))
        write_report(out, payload)
    for line in distribution_table(payload["groups"]):
        log(line)
    for entry in payload["groups"].values():
        for line in entry["acceptance"]:
            log(line)
    log(f"[population] wrote {args.out}/results.json and {args.out}/report.md in "
        f"{(time.perf_counter() - started) / 60:.1f} min")
    return 1 if failed else 0
